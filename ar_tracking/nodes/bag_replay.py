"""bag_replay: publishes the topics of any bag (rosbag2 sqlite3 / mcap, ROS 1) on their topics.

Like ``ros2 bag play`` for machines without the ROS CLI: a rate factor, a start offset, looping,
topic selection and remapping (``remap`` parameter or the usual ``--ros-args -r``), and
``/clock`` from the bag's time so that other nodes can run with ``use_sim_time``. Messages are
published as the raw CDR bytes of the bag (no deserialize/serialize round). Bag topics are
published under relative names, so a node namespace applies to them; ``/tf_static`` stays
absolute and latched (transient local), as tf2 expects.

At the end of the bag the node exits (exit code 0, 1 when the bag could not be read), like
``ros2 bag play``, unless ``loop`` is set.

Two robots side by side: each replay in its own namespace with ``clock_topic: clock`` publishes
its bag time on ``/<namespace>/clock`` instead of the shared ``/clock`` (two bags on one
``/clock`` make time jump back and forth). The nodes of that namespace then take their time
from it with the remap ``-r /clock:=/<namespace>/clock`` (in a launch file:
``remappings=[('/clock', 'clock')]`` inside the namespace), each with a monotonic clock.
"""
from __future__ import annotations

from typing import Any

from rosgraph_msgs.msg import Clock

from ..io.bags import BagError, BagReader, normalize_topic
from ..io.replay import ReplayOptions, ScheduledMessage, parse_remaps
from ..ros.conversions import ConversionError, message_class, to_stamp
from ..ros.node_base import LATCHED_QOS, RELIABLE_QOS, TrackingNode, run_node
from ..ros.param_table import ParamSpec, declare_params, with_defaults
from ..ros.player import CLOCK_PERIOD_S, BagPlayer, ClockTicker

#: Topics that keep their absolute name and are latched (late joiners get them).
LATCHED_TOPICS = ('/tf_static', '/ground_truth/annotations')



def _names_a_topic(v: Any) -> str | None:
    return None if v.strip('/') else 'must name a topic'


#: The replay's parameters (a subclass sets the default of ``topics`` from its DEFAULT_TOPICS).
PARAMS = (
    ParamSpec('bag_path', '', 'Bag to play: rosbag2 directory, .mcap, .db3 or ROS 1 .bag', read_only=True),
    ParamSpec('rate', 1.0,
              'Playback rate factor (0: as fast as possible)', min_value=0.0, max_value=1000.0, read_only=True),
    ParamSpec('start_offset_s', 0.0, 'Skip this much of the bag, s', min_value=0.0, max_value=1e7, read_only=True),
    ParamSpec('loop', False, 'Play again from the start offset when the bag ends', read_only=True),
    ParamSpec('topics', [''], 'Bag topics to play (empty: all)', read_only=True),
    ParamSpec('remap', [''], 'Remappings from:=to applied to bag topics', read_only=True),
    ParamSpec('publish_clock', True, 'Publish /clock from the bag time', read_only=True),
    ParamSpec('clock_rate_hz', 1.0 / CLOCK_PERIOD_S,
              '/clock at most this often in bag time, Hz (as ros2 bag play --clock; 0: before every message)',
              min_value=0.0, max_value=1e6, read_only=True),
    ParamSpec('clock_topic', '/clock',
              'Topic of the bag clock: /clock, or clock (relative: /<namespace>/clock, one clock per robot; remap '
              "/clock to it in that namespace's nodes)",
              read_only=True, validate=_names_a_topic),
    ParamSpec('linger_s', 0.5,
              'Wall time to stay after the last message before exiting (late subscribers and reliable deliveries), s',
              min_value=0.0, max_value=60.0, read_only=True),
)

