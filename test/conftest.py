"""pytest setup: find the shared fakes in test/, and the package in src/ when no catkin workspace
is sourced (scripts/test sources .ws/devel, whose coop_slam also carries the generated messages)."""

import importlib.util
import os
import sys

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
if importlib.util.find_spec("coop_slam") is None:
    sys.path.insert(0, os.path.join(os.path.dirname(HERE), "src"))
