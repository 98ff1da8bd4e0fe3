"""Fault injection for ``scripts/demo --faults SPEC``: what the team map must survive.

SPEC is a comma-separated list of

- ``server-kill@T``: kill -9 the server T seconds (sim time) into the run; roslaunch restarts it
  and it resumes from its map file;
- ``client-kill:K@T``: kill -9 robot K's client at T s; it restarts in a new map segment;
- ``drop:P``: a radio relay between each client and the server drops a share P of the keyframe
  messages (the clients send them again).
"""

from __future__ import annotations

import os
import re
import signal
from dataclasses import dataclass, field

from ..errors import CoopSlamError


class FaultError(CoopSlamError):
    """A fault specification that cannot be run."""


@dataclass
class Kill:
    node: str  # "server" or "client"
    at_s: float  # seconds into the run (sim time)
    robot_id: int = 0  # client kills
    tried: bool = False
    done: bool = False  # the process was found and killed

    @property
    def label(self) -> str:
        who = "server" if self.node == "server" else f"client {self.robot_id}"
        return f"{who} killed at {self.at_s:g} s"


@dataclass
class Faults:
    kills: list[Kill] = field(default_factory=list)
    drop: float = 0.0
    spec: str = ""

    @property
    def any(self) -> bool:
        return bool(self.kills) or self.drop > 0

    def summary(self) -> dict:
        return {
            "spec": self.spec,
            "kills": [
                {"node": k.node, "robot": k.robot_id or None, "at_s": k.at_s, "done": k.done}
                for k in self.kills
            ],
            "drop": self.drop,
        }


_KILL = re.compile(r"^(server-kill|client-kill:(\d+))@([0-9.]+)$")
_DROP = re.compile(r"^drop:([0-9.]+)$")


def parse_faults(spec: str, robot_ids: list[int] | None = None) -> Faults:
    out = Faults(spec=spec)
    for item in (s.strip() for s in spec.split(",") if s.strip()):
        if m := _KILL.match(item):
            robot = int(m.group(2)) if m.group(2) else 0
            if robot_ids is not None and m.group(2) and robot not in robot_ids:
                raise FaultError(f"--faults {item}: this run has robots {robot_ids}")
            at_s = float(m.group(3))
            out.kills.append(Kill("client" if robot else "server", at_s, robot))
        elif m := _DROP.match(item):
            out.drop = float(m.group(1))
            if not 0.0 < out.drop < 1.0:
                raise FaultError(f"--faults {item}: the share dropped must be in (0, 1)")
        else:
            raise FaultError(
                f"--faults: cannot read '{item}'; use server-kill@T, client-kill:K@T or drop:P "
                "(e.g. server-kill@25,client-kill:2@30,drop:0.1)"
            )
    out.kills.sort(key=lambda k: k.at_s)
    return out


def _descendants(pid: int) -> list[int]:
    """Processes started (directly or not) by ``pid`` (Linux /proc)."""
    children: dict[int, list[int]] = {}
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            with open(f"/proc/{entry}/stat") as fh:
                ppid = int(fh.read().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        children.setdefault(ppid, []).append(int(entry))
    out, todo = [], [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def _cmdline(pid: int) -> list[str]:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return fh.read().decode(errors="replace").split("\0")
    except OSError:
        return []


def node_pids(launch_pid: int, name: str, namespace: str = "/") -> list[int]:
    """The processes of a ROS node roslaunch started (``__name:=name``; roslaunch passes the
    namespace in the environment, and names the node's log file ``<ns>-<name>-<n>.log``)."""
    ns = namespace.strip("/").replace("/", "-")
    prefix = f"{ns}-{name}-" if ns else f"{name}-"
    out = []
    for pid in _descendants(launch_pid):
        args = _cmdline(pid)
        logs = [os.path.basename(a.split(":=", 1)[1]) for a in args if a.startswith("__log:=")]
        if f"__name:={name}" in args and any(x.startswith(prefix) for x in logs):
            out.append(pid)
    return out


def kill_node(launch_pid: int, kill: Kill) -> str:
    """kill -9 the node of a fault; returns what was done."""
    ns = "/" if kill.node == "server" else f"/robot_{kill.robot_id}"
    pids = node_pids(launch_pid, kill.node, ns)
    if not pids:
        return f"{kill.label}: no such process found (not running?)"
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    kill.done = True
    return f"{kill.label} (kill -9, pid {', '.join(map(str, pids))}); roslaunch restarts it"
