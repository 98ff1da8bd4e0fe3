"""The pure core logs with Python's ``logging`` (logger ``coop_slam``). Under rospy such records go
only to the node's log file; a user must see why a merge was accepted or refused on the console
and in ``/rosout`` (``rqt_console``). :func:`forward_core_logs` hands them to rospy's ``rosout``
logger, which does both, keeping each record's own file, line and function."""

from __future__ import annotations

import logging


class RospyHandler(logging.Handler):
    """Hands core records, prefixed with the node's name, to rospy's ``rosout`` logger."""

    def __init__(self, node_name: str):
        super().__init__()
        self.prefix = f"{node_name}: "

    def emit(self, record: logging.LogRecord) -> None:
        try:
            text = record.getMessage()
        except Exception:  # a malformed log call must not take a node down
            self.handleError(record)
            return
        forwarded = logging.makeLogRecord(record.__dict__)
        forwarded.msg, forwarded.args = self.prefix + text, None
        logging.getLogger("rosout").handle(forwarded)


def forward_core_logs(node_name: str, level: int = logging.INFO) -> None:
    """Forward the core's log records at ``level`` and above to rospy (once per process). Debug
    records stay out unless ``level`` says otherwise."""
    core = logging.getLogger("coop_slam")
    if any(isinstance(h, RospyHandler) for h in core.handlers):
        return
    core.addHandler(RospyHandler(node_name))
    core.setLevel(level)
    core.propagate = False  # the rosout logger writes them to the node's log file already
