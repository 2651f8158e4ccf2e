"""The replay schedule: due times, rate, offset, topic selection, remapping, looping."""
from __future__ import annotations

import itertools

import pytest

from ar_tracking.io.bags import BagError, BagReader, BagWriter, msg_class
from ar_tracking.io.replay import (
    ReplayOptions,
    normalize_topic,
    parse_remaps,
    schedule,
)

SEC = 1_000_000_000
MS = 1_000_000
T0 = 1_700_000_000 * SEC
String = msg_class('std_msgs/msg/String')

#: /a every 100 ms from 0 to 0.9 s, /b every 250 ms from 0.05 s: a 0.9 s bag of 14 messages.
A_OFFSETS_MS = list(range(0, 1000, 100))
B_OFFSETS_MS = [50, 300, 550, 800]
SPAN_S = 0.9


@pytest.fixture(scope='module')
def bag_path(tmp_path_factory):
    path = tmp_path_factory.mktemp('replay') / 'replay.mcap'
    with BagWriter(path) as writer:
        for ms in A_OFFSETS_MS:
            writer.write('/a', T0 + ms * MS, String(data=f'a{ms}'))
        for ms in B_OFFSETS_MS:
            writer.write('/b', T0 + ms * MS, String(data=f'b{ms}'))
    return path


@pytest.fixture
def bag(bag_path):
    with BagReader(bag_path) as reader:
        yield reader


ALL_OFFSETS_S = sorted(ms / 1000 for ms in A_OFFSETS_MS + B_OFFSETS_MS)


def test_rate_one_follows_log_time(bag):
    items = list(schedule(bag, ReplayOptions()))
    assert [s.due_s for s in items] == pytest.approx(ALL_OFFSETS_S, abs=1e-9)
    assert all(s.loop_index == 0 for s in items)
    assert [s.topic for s in items] == [s.message.topic for s in items]
    assert {s.topic for s in items} == {'/a', '/b'}


@pytest.mark.parametrize('rate', [0.5, 2.0, 10.0])
def test_due_times_scale_with_rate(bag, rate):
    items = list(schedule(bag, ReplayOptions(rate=rate)))
    assert len(items) == len(ALL_OFFSETS_S)
    assert [s.due_s for s in items] == pytest.approx([t / rate for t in ALL_OFFSETS_S], abs=1e-9)


def test_rate_zero_makes_everything_due_at_once(bag):
    items = list(schedule(bag, ReplayOptions(rate=0.0)))
    assert len(items) == len(ALL_OFFSETS_S)
    assert all(s.due_s == 0.0 for s in items)
    # still in log-time order
    times = [s.message.log_time_ns for s in items]
    assert times == sorted(times)


def test_start_offset_skips_the_beginning(bag):
    items = list(schedule(bag, ReplayOptions(start_offset_s=0.42)))
    expected = [t for t in ALL_OFFSETS_S if t >= 0.42]
    assert [s.message.log_time_ns for s in items] == [T0 + round(t * 1000) * MS for t in expected]
    # due times count from the offset
    assert [s.due_s for s in items] == pytest.approx([t - 0.42 for t in expected], abs=1e-9)


def test_start_offset_plays_latched_messages_from_before_it_first(bag):
    """/b stands for /tf_static: with an offset of 0.42 s, its messages at 0.05 and 0.3 s are
    played at once, first (a late joiner of a latched topic gets them), then the rest as usual."""
    items = list(schedule(bag, ReplayOptions(start_offset_s=0.42, latched=['b'])))
    assert [(s.topic, s.due_s, s.before_start) for s in items[:2]] == [('/b', 0.0, True), ('/b', 0.0, True)]
    assert not any(s.before_start for s in items[2:])
    assert [s.message.log_time_ns for s in items[:2]] == [T0 + 50 * MS, T0 + 300 * MS]
    rest = [t for t in ALL_OFFSETS_S if t >= 0.42]
    assert [s.message.log_time_ns for s in items[2:]] == [T0 + round(t * 1000) * MS for t in rest]


def test_start_offset_beyond_the_end_yields_nothing(bag):
    assert list(schedule(bag, ReplayOptions(start_offset_s=5.0, loop=True))) == []


