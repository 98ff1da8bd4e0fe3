"""A robot's radio budget: a token bucket over data time that the uplink's planner asks before a
keyframe message goes, so a robot sends at most ``uplink.budget_kBps`` whatever its camera makes,
spread evenly rather than in bursts a radio would queue."""

from __future__ import annotations

KINDS = ("whole", "delta", "signature")


class RadioBudget:
    """Tokens (bytes) accrue at ``kBps`` per second of data time up to ``burst_s`` seconds'
    worth (half a second: a whole RGB-D keyframe may not fit, and then waits for a full bucket and
    leaves it in debt); a message goes when the tokens cover what a message of its kind has cost lately, and
    spends what it really cost (a message that must go -- one the server asked for -- may leave
    the bucket in debt, which later messages then wait out). ``kBps`` 0: no budget."""

    def __init__(self, kBps: float = 0.0, burst_s: float = 0.5):
        self.rate_Bps = 1000.0 * float(kBps)
        self.capacity = self.rate_Bps * float(burst_s)
        self.tokens = self.capacity
        self._t: float | None = None
        # What a message of each kind cost lately [bytes]; until one went, a full bucket
        self._cost = {kind: self.capacity for kind in KINDS}
        self._seen: set[str] = set()

    @property
    def limited(self) -> bool:
        return self.rate_Bps > 0

    def _refill(self, now_s: float) -> None:
        if self._t is not None and now_s > self._t:
            self.tokens = min(self.capacity, self.tokens + (now_s - self._t) * self.rate_Bps)
        if self._t is None or now_s > self._t:
            self._t = now_s

    def affords(self, kind: str, now_s: float) -> bool:
        """Whether a message of ``kind`` fits the budget at data time ``now_s``."""
        if not self.limited:
            return True
        self._refill(now_s)
        return self.tokens >= min(self._cost[kind], self.capacity)

    def spend(self, kind: str, nbytes: int) -> None:
        """A message of ``kind`` went: ``nbytes`` on the wire."""
        if not self.limited:
            return
        self.tokens -= nbytes
        if kind in self._seen:
            self._cost[kind] = 0.7 * self._cost[kind] + 0.3 * nbytes
        else:
            self._cost[kind] = float(nbytes)
            self._seen.add(kind)
