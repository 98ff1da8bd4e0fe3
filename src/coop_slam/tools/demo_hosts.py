"""``scripts/demo --hosts``: the run's team on hosts of its own (:mod:`.hosts`) -- the station
(ROS master, server, the player's conductor, a recorder of what the station publishes) and one host
per robot (its client, its camera's player, a recorder of what the robot publishes) -- each a
roslaunch of demo.launch inside its host, every node at its host's address.

Only what the team itself exchanges crosses the radio: keyframes and sightings up, corrections and
acknowledgements down (and what a viewer on the station asks for). The harness -- /clock, the
conductor's steps, recording -- runs on a network of its own or on the host itself, so a radio
outage stalls none of it, as a robot's own clock and camera would not stall.
"""

from __future__ import annotations

import ctypes
import os
import time
from dataclasses import dataclass, field

from .demo_launch import Master, System, start_launch
from .hosts import Hosts, HostsError, LinkConfig

MASTER_PORT = 11311  # the station's own namespace: nothing else listens there
CLONE_NEWNET = 0x40000000
# A robot's radio still carries its uplink when it sends more than this between two looks (half a
# second apart); idle, a robot sends well under 1 kB/s (log lines, TCP).
SENDING_BYTES = 1000


def with_arguments(launch_args: list[str], **overrides) -> list[str]:
    """``launch_args`` (``name:=value``) with ``overrides`` replacing or adding arguments."""
    out = [a for a in launch_args if a.split(":=", 1)[0] not in overrides]
    return out + [f"{k}:={v}" for k, v in overrides.items()]


def _setns(fd: int) -> None:
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.setns(fd, CLONE_NEWNET) != 0:
        reason = os.strerror(ctypes.get_errno())
        raise HostsError(f"cannot enter a host's network namespace: {reason}")