@pytest.mark.parametrize('topics', [['/a'], ['a']])
def test_topic_selection(bag, topics):
    items = list(schedule(bag, ReplayOptions(topics=topics)))
    assert {s.topic for s in items} == {'/a'}
    assert [s.due_s for s in items] == pytest.approx([ms / 1000 for ms in A_OFFSETS_MS])


def test_missing_topic_is_a_bag_error(bag, bag_path):
    with pytest.raises(BagError) as exc:
        next(schedule(bag, ReplayOptions(topics=['/a', '/camera/image_raw'])))
    assert '/camera/image_raw' in str(exc.value)
    assert str(bag_path) in str(exc.value)


@pytest.mark.parametrize('kwargs', [{'rate': -1.0}, {'start_offset_s': -0.1}])
def test_invalid_options(kwargs):
    with pytest.raises(BagError):
        ReplayOptions(**kwargs)


def test_parse_remaps():
    assert parse_remaps([]) == {}
    assert parse_remaps(['camera/image_raw:=/cam0/image', '/imu/data_raw:=imu_raw']) == {
        '/camera/image_raw': '/cam0/image',
        '/imu/data_raw': 'imu_raw',
    }
    assert normalize_topic('x/y') == '/x/y'
    assert normalize_topic('/x/y') == '/x/y'


@pytest.mark.parametrize('item', ['a', 'a:=', ':=b', ':=', 'a=b', 'a:b', ''])
def test_parse_remaps_rejects_malformed(item):
    with pytest.raises(BagError) as exc:
        parse_remaps(['/ok:=/fine', item])
    assert repr(item) in str(exc.value)


def test_remap_renames_published_topic(bag):
    options = ReplayOptions(remap=parse_remaps(['a:=/renamed']))
    items = list(schedule(bag, options))
    assert {s.topic for s in items} == {'/renamed', '/b'}
    for s in items:
        assert s.message.topic in ('/a', '/b')  # the bag topic stays on the message
        assert s.topic == ('/renamed' if s.message.topic == '/a' else '/b')


@pytest.mark.parametrize('rate', [1.0, 4.0])
def test_loop_repeats_with_increasing_due_times(bag, rate):
    n = len(ALL_OFFSETS_S)
    items = list(itertools.islice(schedule(bag, ReplayOptions(rate=rate, loop=True)), 3 * n + 2))
    assert len(items) == 3 * n + 2  # endless: it did not stop after one pass
    assert [s.loop_index for s in items] == [0] * n + [1] * n + [2] * n + [3] * 2
    dues = [s.due_s for s in items]
    # /a and /b share some log times, so equal neighbours are allowed, never a step back
    assert all(later >= earlier for earlier, later in zip(dues, dues[1:]))
    for k in (1, 2):
        lap = items[k * n : (k + 1) * n]
        assert [s.message for s in lap] == [s.message for s in items[:n]]
        # each lap starts after the previous lap's last message
        assert lap[0].due_s > items[k * n - 1].due_s
        # and keeps the bag's spacing
        assert [s.due_s - lap[0].due_s for s in lap] == pytest.approx(
            [t / rate for t in ALL_OFFSETS_S], abs=1e-9
        )
        # a lap lasts about as long as the bag (a small gap between laps is allowed)
        assert lap[0].due_s - items[(k - 1) * n].due_s == pytest.approx(SPAN_S / rate, abs=0.05)


def test_loop_strictly_increasing_across_laps(bag):
    items = list(itertools.islice(schedule(bag, ReplayOptions(loop=True, topics=['/a'])), 30))
    assert [s.loop_index for s in items] == [0] * 10 + [1] * 10 + [2] * 10
    dues = [s.due_s for s in items]
    assert all(b > a for a, b in zip(dues, dues[1:]))


def test_loop_with_offset_restarts_at_the_offset(bag):
    items = list(
        itertools.islice(schedule(bag, ReplayOptions(loop=True, start_offset_s=0.5)), 20)
    )
    expected = [T0 + round(t * 1000) * MS for t in ALL_OFFSETS_S if t >= 0.5]  # 7 messages
    for lap in (0, 1):
        assert [s.message.log_time_ns for s in items if s.loop_index == lap] == expected
    assert items[len(expected)].due_s == pytest.approx((SPAN_S - 0.5) + items[0].due_s, abs=0.05)
