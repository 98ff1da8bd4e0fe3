"""The wire's plain messages (:mod:`coop_slam.wire.messages`) to and from the generated ROS
classes, field by field: the one place where what crosses the radio meets ROS."""

from __future__ import annotations

import dataclasses
import functools
import importlib
import typing

from ..wire import messages as wm


@functools.lru_cache(maxsize=None)
def ros_class(type_name: str):
    """The generated class of a ROS message type (``pkg/Name``)."""
    pkg, name = type_name.split("/")
    return getattr(importlib.import_module(f"{pkg}.msg"), name)


def ros_class_of(wire_cls: type):
    return ros_class(wm.ROS_TYPES[wire_cls])


@functools.lru_cache(maxsize=None)
def _hints(cls: type) -> dict:
    return typing.get_type_hints(cls)


def to_ros(obj):
    """The ROS message of a wire message (a new instance of its generated class)."""
    return _fill(ros_class_of(type(obj))(), obj)


def _fill(msg, obj):
    for f in dataclasses.fields(obj):
        value = getattr(obj, f.name)
        if isinstance(value, wm.Stamp):
            import genpy

            value = genpy.Time(value.secs, value.nsecs)
        elif dataclasses.is_dataclass(value):
            value = _fill(getattr(msg, f.name), value)
        elif (type(obj), f.name) in wm.LIST_TYPES:
            element = ros_class_of(wm.LIST_TYPES[(type(obj), f.name)])
            value = [_fill(element(), v) for v in value]
        setattr(msg, f.name, value)
    return msg


def from_ros(msg, wire_cls: type):
    """The wire message of class ``wire_cls`` of a ROS message (of its type, or any object with
    its fields)."""
    values = {}
    for name, hint in _hints(wire_cls).items():
        value = getattr(msg, name)
        if hint is wm.Stamp:
            value = wm.Stamp(int(value.secs), int(value.nsecs))
        elif dataclasses.is_dataclass(hint):
            value = from_ros(value, hint)
        elif (wire_cls, name) in wm.LIST_TYPES:
            value = [from_ros(v, wm.LIST_TYPES[(wire_cls, name)]) for v in value]
        elif isinstance(value, tuple):  # (ROS deserializes arrays as tuples)
            value = list(value)
        values[name] = value
    return wire_cls(**values)
