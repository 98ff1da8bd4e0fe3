"""The dense team map: per-keyframe depth images, small enough for a robot's radio, that the
server places by the team graph's current keyframe poses -- a voxel cloud of surfaces and a 2D
occupancy grid of the floor band, re-posed whenever the graph moves (nothing is fused into a
global volume, so a merge or loop closure never smears or doubles a wall).

- :mod:`.depth_image`: decimate a depth image and pack it into a blob for the wire / map file.
- :mod:`.keyframe_points`: a blob back-projected to points in its camera frame.
- :mod:`.dense_cloud`: keyframes' points placed by their poses, voxel-filtered.
- :mod:`.occupancy`: the floor band's 2D occupancy grid from placed keyframes.
- :mod:`.grid_files`: the grid as map_server's PGM + YAML.
"""