@dataclass
class HostsTeam:
    """A run's hosts, their outages and radio counters."""

    hosts: Hosts
    outages: list[tuple[int, float, float]]  # (robot, start s, end s) of data time
    say: object
    radio_start: dict[int, tuple[int, int]] = field(default_factory=dict)
    wall_start: float = 0.0
    _last_sent: dict[int, int] = field(default_factory=dict)
    down: set[int] = field(default_factory=set)
    events_done: set[tuple[int, float, bool]] = field(default_factory=set)
    _root_ns: int | None = None

    @classmethod
    def make(cls, args, robot_ids: list[int], say) -> "HostsTeam":
        """Make the hosts (raises :class:`HostsError` saying what is missing)."""
        bad = sorted({r for r, _, _ in args.outage} - set(robot_ids))
        if bad:
            raise HostsError(f"--outage: this run has robots {robot_ids}, not {bad}")
        hosts = Hosts(f"coop{os.getpid()}", robot_ids, LinkConfig(rate_kbit=args.link_rate))
        hosts.make()
        rate = f"{args.link_rate:g} kbit/s each way" if args.link_rate else "no rate limit"
        say(
            f"      hosts (network namespaces {hosts.prefix}_*): station "
            f"{hosts.station.radio_ip} (master, server), "
            + ", ".join(f"robot_{r} {h.radio_ip}" for r, h in hosts.robots.items())
            + f"; radio links: {rate}"
        )
        for r, start, end in args.outage:
            say(f"      outage: robot_{r}'s link down from {start:g} s to {end:g} s")
        return cls(hosts, list(args.outage), say)

    def master(self, out: str) -> Master:
        """The run's master on the station; the environment of the station's nodes."""
        uri = f"http://{self.hosts.station.radio_ip}:{MASTER_PORT}"
        env = {k: v for k, v in os.environ.items() if k != "ROS_HOSTNAME"}  # it beats ROS_IP
        env.update(
            ROS_MASTER_URI=uri,
            ROS_IP=self.hosts.station.radio_ip,
            ROS_LOG_DIR=os.path.join(out, "ros_log"),
        )
        os.environ.pop("ROS_HOSTNAME", None)
        os.environ.update(ROS_MASTER_URI=uri, ROS_IP=self.hosts.station.radio_ip)
        return Master(MASTER_PORT, uri, env)

    def start(self, master: Master, launch_args: list[str], out: str, topics) -> System:
        """One roslaunch per host: the station's first (it starts the master), then each robot's
        (waiting for the master). ``topics(where, robot)`` names what each host records."""
        station = self.hosts.station
        launches = [
            start_launch(
                ["-p", str(master.port)],
                with_arguments(
                    launch_args,
                    clients="false",
                    player_role="conductor",
                    harness_ip=station.harness_ip,
                    record_bag=os.path.join(out, "run.bag"),
                    record_topics=" ".join(topics("station", None)),
                ),
                os.path.join(out, "roslaunch.log"),
                master.env,
                wrapper=station.exec_prefix(),
            )
        ]
        for r, host in self.hosts.robots.items():
            launches.append(
                start_launch(
                    ["--wait"],
                    with_arguments(
                        launch_args,
                        only_robots=str(r),
                        server="false",
                        player_role="camera",
                        harness_ip=host.harness_ip,
                        harness_master_uri=f"http://{station.harness_ip}:{master.port}",
                        recorder_name=f"run_recorder_robot_{r}",
                        record_bag=os.path.join(out, f"run_robot_{r}.bag"),
                        record_topics=" ".join(topics("robot", r)),
                    ),
                    os.path.join(out, f"roslaunch_robot_{r}.log"),
                    dict(master.env, ROS_IP=host.radio_ip),
                    robot_id=r,
                    wrapper=host.exec_prefix(),
                )
            )
        return System(master, launches)

    def enter_station(self) -> None:
        """Move this process (its main thread, and every thread it starts from now on: rospy's)
        onto the station, where the master and the server are."""
        self._root_ns = os.open("/proc/self/ns/net", os.O_RDONLY)
        fd = os.open(f"/run/netns/{self.hosts.station.namespace}", os.O_RDONLY)
        try:
            _setns(fd)
        finally:
            os.close(fd)

    def count_from_now(self) -> None:
        self.radio_start = {r: self.hosts.radio_bytes(r) for r in self.hosts.robots}
        self.wall_start = time.monotonic()

    def sending(self) -> bool:
        """Whether a robot's radio still carries its uplink: it sent more than ``SENDING_BYTES``
        since the last call (the demo asks every half second)."""
        now = {r: self.hosts.radio_bytes(r)[0] for r in self.hosts.robots}
        last, self._last_sent = self._last_sent, now
        return any(now[r] - last.get(r, 0) > SENDING_BYTES for r in now)

    def say_radio(self, used: dict[int, tuple[int, int]], data_s: float) -> None:
        """What each radio carried, per second of data and of wall time: lock-step playback runs
        slower (or faster) than the data, and a link's rate limits wall time."""
        wall_s = time.monotonic() - self.wall_start
        for r, (sent, received) in used.items():
            self.say(
                f"      radio robot_{r}: {sent / 1e3:.0f} kB up, {received / 1e3:.0f} kB down: "
                f"{sent / 1e3 / max(data_s, 1e-9):.1f} / {received / 1e3 / max(data_s, 1e-9):.1f} "
                f"kB/s of data time, {sent / 1e3 / wall_s:.1f} / {received / 1e3 / wall_s:.1f} "
                f"kB/s of wall time ({data_s:.0f} s of data played in {wall_s:.0f} s)"
            )

    def poll(self, elapsed_s: float) -> None:
        """Take links down and up at their outages' data times."""
        for r, start, end in self.outages:
            for t, down in ((start, True), (end, False)):
                if elapsed_s >= t and (r, t, down) not in self.events_done:
                    self.events_done.add((r, t, down))
                    self._set(r, down, f"at {elapsed_s:.1f} s")

    def end_outages(self) -> None:
        """The data ended: every link comes back (what robots kept goes through now)."""
        for r in sorted(self.down):
            self._set(r, False, "after the last frame")

    def _set(self, robot_id: int, down: bool, when: str) -> None:
        self.hosts.outage(robot_id, down)
        (self.down.add if down else self.down.discard)(robot_id)
        self.say(f"      radio: robot_{robot_id}'s link {'down' if down else 'back'} {when}")

    def radio_used(self) -> dict[int, tuple[int, int]]:
        """Per robot: (sent, received) bytes on its radio interface since :meth:`count_from_now`."""
        out = {}
        for r in self.hosts.robots:
            tx, rx = self.hosts.radio_bytes(r)
            tx0, rx0 = self.radio_start.get(r, (0, 0))
            out[r] = (tx - tx0, rx - rx0)
        return out

    def close(self) -> None:
        """Back to this machine's own network, and remove the hosts (also after a failure)."""
        if self._root_ns is not None:
            try:
                _setns(self._root_ns)
            finally:
                os.close(self._root_ns)
                self._root_ns = None
        self.hosts.close()
