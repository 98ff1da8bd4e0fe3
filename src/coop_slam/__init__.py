"""coop_slam: collaborative visual SLAM for robot teams.

The package is split into a pure core (numpy / OpenCV / GTSAM in, numpy out, no rospy) and a thin
ROS layer in :mod:`coop_slam.ros`. Every algorithm can be imported and tested without a ROS master.
"""

__version__ = "0.1.0"
