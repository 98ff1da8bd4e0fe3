"""What a client's keyframe messages carry and when they go (``config/client.yaml`` section
``uplink``)."""

from __future__ import annotations

from dataclasses import dataclass

from ..config import require
from ..descriptors import DESCRIPTOR_BYTES
from ..wire.record import MAX_REF_KEYFRAMES

UPLINK_MODES = ("full", "pull")


@dataclass
class UplinkConfig:
    """What a client's keyframe messages carry (``config/client.yaml`` section ``uplink``)."""

    # Updates leave out what the keyframe saw when the server has it, and carry only the
    # observations that changed (false: every update in full, as a new keyframe).
    delta_updates: bool = True
    # A map point that moved less than this since it last went to the server is not sent
    # again with an update [m]; 0 = every point that moved at all.
    point_move_m: float = 0.002
    # full: every keyframe goes whole. pull (low-bandwidth mode, the server's pull.enabled): a
    # new keyframe goes as its place signature; whole when the server asks for it, and only
    # then its updates.
    mode: str = "full"
    # Full mode: a new keyframe waits this long before it goes [s of data time], and goes with
    # what local BA made of it meanwhile; one the client culls within it (most culled keyframes
    # are) never travels. 0 = at once.
    hold_new_s: float = 1.0
    # Full mode: the updates of a keyframe the server has go at most once per this long, the
    # latest of them [s of data time] (local BA moves every keyframe of its window after each new
    # keyframe). 0 = each as it comes.
    coalesce_updates_s: float = 1.0
    # Full mode: a keyframe leaves out the descriptors of keypoints observing a map point the
    # server has in another keyframe (it takes them there): a map point's descriptor travels
    # once. false: every keyframe carries all its descriptors.
    share_descriptors: bool = True
    # ... when the descriptor there differs from the keypoint's own in at most this many bits
    # (of 256): a map point's descriptor changes with the view, and matching across robots,
    # which the server does with them, needs them close to what the camera saw (docs/tuning.md).
    # 256: always.
    share_max_bits: int = 32
    # How many of the keyframes the server holds are searched for a new keyframe's map points:
    # its covisible ones first, then the newest.
    ref_keyframes: int = 32
    # The robot's radio budget in full mode [kB/s of data time]: every new keyframe's place
    # signature goes, and whole keyframes and updates only as far as the budget reaches, those
    # that show most the server has not seen first (coop_slam.uplink.budget); the server asks
    # for others whole when it recognises their place. 0 = no budget: every keyframe whole.
    budget_kBps: float = 50.0
    # ... and in pull mode (low-bandwidth): signatures go as far as it reaches; the rest stay on
    # the robot. Keyframes the server asks for always go. 0 = no budget.
    pull_budget_kBps: float = 5.0
    # A new keyframe the budget cannot afford now waits this long for it, then stays as it went
    # (its signature in full mode, nothing in pull mode) [s of data time]
    budget_defer_s: float = 2.0
    # Whole keyframes carry the keyframe's depth image (vo.dense) for the team's dense map and
    # occupancy grid, in full mode; in pull mode only if pull_depth_images (a low-bandwidth
    # radio rarely affords them: 5-20 kB each).
    depth_images: bool = True
    pull_depth_images: bool = False
    # Wall-clock seconds without a camera frame after which whatever is held goes (the camera
    # stopped, or the run ended).
    idle_flush_s: float = 2.0

    def sends_depth_images(self) -> bool:
        return self.depth_images and (self.mode == "full" or self.pull_depth_images)

    def validate(self) -> None:
        require(self.point_move_m >= 0, "uplink.point_move_m must be >= 0 [m]")
        require(self.mode in UPLINK_MODES, f"uplink.mode must be one of {UPLINK_MODES}")
        require(self.hold_new_s >= 0, "uplink.hold_new_s must be >= 0 [s]")
        require(self.coalesce_updates_s >= 0, "uplink.coalesce_updates_s must be >= 0 [s]")
        require(self.idle_flush_s > 0, "uplink.idle_flush_s must be > 0 [s]")
        require(self.budget_kBps >= 0, "uplink.budget_kBps must be >= 0 [kB/s]")
        require(self.pull_budget_kBps >= 0, "uplink.pull_budget_kBps must be >= 0 [kB/s]")
        require(self.budget_defer_s >= 0, "uplink.budget_defer_s must be >= 0 [s]")
        require(
            0 <= self.share_max_bits <= 8 * DESCRIPTOR_BYTES,
            f"uplink.share_max_bits must be in [0, {8 * DESCRIPTOR_BYTES}]",
        )
        require(
            1 <= self.ref_keyframes <= MAX_REF_KEYFRAMES,
            f"uplink.ref_keyframes must be in [1, {MAX_REF_KEYFRAMES}]",
        )
