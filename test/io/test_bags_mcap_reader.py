"""BagReader's own MCAP message reader gives exactly what rosbags gives (same messages, same
order: log time, then file position), for any topic filter and time window."""
from __future__ import annotations

import numpy as np
import pytest

from ar_tracking.io.bags import BagError, BagReader, BagWriter, msg_class, ns_to_stamp, serialize

SEC = 1_000_000_000
T0 = 1_700_000_000 * SEC
String = msg_class('std_msgs/msg/String')
Vector3Stamped = msg_class('geometry_msgs/msg/Vector3Stamped')
Header = msg_class('std_msgs/msg/Header')
Vector3 = msg_class('geometry_msgs/msg/Vector3')


def vec(i: int, t: int) -> bytes:
    return serialize(Vector3Stamped(header=Header(stamp=ns_to_stamp(t), frame_id='f'), vector=Vector3(x=float(i), y=0.0, z=0.0)))


def write_shuffled_bag(path, chunk_size: int, compression: str = 'lz4', n: int = 600):
    """Three topics, many equal log times (within and across chunks), written partly out of
    log-time order, so that the order rules matter."""
    rng = np.random.default_rng(4)
    times = T0 + (np.arange(n) // 3) * 10_000_000  # three messages share each log time
    times = times + rng.integers(-2, 3, size=n) * 10_000_000  # and some are written late or early
    with BagWriter(path, chunk_size=chunk_size, compression=compression) as w:
        for i, t in enumerate(times):
            topic = ('/a', '/b', '/c')[i % 3]
            if topic == '/c':
                w.write(topic, int(t), serialize(String(data='x' * (i % 50))), msgtype='std_msgs/msg/String')
            else:
                w.write(topic, int(t), vec(i, int(t)), msgtype='geometry_msgs/msg/Vector3Stamped')
    return path


def both(path, **kwargs):
    out = []
    for fast in (False, True):
        with BagReader(path) as bag:
            bag.fast_mcap = fast
            out.append(list(bag.messages(**kwargs)))
    return out


@pytest.mark.parametrize('compression', ['lz4', 'zstd', 'none'])
@pytest.mark.parametrize('chunk_size', [200, 4000, 1 << 20])
def test_same_messages_in_the_same_order_as_rosbags(tmp_path, compression, chunk_size):
    path = write_shuffled_bag(tmp_path / 'b.mcap', chunk_size, compression)
    slow, fast = both(path)
    assert len(slow) == 600
    assert fast == slow
    times = [m.log_time_ns for m in fast]
    assert times == sorted(times)
    # ties between topics of one log time: some exist, and the order is the file's
    assert len(set(times)) < len(times)


def test_topic_filter_and_time_window(tmp_path):
    path = write_shuffled_bag(tmp_path / 'b.mcap', 500)
    for kwargs in ({'topics': ['/a']}, {'topics': ['c', '/b']}, {'topics': ['/nothing']},
                   {'start_ns': T0 + SEC // 2}, {'stop_ns': T0 + SEC // 3},
                   {'topics': ['/b'], 'start_ns': T0 + 100_000_000, 'stop_ns': T0 + 900_000_000}):
        slow, fast = both(path, **kwargs)
        assert fast == slow, kwargs
    assert len(both(path, topics=['/a'])[1]) == 200


def test_sample_bag_read_alike():
    from pathlib import Path

    bag = Path(__file__).resolve().parents[2] / 'bags' / 'rotation_sweep_browsing.mcap'
    if not bag.exists():
        pytest.skip('sample bag not present')
    slow, fast = both(bag)
    assert len(fast) > 10_000 and fast == slow


def test_a_damaged_chunk_is_a_bag_error(tmp_path):
    path = write_shuffled_bag(tmp_path / 'b.mcap', 4000, 'none')
    data = bytearray(path.read_bytes())
    # flip bytes in the middle of the data section (inside a chunk: its CRC no longer matches)
    mid = len(data) // 3
    data[mid:mid + 16] = bytes(b ^ 0xFF for b in data[mid:mid + 16])
    path.write_bytes(bytes(data))
    with BagReader(path) as bag:
        assert bag.fast_mcap
        with pytest.raises(BagError):
            list(bag.messages())
