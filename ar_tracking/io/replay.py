"""The schedule of a bag replay: which messages, in which order, at which playback time.

Kept free of rclpy so that it is testable on its own; :mod:`ar_tracking.ros.player` turns the
schedule into publications. Options follow ``ros2 bag play``: a rate factor, a start offset,
looping, topic selection and remapping.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Iterator

from .bags import BagError, BagMessage, BagReader


@dataclass
class ReplayOptions:
    """How to play a bag. ``rate`` 0 means as fast as possible."""

    rate: float = 1.0
    start_offset_s: float = 0.0
    loop: bool = False
    topics: list[str] = field(default_factory=list)  # empty: every topic
    remap: dict[str, str] = field(default_factory=dict)  # bag topic -> published topic
    #: Latched topics (e.g. /tf_static): with a start offset, their messages logged before the
    #: start are played first, as a late joiner of the recording would have received them.
    latched: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.rate < 0:
            raise BagError(f'replay rate must be >= 0 (got {self.rate})')
        if self.start_offset_s < 0:
            raise BagError(f'start offset must be >= 0 s (got {self.start_offset_s})')


def parse_remaps(items: list[str]) -> dict[str, str]:
    """'from:=to' strings (as on a ros2 command line) -> dict; BagError on a malformed one."""
    remap: dict[str, str] = {}
    for item in items:
        src, sep, dst = item.partition(':=')
        if not sep or not src or not dst:
            raise BagError(f'remapping {item!r} is not of the form from:=to')
        remap[normalize_topic(src)] = dst
    return remap


def normalize_topic(topic: str) -> str:
    """Bag topics are absolute; accept 'camera/image_raw' for '/camera/image_raw'."""
    return topic if topic.startswith('/') else '/' + topic


@dataclass(frozen=True)
class ScheduledMessage:
    """A message with the playback time (seconds after playback start) it is due at."""

    due_s: float
    topic: str  # after remapping
    message: BagMessage
    loop_index: int
    #: a latched message from before the start offset, played first: it does not set the clock
    before_start: bool = False


def schedule(bag: BagReader, options: ReplayOptions) -> Iterator[ScheduledMessage]:
    """Messages of an open bag with their due times; endless when looping.

    Due times follow the bag's log time divided by the rate (0 when the rate is 0). A loop
    starts again from the start offset; its messages are due after the previous loop's end.
    """
    available = bag.topics
    wanted = [normalize_topic(t) for t in options.topics] or list(available)
    missing = [t for t in wanted if t not in available]
    if missing:
        raise BagError(f'{bag.path}: no topic {", ".join(missing)} in the bag')
    start_ns = bag.start_ns + int(options.start_offset_s * 1e9)
    span_s = max(0.0, (bag.end_ns - start_ns) * 1e-9)
    loop_index = 0
    offset_s = 0.0
    latched = [t for t in (normalize_topic(t) for t in options.latched) if t in wanted]
    if latched and start_ns > bag.start_ns:
        for msg in bag.messages(latched, stop_ns=start_ns):
            yield ScheduledMessage(0.0, options.remap.get(msg.topic, msg.topic), msg, loop_index, before_start=True)
    while True:
        count = 0
        for msg in bag.messages(wanted, start_ns=start_ns):
            count += 1
            t = (msg.log_time_ns - start_ns) * 1e-9
            due = 0.0 if options.rate == 0 else offset_s + t / options.rate
            yield ScheduledMessage(due, options.remap.get(msg.topic, msg.topic), msg, loop_index)
        if not options.loop or count == 0:
            return
        loop_index += 1
        offset_s += 0.0 if options.rate == 0 else (span_s + 0.01) / options.rate
