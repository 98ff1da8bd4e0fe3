"""The player's bag mode: replays a rosbag's camera topics, in lock-step with the clients or in
real time, and drives /clock with the bag's time. A bag recorded by real robots keeps its
drivers' topic names: each camera (:mod:`coop_slam.bag_topics`) is published under the player's
names, which the clients subscribe to."""

from __future__ import annotations

import re
import time

import rospy
from rosgraph_msgs.msg import Clock
from std_msgs.msg import Bool

from ..bag_topics import bag_cameras, describe_drivers
from ..playback import PlaybackError
from .lockstep import FrameAcks, wait_for_consumers
from .player_config import PlayerConfig

# What the system itself publishes: a bag recorded on a running team may hold these, and replaying
# them would fight the live clients and server.
SYSTEM_OUTPUT_TOPICS = re.compile(
    r"^/(robot_\d+/(keyframes|keyframe_ack|frame_stats|correction|pose|path|local_map)"
    r"|team_map/.*|merge_events|server/.*|robot_sightings|player/.*|clock|rosout(_agg)?|tf)$"
)


class BagPlayer:
    """Replays a rosbag (the user's own recording, or one written by ``scripts/export_bag``) and
    drives /clock with the bag's time.

    Cameras go out under the player's topics, other topics keep their names; the system's own
    outputs in the bag are not replayed. In lock-step
    mode, robot k's next colour image waits until its client acknowledged the previous one on
    ``robot_k/frame_stats`` (other robots' messages keep flowing meanwhile); robots without a
    consumer, and everything when not in lock-step, play at ``rate`` x real time.
    """

    def __init__(self, cfg: PlayerConfig):
        import rosbag

        self.cfg = cfg
        try:
            self.bag = rosbag.Bag(cfg.bag)
        except (OSError, rosbag.ROSBagException) as exc:
            raise PlaybackError(f"cannot open bag {cfg.bag}: {exc}") from None
        self.clock = rospy.Publisher("/clock", Clock, queue_size=10)
        self.done = rospy.Publisher("~done", Bool, queue_size=1, latch=True)
        self.done.publish(Bool(False))
        self.pubs = {}
        for topic, info in self.bag.get_type_and_topic_info().topics.items():
            if SYSTEM_OUTPUT_TOPICS.match(topic):
                continue
            self.pubs[topic] = info.msg_type
        self.cameras = bag_cameras(self.pubs)
        self.robot_ids = [c.robot_id for c in self.cameras]
        if not self.robot_ids:
            raise PlaybackError(
                f"bag {cfg.bag} has no camera topics this player knows ({describe_drivers()}); "
                f"it has: {', '.join(sorted(self.pubs)) or 'nothing'}"
            )
        self.remap = {t: own for c in self.cameras for t, own in c.remap.items()}
        self.image_of = {c.image_topic: c.robot_id for c in self.cameras}  # bag topic -> robot
        for c in self.cameras:
            rospy.loginfo(
                "player: robot_%d: %s camera %s (%s topics)",
                c.robot_id,
                c.sensor,
                c.namespace or "/",
                c.driver.name,
            )
        self.acks = {rid: FrameAcks(f"robot_{rid}") for rid in self.robot_ids}

    def run(self) -> None:
        import roslib.message

        cfg = self.cfg
        publishers = {}
        for topic, type_name in self.pubs.items():
            cls = roslib.message.get_message_class(type_name)
            if cls is None:
                rospy.logwarn(
                    "player: message type %s of %s unknown here; skipped", type_name, topic
                )
                continue
            publishers[topic] = rospy.Publisher(self.remap.get(topic, topic), cls, queue_size=20)
        start = self.bag.get_start_time()
        self.clock.publish(Clock(clock=rospy.Time.from_sec(max(0.0, start - 0.1))))
        # robot id -> its camera topics' publishers (images, camera infos)
        cameras = {
            c.robot_id: [publishers[t] for t in c.remap if t in publishers] for c in self.cameras
        }
        wait_for_consumers(cameras, cfg)
        lockstep = {rid for rid, a in self.acks.items() if cfg.lockstep and a.has_consumer}
        for rid in sorted(set(self.acks) - lockstep):
            rospy.logwarn(
                "player: robot_%d's frames play at %g x real time (%s)",
                rid,
                cfg.rate,
                "no consumer acknowledges them" if cfg.lockstep else "lock-step off",
            )
        total = self.bag.get_message_count(topic_filters=list(publishers))
        rospy.loginfo("player: bag %s, robots %s, %d messages", cfg.bag, self.robot_ids, total)
        pending = {}  # robot id -> stamp of its last colour image not yet acknowledged
        wall0 = time.monotonic()
        last_progress = wall0
        for k, (topic, msg, t) in enumerate(self.bag.read_messages(topics=list(publishers))):
            if rospy.is_shutdown():
                return
            rid = self.image_of.get(topic)
            if rid in lockstep:
                if rid in pending and not self.acks[rid].wait(pending[rid], cfg.ack_timeout_s):
                    rospy.logwarn(
                        "player: robot_%d did not acknowledge the frame at %.3f s within "
                        "%.0f s; going on",
                        rid,
                        pending[rid],
                        cfg.ack_timeout_s,
                    )
                pending[rid] = msg.header.stamp.to_sec()
            elif not lockstep:
                delay = wall0 + (t.to_sec() - start) / cfg.rate - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            self.clock.publish(Clock(clock=t))
            publishers[topic].publish(msg)
            if time.monotonic() - last_progress > cfg.progress_period_s:
                last_progress = time.monotonic()
                rospy.loginfo(
                    "player: %d/%d bag messages (%.0f %%), sim time %.2f s",
                    k + 1,
                    total,
                    100.0 * (k + 1) / max(total, 1),
                    t.to_sec() - start,
                )
        for rid, stamp_s in pending.items():
            self.acks[rid].wait(stamp_s, cfg.ack_timeout_s)
        self.clock.publish(Clock(clock=rospy.Time.from_sec(self.bag.get_end_time() + 0.5)))
        self.done.publish(Bool(True))
        rospy.loginfo("player: bag done")
