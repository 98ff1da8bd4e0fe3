"""The launch files: one parameterized file per role, every argument used, and a robot named by its
id alone -- the server finds robot k under /robot_k, so no argument may rename it."""

import glob
import os
import re
import xml.etree.ElementTree as ET

import pytest

from helpers import REPO

LAUNCH = sorted(glob.glob(os.path.join(REPO, "launch", "*.launch")))


@pytest.mark.parametrize("path", LAUNCH, ids=[os.path.basename(p) for p in LAUNCH])
def test_every_launch_argument_is_used(path):
    text = open(path, encoding="utf-8").read()
    args = [a.get("name") for a in ET.fromstring(text).iter("arg") if a.get("value") is None]
    for name in args:
        assert re.search(
            rf"arg\(?\s*'?{name}'?\)|\$\(arg {name}\)", text
        ), f"{os.path.basename(path)} declares '{name}' but never uses it"


def test_a_client_is_named_by_its_robot_id_only():
    root = ET.parse(os.path.join(REPO, "launch", "client.launch")).getroot()
    args = {a.get("name") for a in root.iter("arg")}
    assert "robot_id" in args
    # An argument that renames the robot's namespace or frames would leave the server (which
    # subscribes /robot_k/keyframes and publishes /robot_k/correction) without it.
    assert not args & {"robot_name", "name", "ns", "namespace", "tf_prefix"}, args
    (group,) = root.iter("group")
    assert group.get("ns") == "robot_$(arg robot_id)"