class BagReplayNode(TrackingNode):
    """Replays a bag; subclasses change the name and the default topic selection."""

    DEFAULT_TOPICS: list[str] = []

    def __init__(self, node_name: str = 'bag_replay', **kwargs: Any) -> None:
        super().__init__(node_name, **kwargs)
        v = declare_params(self, with_defaults(PARAMS, topics=self.DEFAULT_TOPICS or ['']))
        bag_path: str = v['bag_path']
        options = ReplayOptions(
            rate=v['rate'],
            start_offset_s=v['start_offset_s'],
            loop=v['loop'],
            topics=list(v['topics']),
            remap=parse_remaps([r for r in v['remap'] if r]),
        )
        options.topics = [normalize_topic(t) for t in options.topics if t]
        self.publish_clock: bool = v['publish_clock']
        clock_topic: str = v['clock_topic']
        self.linger_s: float = v['linger_s']
        if not bag_path:
            raise ValueError('parameter bag_path is required (-p bag_path:=/path/to/bag)')
        try:
            with BagReader(bag_path) as bag:
                types = bag.topics
                latched_in_bag = bag.latched_topics
        except BagError as exc:
            raise ValueError(str(exc)) from exc
        if self.DEFAULT_TOPICS and options.topics == self.DEFAULT_TOPICS:
            options.topics = [t for t in options.topics if t in types]  # whichever of them exist
            if not options.topics:
                raise ValueError(f'{bag_path}: none of {", ".join(self.DEFAULT_TOPICS)} in the bag')
        self.publishers_by_topic: dict[str, Any] = {}
        for topic in options.topics or list(types):
            if topic not in types:
                raise ValueError(f'{bag_path}: no topic {topic} in the bag')
            try:
                cls = message_class(types[topic])
            except ConversionError as exc:
                self.get_logger().warning(f'{topic}: {exc}; not played')
                continue
            name = options.remap.get(topic, topic)
            latched = topic in LATCHED_TOPICS or topic in latched_in_bag  # as recorded (offered_qos_profiles)
            if topic not in LATCHED_TOPICS and name.startswith('/'):
                name = name[1:]  # relative, so that the node's namespace applies
            self.publishers_by_topic[topic] = self.advertise(cls, name, LATCHED_QOS if latched else RELIABLE_QOS)
        options.topics = list(self.publishers_by_topic)
        options.latched = [t for t in options.topics if t in LATCHED_TOPICS or t in latched_in_bag]
        self.clock_pub = self.advertise(Clock, clock_topic, RELIABLE_QOS) if self.publish_clock else None
        self._clock_msg = Clock()  # not _clock: rclpy.Node keeps its clock there
        rate_hz = float(v['clock_rate_hz'])
        self._clock_ticker = ClockTicker(int(1e9 / rate_hz) if rate_hz > 0 else 0)
        self.player = BagPlayer(bag_path, options, self._publish, self._done)
        self.get_logger().info(
            f'playing {len(options.topics)} topics of {bag_path} at rate {options.rate:g}'
            + (' (looping)' if options.loop else '')
        )
        self.player.start()

    def _publish(self, item: ScheduledMessage) -> None:
        if (self.clock_pub is not None and not item.before_start  # the clock starts at the offset
                and self._clock_ticker.due(item.message.log_time_ns)):
            to_stamp(item.message.log_time_ns, self._clock_msg.clock)
            self.clock_pub.publish(self._clock_msg)
        self.publishers_by_topic[item.message.topic].publish(item.message.rawdata)

    def _done(self, error: str | None) -> None:
        """Runs on the player thread when the playback ends (the bag's end, an error, or stop)."""
        if error:
            self.get_logger().error(error)
        elif self.player.stopped:
            self.get_logger().info(f'replay stopped: {self.player.published} messages')
            return
        else:
            self.get_logger().info(f'replay finished: {self.player.published} messages')
        if not self.player.stopped and not self.player.wait_stop(self.linger_s):
            self.exit_code = 1 if error else 0

    def close(self) -> None:
        self.player.stop()


def main(args: list[str] | None = None) -> int:
    return run_node(BagReplayNode, args)


if __name__ == '__main__':
    raise SystemExit(main())
