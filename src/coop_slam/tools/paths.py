"""Where the user commands find the repository's own files (config, docs, scripts) and the shared
data next to it: one definition for every tool."""

from __future__ import annotations

import os

# The real path: catkin's workspace reaches the package through a symlink.
REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.realpath(__file__)), "..", "..", ".."))
CONFIG_DIR = os.path.join(REPO, "config")
SHARED_DATA = os.path.normpath(os.path.join(REPO, "..", "shared", "data"))
