"""Hosts and radio links of a team on one machine, for ``scripts/demo --hosts``: one Linux network
namespace per host (the station: master and server; one per robot), each with two interfaces --
``radio0`` on the team's radio (shaped, outages, counted) and ``harness0`` on the harness's own
network (the player's clock and lock-step, which a field team does not have) -- joined by two
bridges in a switch namespace. Nothing is created in the caller's namespace; :meth:`Hosts.close`
removes everything (also after a failure), and the addresses exist only inside these namespaces.

A robot's link is rate-limited with ``tc tbf`` in both directions; an outage takes the robot's
switch port down (the robot keeps its address and routes, as behind a radio fade). Each host's
TCP gives up retransmitting late and retries often, so connections outlive an outage and resume
within a second of the link coming back. Delay and random loss need the kernel's ``netem``,
which not every kernel has (:func:`has_netem`).
"""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass, field

from ..config import require
from ..errors import CoopSlamError

RADIO_NET, HARNESS_NET = "10.77.0", "10.78.0"  # /24 each, only inside the namespaces made here
STATION = 0  # the station's host number (robots are 1..254)
# Fast recovery after an outage: retransmissions at most 1 s apart, and many of them (with only
# the first, the connection is given up during a longer outage).
TCP_SYSCTLS = {"net.ipv4.tcp_rto_max_ms": "1000", "net.ipv4.tcp_retries2": "100"}


class HostsError(CoopSlamError):
    """Hosts cannot be made here (not root, no iproute2, no namespaces) or a link setting is bad."""


@dataclass
class LinkConfig:
    """Every robot's radio link."""

    rate_kbit: float = 0.0  # rate limit in each direction [kbit/s]; 0 = unlimited
    burst_kb: float = 16.0  # tbf bucket [kB]
    latency_ms: float = 200.0  # tbf queue: packets waiting longer are dropped [ms]
    delay_ms: float = 0.0  # one-way delay [ms] (needs netem)
    loss: float = 0.0  # share of packets lost at random (needs netem)

    def validate(self) -> None:
        require(self.rate_kbit >= 0, "link rate must be >= 0 [kbit/s]")
        require(self.burst_kb > 0 and self.latency_ms > 0, "tbf burst and latency must be > 0")
        require(self.delay_ms >= 0, "link delay must be >= 0 [ms]")
        require(0 <= self.loss < 1, "link loss must be in [0, 1)")


def check_available() -> None:
    """Raise :class:`HostsError` saying what is missing to make hosts here."""
    if os.geteuid() != 0:
        raise HostsError("--hosts needs root (network namespaces and tc); run as root")
    for tool in ("ip", "tc"):
        if shutil.which(tool) is None and not os.path.exists(f"/usr/sbin/{tool}"):
            raise HostsError(f"--hosts needs '{tool}' (Debian package iproute2)")
    if not os.path.exists("/proc/self/ns/net"):
        raise HostsError("--hosts needs network namespaces (kernel CONFIG_NET_NS)")


def unavailable_reason() -> str:
    """Why hosts cannot be made here ("" when they can): what :func:`check_available` says."""
    try:
        check_available()
    except HostsError as exc:
        return str(exc)
    return ""


def has_netem() -> bool:
    """Whether this kernel has the netem qdisc (delay and loss)."""
    config = "/proc/config.gz"
    if os.path.exists(config):
        import gzip

        with gzip.open(config, "rt") as fh:
            return any(
                line.strip() in ("CONFIG_NET_SCH_NETEM=y", "CONFIG_NET_SCH_NETEM=m") for line in fh
            )
    return os.path.isdir("/sys/module/sch_netem")


def _run(*cmd: str) -> str:
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=30)
    except FileNotFoundError as exc:
        raise HostsError(f"{cmd[0]} not found: {exc}") from None
    except subprocess.CalledProcessError as exc:
        raise HostsError(f"'{' '.join(cmd)}' failed: {exc.stderr.strip()}") from None
    return out.stdout


@dataclass
class Host:
    """One host: its namespace, number (station 0, robot k) and addresses."""

    namespace: str
    number: int

    @property
    def radio_ip(self) -> str:
        return f"{RADIO_NET}.{self.number + 1}"

    @property
    def harness_ip(self) -> str:
        return f"{HARNESS_NET}.{self.number + 1}"

    def exec_prefix(self) -> list[str]:
        """Prepended to a command to run it on this host."""
        return ["ip", "netns", "exec", self.namespace]


