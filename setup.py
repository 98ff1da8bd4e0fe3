"""Python package setup for catkin (catkin_python_setup reads this)."""
from catkin_pkg.python_setup import generate_distutils_setup
from setuptools import setup

setup(**generate_distutils_setup(packages=["coop_slam", "coop_slam.datasets", "coop_slam.synthetic",
                                           "coop_slam.ros", "coop_slam.tools"],
                                 package_dir={"": "src"}))
