"""The pure core logs with Python's ``logging`` (logger ``coop_slam``). Under rospy such records go
only to the node's log file; a user must see why a merge was accepted or refused on the console
and in ``/rosout`` (``rqt_console``). :func:`forward_core_logs` sends them through rospy."""

from __future__ import annotations

import logging

import rospy

_LEVELS = (
    (logging.ERROR, rospy.logerr),
    (logging.WARNING, rospy.logwarn),
    (logging.INFO, rospy.loginfo),
)


class RospyHandler(logging.Handler):
    """A logging handler that logs through rospy (console and ``/rosout``)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = self.format(record)
        except Exception:  # a malformed log call must not take a node down
            self.handleError(record)
            return
        for level, log in _LEVELS:
            if record.levelno >= level:
                log(text)
                return
        rospy.logdebug(text)


def forward_core_logs(node_name: str, level: int = logging.INFO) -> None:
    """Forward the core's log records at ``level`` and above to rospy, prefixed with the node's
    name (once per process). Debug records stay out unless ``level`` says otherwise."""
    core = logging.getLogger("coop_slam")
    if any(isinstance(h, RospyHandler) for h in core.handlers):
        return
    handler = RospyHandler()
    handler.setFormatter(logging.Formatter(f"{node_name}: %(message)s"))
    core.addHandler(handler)
    core.setLevel(level)
    core.propagate = False  # rospy writes them to the node's log file already