@dataclass
class Hosts:
    """The station and robots' hosts of one run (:meth:`make`; :meth:`close` removes them)."""

    prefix: str
    robot_ids: list[int]
    link: LinkConfig = field(default_factory=LinkConfig)
    station: Host | None = None
    robots: dict[int, Host] = field(default_factory=dict)
    made: list[str] = field(default_factory=list)  # namespaces made, for close()

    @property
    def switch(self) -> str:
        return f"{self.prefix}_sw"

    def make(self) -> "Hosts":
        check_available()
        self.link.validate()
        if (self.link.delay_ms or self.link.loss) and not has_netem():
            raise HostsError(
                "link delay and loss need the kernel's netem qdisc, which this kernel does not "
                "have (CONFIG_NET_SCH_NETEM); use --link-rate, --outage and --faults drop:P"
            )
        bad = [r for r in self.robot_ids if not 1 <= r <= 253]
        if bad:
            raise HostsError(f"--hosts: robot ids must be 1..253, got {bad}")
        try:
            self._namespace(self.switch)
            for bridge in ("br_radio", "br_harness"):
                _run("ip", "-n", self.switch, "link", "add", bridge, "type", "bridge")
                _run("ip", "-n", self.switch, "link", "set", bridge, "up")
            self.station = self._host("station", STATION)
            self.robots = {r: self._host(f"robot{r}", r) for r in self.robot_ids}
            for r in self.robot_ids:
                self._shape(r)
        except BaseException:
            self.close()
            raise
        return self

    def _namespace(self, name: str) -> None:
        _run("ip", "netns", "add", name)
        self.made.append(name)
        _run("ip", "-n", name, "link", "set", "lo", "up")

    def _host(self, name: str, number: int) -> Host:
        host = Host(f"{self.prefix}_{name}", number)
        self._namespace(host.namespace)
        for net, dev, bridge, ip in (
            ("r", "radio0", "br_radio", host.radio_ip),
            ("h", "harness0", "br_harness", host.harness_ip),
        ):
            port = f"{net}{number}"
            _run("ip", "-n", self.switch, "link", "add", port, "type", "veth", "peer", "name", dev,
                 "netns", host.namespace)  # fmt: skip
            _run("ip", "-n", self.switch, "link", "set", port, "master", bridge, "up")
            _run("ip", "-n", host.namespace, "addr", "add", f"{ip}/24", "dev", dev)
            # One segment per packet: the counters then see every frame's headers, as a radio does.
            _run("ip", "-n", host.namespace, "link", "set", dev, "gso_max_segs", "1", "up")
        for key, value in TCP_SYSCTLS.items():
            if os.path.exists("/proc/sys/" + key.replace(".", "/")):
                _run(*host.exec_prefix(), "sysctl", "-qw", f"{key}={value}")
        return host

    def _shape(self, robot_id: int) -> None:
        """tbf (and netem) on the robot's side (uplink) and on its switch port (downlink)."""
        link = self.link
        if not (link.rate_kbit or link.delay_ms or link.loss):
            return
        for ns, dev in ((self.robots[robot_id].namespace, "radio0"), (self.switch, f"r{robot_id}")):
            for cmd in qdisc_commands(link, dev):
                _run("ip", "netns", "exec", ns, *cmd)

    def outage(self, robot_id: int, down: bool) -> None:
        """Take robot ``robot_id``'s radio link down (or bring it back)."""
        _run("ip", "-n", self.switch, "link", "set", f"r{robot_id}", "down" if down else "up")

    def radio_bytes(self, robot_id: int) -> tuple[int, int]:
        """(sent, received) bytes on robot ``robot_id``'s radio interface so far."""
        ns = self.robots[robot_id].namespace
        stats = "/sys/class/net/radio0/statistics"
        out = _run("ip", "netns", "exec", ns, "cat", f"{stats}/tx_bytes", f"{stats}/rx_bytes")
        tx, rx = (int(v) for v in out.split())
        return tx, rx

    def close(self) -> None:
        """Stop what still runs in the hosts and remove them (and with them links and qdiscs)."""
        for ns in reversed(self.made):
            try:
                pids = subprocess.run(
                    ["ip", "netns", "pids", ns], capture_output=True, text=True, timeout=10
                ).stdout.split()
            except (OSError, subprocess.SubprocessError):
                pids = []
            for pid in pids:
                if pid == str(os.getpid()):
                    continue  # the caller itself, still on a host
                try:
                    os.kill(int(pid), 9)
                except (ProcessLookupError, ValueError):
                    pass
            subprocess.run(["ip", "netns", "del", ns], capture_output=True, timeout=10)
        self.made.clear()


def qdisc_commands(link: LinkConfig, dev: str) -> list[list[str]]:
    """The tc commands shaping ``dev``: netem (delay, loss) at the root when asked for, tbf (rate)
    at the root or under it."""
    out = []
    parent = ["root"]
    if link.delay_ms or link.loss:
        netem = ["tc", "qdisc", "add", "dev", dev, "root", "handle", "1:", "netem"]
        if link.delay_ms:
            netem += ["delay", f"{link.delay_ms:g}ms"]
        if link.loss:
            netem += ["loss", f"{100 * link.loss:g}%"]
        out.append(netem)
        parent = ["parent", "1:"]
    if link.rate_kbit:
        out.append(
            ["tc", "qdisc", "add", "dev", dev, *parent, "handle", "2:", "tbf",
             "rate", f"{link.rate_kbit:g}kbit", "burst", f"{link.burst_kb:g}kb",
             "latency", f"{link.latency_ms:g}ms"]
        )  # fmt: skip
    return out
