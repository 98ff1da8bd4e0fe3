"""Server-side team map: merged groups of robot maps and the transforms between them."""
