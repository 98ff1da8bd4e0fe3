"""coop_slam: collaborative visual SLAM for robot teams.

The package is split into a pure core (numpy / OpenCV / GTSAM in, numpy out, no rospy) and a thin
ROS layer in :mod:`coop_slam.ros`. Every algorithm can be imported and tested without a ROS master.
"""

import os as _os

__version__ = "0.1.0"

# Our dense algebra is small (6x6 normal equations, a few thousand Jacobian rows): one BLAS thread
# is faster, and a client's tracking and local-mapping threads must not fight over the cores
# (docs/tuning.md). Takes effect when
# coop_slam is imported before numpy, as in every coop_slam script; the user's setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
