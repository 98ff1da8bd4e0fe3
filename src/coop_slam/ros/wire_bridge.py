"""The wire's plain messages (:mod:`coop_slam.wire.messages`) to and from the generated ROS
classes, field by field: the one place where what crosses the radio meets ROS. Also the
keyframe messages' serializer for the client's uplink (:class:`RosSerializer`): the bytes rospy
publishes, made before a message is numbered and kept in the robot's spool."""

from __future__ import annotations

import dataclasses
import functools
import importlib
import io
import typing

from ..wire import messages as wm
from ..wire.codec import WireError


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
        if not hasattr(msg, name):  # a field added since it was recorded: its default
            continue
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


class RosSerializer:
    """A keyframe message as genpy serializes it (what rospy publishes), and back: the
    :class:`coop_slam.uplink.engine.Serializer` of the client node."""

    def __init__(self):
        self.ros_cls = ros_class(wm.ROS_TYPES[wm.KeyframeMessage])
        self.format_id = f"{self.ros_cls._type}:{self.ros_cls._md5sum}"

    def dumps(self, msg: wm.KeyframeMessage) -> bytes:
        buf = io.BytesIO()
        try:
            to_ros(msg).serialize(buf)
        except Exception as exc:  # genpy's struct.error, OverflowError, TypeError, ...
            why = str(exc).split(" when writing")[0][:300]  # genpy appends the whole message
            raise WireError(
                f"the {msg.kind_name} message of keyframe {msg.keyframe_id} cannot be serialized "
                f"as {self.ros_cls._type} ({type(exc).__name__}: {why}): a field beyond its type"
            ) from None
        return buf.getvalue()

    def loads(self, data: bytes) -> wm.KeyframeMessage:
        try:
            return from_ros(self.ros_cls().deserialize(data), wm.KeyframeMessage)
        except Exception as exc:  # a payload cut short or of another version
            raise WireError(f"a kept keyframe message does not deserialize: {exc}") from None
