"""Low-bandwidth mode's server side: which whole keyframes to ask the robots for.

In low-bandwidth mode (``uplink.mode: pull`` on the clients, ``pull.enabled`` on the server) a
robot sends each new keyframe as a :class:`~coop_slam.wire.record.PlaceSignature` (pose and
BoW vector, 2-3 kB) and its whole keyframe (50-60 kB) only when the server asks. The planner keeps
every signature in a BoW database of its own and runs place recognition on signatures as the
server does on keyframes (candidates scored against the query's covisible keyframes, temporal
consistency over consecutive queries); when a query has a consistent candidate -- another
robot's place (a merge, or a link inside a merged group) or the robot's own place seen long
before (a loop) -- it asks for both keyframes, the ones the server does not hold yet. The team
server then stitches them as any keyframes (its own consistency check is already done here).

Each robot has a budget of whole keyframes per minute (a token bucket), so the radio carries at
most that; a request not answered within ``timeout_s`` is given up (the robot may be gone or the
keyframe culled) and the keyframe may be asked for again later.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..bow.database import ConsistencyChecker, ConsistencyConfig, DatabaseConfig, KeyframeDatabase
from ..bow.vocabulary import l1_score
from ..config import require
from ..wire.record import PlaceSignature

RobotKey = tuple[int, int]  # (robot id, keyframe id): the pull planner works per robot


@dataclass
class PullConfig:
    """``config/server.yaml`` section ``pull``."""

    enabled: bool = False  # low-bandwidth mode: clients send place signatures (uplink.mode: pull)
    keyframes_per_min: float = 2.0  # whole keyframes asked of one robot per minute, on average
    burst: int = 2  # ... and at once (one place recognition: the query and its candidate)
    timeout_s: float = 5.0  # a request not answered in this long is given up [s]
    loop_min_keyframes: int = 30  # a robot's own place counts as a loop this many keyframes back
    # A candidate must look at least this alike (BoW score) as the query and the robot's previous
    # keyframe do: a whole keyframe costs 50-60 kB, so only views that resemble each other as
    # much as two neighbouring views of one place are worth asking for.
    min_score_ratio: float = 0.8
    # Where the server is not in low-bandwidth mode (a robot's radio budget sends signatures of
    # the keyframes it holds back), a whole keyframe is a second or so of a robot's budget, which
    # the robot charges it to: the floor is lower (0.8 lost the merge of the RedKitchen thirds at
    # 50 kB/s, issue #49's note), and a robot is asked for more keyframes per minute.
    budget_min_score_ratio: float = 0.7
    budget_keyframes_per_min: float = 12.0
    # Robots seen together (a marker sighting): their alike signatures match at once for this
    # long [s] (the rendezvous; otherwise place recognition's consistency over keyframes).
    rendezvous_window_s: float = 10.0

    def validate(self) -> None:
        require(self.keyframes_per_min > 0, "pull.keyframes_per_min must be > 0")
        require(self.burst >= 1, "pull.burst must be >= 1")
        require(self.timeout_s > 0, "pull.timeout_s must be > 0 [s]")
        require(self.loop_min_keyframes >= 1, "pull.loop_min_keyframes must be >= 1")
        require(self.min_score_ratio >= 0, "pull.min_score_ratio must be >= 0")
        require(self.budget_min_score_ratio >= 0, "pull.budget_min_score_ratio must be >= 0")
        require(self.budget_keyframes_per_min > 0, "pull.budget_keyframes_per_min must be > 0")
        require(self.rendezvous_window_s >= 0, "pull.rendezvous_window_s must be >= 0 [s]")


class PullPlanner:
    """Signatures in, requests for whole keyframes out (see the module docstring)."""

    def __init__(
        self,
        config: PullConfig,
        database: DatabaseConfig | None = None,
        min_consecutive: int = 2,
        same_group: Callable[[int, int], bool] | None = None,
    ):
        config.validate()
        self.config = config
        self.db = KeyframeDatabase(database or DatabaseConfig())
        self.consistency = ConsistencyChecker(ConsistencyConfig(min_consecutive=min_consecutive))
        self.same_group = same_group or (lambda a, b: a == b)
        self.held: set[RobotKey] = set()  # keyframes the server holds whole
        self.pending: dict[RobotKey, float] = {}  # asked for, not arrived yet: when asked
        self._tokens: dict[int, tuple[float, float]] = {}  # robot -> (tokens, at)
        self._out: dict[int, list[int]] = {}  # robot -> keyframe ids to ask for
        self.requested = 0  # keyframes asked for
        self.timeouts = 0  # requests given up
        self.over_budget = 0  # consistent candidates left because a robot's budget was spent
        self._last: dict[int, RobotKey] = {}  # robot -> its newest keyframe's key
        self._together: dict[tuple[int, int], float] = {}  # robot pair -> when seen together

    # --- inputs -----------------------------------------------------------------------------------
    def add(self, sig: PlaceSignature, now_s: float) -> list[RobotKey]:
        """One new keyframe's signature; returns the keyframes this asks for (maybe none)."""
        rec = sig.record
        return self.add_view(rec.robot_id, rec.keyframe_id, sig.bow, rec.covisible_ids, now_s)

    def add_view(self, robot: int, kf: int, bow, covisible_ids, now_s: float) -> list[RobotKey]:
        """A new keyframe's view: from its signature, or (a robot whose budget sends some whole,
        some as signatures) a whole keyframe the server holds, so that a signature can match it
        and a whole keyframe can find a signature; returns the keyframes this asks for."""
        self.expire(now_s)
        robot, kf = int(robot), int(kf)
        key = (robot, kf)
        if key in self.db:
            return []  # sent again (a restarted delivery), or asked for: nothing new
        covisible = [(robot, int(c)) for c in covisible_ids]
        # How alike two views of one place look here: the query and the robot's previous keyframe.
        previous = self._last.get(robot)
        floor = 0.0
        if previous is not None and previous in self.db:
            floor = self.config.min_score_ratio * l1_score(bow, self.db.bow(*previous))
        self._last[robot] = key
        self.db.add(robot, kf, bow, covisible)
        gap = self.config.loop_min_keyframes
        candidates = [
            c
            for c in self.db.query(bow, robot, kf, covisible, other_robots_only=False)
            if (c.key[0] != robot or abs(c.key[1] - kf) >= gap) and c.score >= floor
        ]
        consistent = set(self.consistency.check(robot, candidates, self.db))
        window = self.config.rendezvous_window_s
        partners = {b for (a, b), t in self._together.items() if a == robot and now_s - t <= window}
        consistent |= {c.key for c in candidates if c.key[0] in partners}
        # Another group's place first (a merge), then the best score.
        ranked = sorted(
            (c for c in candidates if c.key in consistent),
            key=lambda c: (self.same_group(robot, c.key[0]), -c.score),
        )
        for cand in ranked:
            want = [k for k in (key, cand.key) if k not in self.held and k not in self.pending]
            if not want:
                continue
            if self._ask(want, now_s):
                return want
        return []

    def ask_for_view(self, robot_id: int, bow, now_s: float) -> RobotKey | None:
        """A lost robot's view (server-assisted relocalization): the best-matching signature of
        the robots of its group. Asks for that keyframe when the server does not hold it (within
        the budget); returns its key while it is asked for, None when the server holds it (its
        own keyframes answer) or nothing matches."""
        self.expire(now_s)
        candidates = [
            c
            for c in self.db.query(bow, robot_id, 0, covisible=(), other_robots_only=False)
            if self.same_group(robot_id, c.key[0])
        ]
        if not candidates:
            return None
        best = max(candidates, key=lambda c: c.score).key
        if best in self.held:
            return None
        # A lost robot goes first: asked for even over its budget (later pulls wait the longer).
        if best in self.pending or self._ask([best], now_s, force=True):
            return best
        return None

    def seen_together(self, robot_a: int, robot_b: int, now_s: float) -> None:
        """Robots seen together (a marker sighting, a rendezvous request): for the next
        ``rendezvous_window_s`` their signatures alike enough count as a match at once, without
        waiting for consistency over consecutive keyframes (the sighting is the evidence)."""
        self._together[(int(robot_a), int(robot_b))] = now_s
        self._together[(int(robot_b), int(robot_a))] = now_s

    def _ask(self, want: list[RobotKey], now_s: float, force: bool = False) -> bool:
        """Ask for these keyframes if the robots' budgets allow all of them (``force``: in any
        case, the budgets going below zero)."""
        if not self._spend(want, now_s, force):
            self.over_budget += 1
            return False
        for k in want:
            self.pending[k] = now_s
            self._out.setdefault(k[0], []).append(k[1])
        self.requested += len(want)
        return True

    def hold(self, robot_id: int, keyframe_id: int) -> None:
        """The server now holds this keyframe whole."""
        key = (int(robot_id), int(keyframe_id))
        self.held.add(key)
        self.pending.pop(key, None)

    def remove(self, robot_id: int, keyframe_id: int) -> None:
        """The robot culled the keyframe."""
        key = (int(robot_id), int(keyframe_id))
        if key in self.db:
            self.db.remove(*key)
        self.held.discard(key)
        self.pending.pop(key, None)

    def holds(self, robot_id: int, keyframe_id: int) -> bool:
        return (int(robot_id), int(keyframe_id)) in self.held

    def stats(self) -> dict:
        """What the planner did: keyframes asked for, given up, held whole per robot, and
        consistent candidates left for lack of budget."""
        held: dict[str, int] = {}
        for robot, _ in self.held:
            held[str(robot)] = held.get(str(robot), 0) + 1
        return {
            "requested": self.requested,
            "timeouts": self.timeouts,
            "over_budget": self.over_budget,
            "held": held,
        }

    # --- outputs ----------------------------------------------------------------------------------
    def take_requests(self) -> dict[int, list[int]]:
        """Keyframe ids to ask each robot for now (each once)."""
        out, self._out = self._out, {}
        return out

    def expire(self, now_s: float) -> list[RobotKey]:
        """Requests older than ``timeout_s``, given up now (they may be asked for again)."""
        late = [k for k, t in self.pending.items() if now_s - t > self.config.timeout_s]
        for k in late:
            del self.pending[k]
        self.timeouts += len(late)
        return late

    def _spend(self, keys: list[RobotKey], now_s: float, force: bool = False) -> bool:
        """Take one token per keyframe from its robot's bucket, all or none."""
        rate = self.config.keyframes_per_min / 60.0
        burst = float(self.config.burst)
        need: dict[int, int] = {}
        for robot, _ in keys:
            need[robot] = need.get(robot, 0) + 1
        level = {}
        for robot, n in need.items():
            tokens, at = self._tokens.get(robot, (burst, now_s))
            tokens = min(burst, tokens + max(0.0, now_s - at) * rate)
            if tokens < n and not force:
                return False
            level[robot] = tokens - n
        for robot, tokens in level.items():
            self._tokens[robot] = (tokens, now_s)
        return True
