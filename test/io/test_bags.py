"""Bag writing and reading without ROS: round trips in both storages and clear errors."""
from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from ar_tracking.io.bags import (
    BagError,
    BagReader,
    BagWriter,
    deserialize,
    msg_class,
    ns_to_stamp,
    serialize,
    stamp_to_ns,
)

SEC = 1_000_000_000
MS = 1_000_000
T0 = 1_700_000_000 * SEC

String = msg_class('std_msgs/msg/String')
Header = msg_class('std_msgs/msg/Header')
Vector3 = msg_class('geometry_msgs/msg/Vector3')
Quaternion = msg_class('geometry_msgs/msg/Quaternion')
Imu = msg_class('sensor_msgs/msg/Imu')
Image = msg_class('sensor_msgs/msg/Image')


def imu(i: int, stamp_ns: int) -> object:
    return Imu(
        header=Header(stamp=ns_to_stamp(stamp_ns), frame_id='imu'),
        orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=np.full(9, float(i)),
        angular_velocity=Vector3(x=0.1 * i, y=0.0, z=-0.1),
        angular_velocity_covariance=np.zeros(9),
        linear_acceleration=Vector3(x=0.0, y=0.0, z=9.81),
        linear_acceleration_covariance=np.zeros(9),
    )


def image(i: int, stamp_ns: int, rng: np.random.Generator, size: int = 32) -> object:
    return Image(
        header=Header(stamp=ns_to_stamp(stamp_ns), frame_id='camera_optical'),
        height=size,
        width=size,
        encoding='mono8',
        is_bigendian=0,
        step=size,
        data=rng.integers(0, 256, size * size, dtype=np.uint8),
    )


#: The written content: (topic, log time ns) per message. IMU at 100 Hz, images at 30 Hz,
#: text at 2 Hz, written topic by topic (not in time order) to check the reader merges them.
IMU_TIMES = [T0 + i * 10 * MS for i in range(50)]
IMAGE_TIMES = [T0 + 3 * MS + i * 33 * MS for i in range(15)]
TEXT_TIMES = [T0 + 1 * MS + i * 250 * MS for i in range(2)]


def write_sample_bag(path: Path, storage: str | None = None, **kwargs) -> Path:
    rng = np.random.default_rng(0)
    with BagWriter(path, storage=storage, **kwargs) as writer:
        for i, t in enumerate(IMU_TIMES):
            writer.write('/imu/data_raw', t, imu(i, t))
        for i, t in enumerate(IMAGE_TIMES):
            writer.write('/camera/image_raw', t, image(i, t, rng))
        for i, t in enumerate(TEXT_TIMES):
            writer.write('/notes', t, String(data=f'note {i}'))
        assert writer.message_count == len(IMU_TIMES) + len(IMAGE_TIMES) + len(TEXT_TIMES)
    return writer.path


def assert_one_line_mentioning(exc: pytest.ExceptionInfo, path: Path) -> None:
    text = str(exc.value)
    assert '\n' not in text and text.strip()
    assert str(path) in text, text


STORAGES = [('mcap', 'run.mcap'), ('sqlite3', 'run_db')]


@pytest.mark.parametrize('storage, name', STORAGES)
def test_round_trip(tmp_path, storage, name):
    path = write_sample_bag(tmp_path / name, storage)
    if storage == 'mcap':
        assert path.is_file() and path.suffix == '.mcap'
    else:
        assert path.is_dir() and (path / 'metadata.yaml').exists()
    with BagReader(path) as bag:
        assert bag.topics == {
            '/imu/data_raw': 'sensor_msgs/msg/Imu',
            '/camera/image_raw': 'sensor_msgs/msg/Image',
            '/notes': 'std_msgs/msg/String',
        }
        assert bag.message_count() == 67
        assert bag.message_count(['/imu/data_raw']) == 50
        assert bag.message_count(['/camera/image_raw', '/notes']) == 17
        assert bag.message_count(['/nope']) == 0
        all_times = sorted(IMU_TIMES + IMAGE_TIMES + TEXT_TIMES)
        assert bag.start_ns == all_times[0]
        # rosbags reports the end as one nanosecond after the last message
        assert bag.end_ns - 1 <= all_times[-1] <= bag.end_ns
        assert bag.duration_s == pytest.approx((all_times[-1] - all_times[0]) * 1e-9, abs=2e-9)

        messages = list(bag.messages())
        assert [m.log_time_ns for m in messages] == all_times  # merged in log-time order
        imu_msgs = bag.read_all('/imu/data_raw')
        assert [t for t, _ in imu_msgs] == IMU_TIMES
        for i, (t, msg) in enumerate(imu_msgs):
            assert stamp_to_ns(msg.header.stamp) == t
            assert msg.header.frame_id == 'imu'
            assert msg.angular_velocity.x == pytest.approx(0.1 * i)
            np.testing.assert_array_equal(msg.orientation_covariance, np.full(9, float(i)))
        rng = np.random.default_rng(0)
        for i, (t, msg) in enumerate(bag.read_all('/camera/image_raw')):
            np.testing.assert_array_equal(msg.data, image(i, t, rng).data)
        assert [m.data for _, m in bag.read_all('/notes')] == ['note 0', 'note 1']


@pytest.mark.parametrize('storage, name', STORAGES)
def test_time_window_and_topic_selection(tmp_path, storage, name):
    path = write_sample_bag(tmp_path / name, storage)
    with BagReader(path) as bag:
        start, stop = T0 + 100 * MS, T0 + 200 * MS
        window = list(bag.messages(['/imu/data_raw'], start_ns=start, stop_ns=stop))
        assert [m.log_time_ns for m in window] == [t for t in IMU_TIMES if start <= t < stop]
        assert {m.topic for m in bag.messages(['/notes'])} == {'/notes'}
        assert list(bag.messages(['/nope'])) == []


@pytest.mark.parametrize('storage, name', STORAGES)
def test_raw_bytes_and_message_objects_are_interchangeable(tmp_path, storage, name):
    msgs = [imu(i, T0 + i * MS) for i in range(5)]
    with BagWriter(tmp_path / name, storage=storage) as writer:
        for i, msg in enumerate(msgs):
            if i % 2:  # odd ones as CDR bytes (the first of a topic needs the type)
                writer.write('/imu', T0 + i * MS, serialize(msg), 'sensor_msgs/msg/Imu')
            else:
                writer.write('/imu', T0 + i * MS, msg)
        # once the topic exists, raw bytes without a type are fine
        writer.write('/imu', T0 + 10 * MS, memoryview(serialize(msgs[0])))
    with BagReader(writer.path) as bag:
        raw = list(bag.messages())
        assert len(raw) == 6
        for message, msg in zip(raw, msgs):
            assert isinstance(message.rawdata, bytes)
            assert message.msgtype == 'sensor_msgs/msg/Imu'
            assert message.rawdata == serialize(msg)
            decoded = bag.deserialize(message)
            assert decoded.header.stamp == msg.header.stamp
            assert decoded.angular_velocity == msg.angular_velocity
        assert raw[-1].rawdata == raw[0].rawdata


def test_raw_bytes_on_a_new_topic_need_a_type(tmp_path):
    with BagWriter(tmp_path / 'a.mcap') as writer:
        with pytest.raises(BagError):
            writer.write('/x', T0, serialize(String(data='x')))
        writer.write('/x', T0, String(data='x'))
        with pytest.raises(BagError):  # a topic has one type
            writer.write('/x', T0 + 1, imu(0, T0))
        with pytest.raises(BagError):
            writer.write('/x', T0 + 2, serialize(imu(0, T0)), 'sensor_msgs/msg/Imu')
        writer.write('/x', T0 + 3, serialize(String(data='y')), 'std_msgs/msg/String')
    with BagReader(writer.path) as bag:  # the refused messages are not in the bag
        assert [m.data for _, m in bag.read_all('/x')] == ['x', 'y']


def test_writer_chooses_storage_from_the_name(tmp_path):
    assert BagWriter(tmp_path / 'a.mcap').storage == 'mcap'
    assert BagWriter(tmp_path / 'a').storage == 'mcap'
    assert BagWriter(tmp_path / 'a.db3').storage == 'sqlite3'
    with pytest.raises(BagError):
        BagWriter(tmp_path / 'a.mcap', storage='rosbag1')


@pytest.mark.parametrize('storage, name', STORAGES)
def test_overwrite_is_refused_unless_asked(tmp_path, storage, name):
    path = write_sample_bag(tmp_path / name, storage)
    with pytest.raises(BagError) as exc:
        with BagWriter(path, storage=storage) as writer:
            writer.write('/notes', T0, String(data='lost'))
    assert_one_line_mentioning(exc, path)
    with BagReader(path) as bag:  # untouched
        assert bag.message_count() == 67
    with BagWriter(path, storage=storage, overwrite=True) as writer:
        writer.write('/notes', T0, String(data='new'))
    with BagReader(path) as bag:
        assert bag.topics == {'/notes': 'std_msgs/msg/String'}
        assert [m.data for _, m in bag.read_all('/notes')] == ['new']


@pytest.mark.parametrize('storage, name', STORAGES)
def test_writer_closes_on_exception_and_bag_stays_readable(tmp_path, storage, name):
    writer = BagWriter(tmp_path / name, storage=storage)
    with pytest.raises(RuntimeError, match='boom'):
        with writer:
            for i in range(3):
                writer.write('/notes', T0 + i * MS, String(data=str(i)))
            raise RuntimeError('boom')
    with BagReader(writer.path) as bag:
        assert [m.data for _, m in bag.read_all('/notes')] == ['0', '1', '2']
    writer.close()  # closing twice is harmless
    with pytest.raises(BagError):  # but it no longer writes
        writer.write('/notes', T0, String(data='late'))


# --- errors ---------------------------------------------------------------------------------

def test_missing_path(tmp_path):
    path = tmp_path / 'nope.mcap'
    with pytest.raises(BagError) as exc:
        with BagReader(path):
            pass
    assert_one_line_mentioning(exc, path)


def test_random_bytes_named_mcap(tmp_path):
    path = tmp_path / 'noise.mcap'
    path.write_bytes(np.random.default_rng(1).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(BagError) as exc:
        BagReader(path).open()
    assert_one_line_mentioning(exc, path)


def test_empty_file(tmp_path):
    path = tmp_path / 'empty.mcap'
    path.write_bytes(b'')
    with pytest.raises(BagError) as exc:
        BagReader(path).open()
    assert_one_line_mentioning(exc, path)


def test_empty_directory(tmp_path):
    path = tmp_path / 'not_a_bag'
    path.mkdir()
    with pytest.raises(BagError) as exc:
        BagReader(path).open()
    assert_one_line_mentioning(exc, path)


def read_everything(path: Path) -> int:
    """Open and iterate a bag; BagError is the only acceptable failure."""
    count = 0
    with BagReader(path) as bag:
        for message in bag.messages():
            bag.deserialize(message)
            count += 1
    return count


@pytest.mark.parametrize('fraction', [0.5, 0.1, 0.3])
def test_truncated_mcap(tmp_path, fraction):
    """Cut inside the only chunk: not one complete message is left, so the bag is unreadable."""
    whole = write_sample_bag(tmp_path / 'whole.mcap')
    data = whole.read_bytes()
    path = tmp_path / 'cut.mcap'
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(BagError) as exc:
        read_everything(path)  # either open or the iteration fails, with BagError only
    assert_one_line_mentioning(exc, path)


def test_corrupt_mcap_middle(tmp_path):
    whole = write_sample_bag(tmp_path / 'whole.mcap')
    data = bytearray(whole.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 256] = np.random.default_rng(2).bytes(256)
    path = tmp_path / 'corrupt.mcap'
    path.write_bytes(bytes(data))
    with pytest.raises(BagError) as exc:
        read_everything(path)
    assert_one_line_mentioning(exc, path)


def test_unknown_message_type(tmp_path):
    with pytest.raises(BagError):
        msg_class('nope_msgs/msg/Nothing')
    path = tmp_path / 'a.mcap'
    with BagWriter(path) as writer:
        with pytest.raises(BagError) as exc:
            writer.add_topic('/x', 'nope_msgs/msg/Nothing')
        assert 'nope_msgs/msg/Nothing' in str(exc.value)
        assert_one_line_mentioning(exc, path)
        with pytest.raises(BagError) as exc:
            writer.write('/x', T0, b'\x00\x01\x00\x00', 'sensor_msgs/msg/Nope')
        assert_one_line_mentioning(exc, path)
        writer.write('/ok', T0, String(data='still writing'))
    with BagReader(path) as bag:  # the failed topics left nothing behind
        assert bag.topics == {'/ok': 'std_msgs/msg/String'}


def test_deserialize_errors_are_bag_errors():
    with pytest.raises(BagError):
        deserialize(b'\x00\x01\x00\x00\x05', 'sensor_msgs/msg/Imu')  # truncated CDR
    with pytest.raises(BagError):
        deserialize(serialize(String(data='x')), 'nope_msgs/msg/Nothing')
    assert deserialize(serialize(String(data='x')), 'std_msgs/msg/String').data == 'x'


def test_reader_not_open(tmp_path):
    bag = BagReader(tmp_path / 'x.mcap')
    with pytest.raises(BagError):
        _ = bag.topics


def test_stamp_helpers_keep_integer_nanoseconds():
    for ns in (0, 1, SEC - 1, T0 + 123_456_789, 2**31 * SEC - 1):
        stamp = ns_to_stamp(ns)
        assert 0 <= stamp.nanosec < SEC
        assert stamp_to_ns(stamp) == ns


def test_written_files_are_not_left_open(tmp_path):
    path = write_sample_bag(tmp_path / 'a.mcap')
    # the writer released the file: it can be removed and recreated at once
    os.remove(path)
    assert write_sample_bag(path).exists()


# --- Ctrl-C inside the writer ------------------------------------------------------------------

MCAP_PACKAGE_DIR = str(Path(__import__('mcap').__file__).parent)


class _InterruptAtLine:
    """A trace hook raising KeyboardInterrupt at the n-th line run inside the mcap package.

    This is what a SIGINT does to a writer in the main thread: Python raises the interrupt
    between any two statements, possibly in the middle of a chunk flush.
    """

    def __init__(self, at: int) -> None:
        self.at = at
        self.lines = 0

    def __call__(self, frame, event, arg):
        if not frame.f_code.co_filename.startswith(MCAP_PACKAGE_DIR):
            return None
        return self._local

    def _local(self, frame, event, arg):
        if event == 'line':
            self.lines += 1
            if self.lines == self.at:
                raise KeyboardInterrupt
        return self._local


def _write_interrupted(path: Path, at: int) -> int:
    """Write a small bag, interrupted at line ``at`` that mcap runs inside ``write``.

    Returns the number of lines mcap ran inside the writes.
    """
    hook = _InterruptAtLine(at)
    writer = BagWriter(path, overwrite=True)
    writer.open()
    previous = sys.gettrace()
    try:
        sys.settrace(hook)
        try:
            for i in range(3):
                writer.write('/notes', T0 + i * MS, String(data=f'note {i}'))
                writer.write('/imu', T0 + i * MS, imu(i, T0 + i * MS))
        finally:
            sys.settrace(previous)
    except KeyboardInterrupt:
        pass
    try:
        writer.close()  # what the runner's `finally` does: only BagError may come out
    except BagError:
        pass
    return hook.lines


def test_interrupted_writer_never_leaves_a_silently_short_bag(tmp_path):
    path = tmp_path / 'interrupted.mcap'
    total_lines = _write_interrupted(path, at=-1)
    with BagReader(path) as bag:
        assert bag.message_count() == 6 and len(list(bag.messages())) == 6
    outcomes = set()
    # every 4th line: the windows in which an interrupt loses a message span ~16 lines
    for at in range(1, total_lines + 1, 4):
        _write_interrupted(path, at)
        try:
            with BagReader(path) as bag:
                declared = bag.message_count()
                read = [bag.deserialize(m) for m in bag.messages()]
        except BagError:
            outcomes.add('error')
            continue
        assert len(read) == declared, f'interrupt at mcap line {at}: {len(read)} of {declared}'
        outcomes.add('complete')
    assert outcomes == {'error', 'complete'}  # both kinds happened: the sweep is not vacuous


@pytest.mark.parametrize('storage, name', STORAGES)
def test_failing_finalisation_is_a_bag_error(tmp_path, monkeypatch, storage, name):
    """A writer left inconsistent (e.g. interrupted in a chunk flush) fails to close cleanly."""
    import mcap.writer
    import rosbags.rosbag2

    def broken(self, *args, **kwargs):
        raise ValueError('I/O operation on closed file.')

    writer = BagWriter(tmp_path / name, storage=storage)
    writer.open()
    writer.write('/notes', T0, String(data='x'))
    if storage == 'mcap':
        monkeypatch.setattr(mcap.writer.Writer, 'finish', broken)
    else:
        monkeypatch.setattr(rosbags.rosbag2.Writer, 'close', broken)
    with pytest.raises(BagError) as exc:
        writer.close()
    assert_one_line_mentioning(exc, writer.path)
    writer.close()  # a second close is a no-op
    if storage == 'mcap':
        assert writer._file is None  # the file handle was released all the same


def test_unfinished_mcap_of_one_complete_chunk_is_recovered_in_time_order(tmp_path, caplog):
    """Cut after the (only) chunk, inside the summary: every message is recovered, merged into
    log-time order although the writer wrote them topic by topic."""
    whole = write_sample_bag(tmp_path / 'whole.mcap')
    data = whole.read_bytes()
    path = tmp_path / 'cut.mcap'
    path.write_bytes(data[: int(len(data) * 0.999)])
    with caplog.at_level('WARNING', logger='ar_tracking.io.bags'):
        with BagReader(path) as bag:
            assert bag.recovered is not None
            total = len(IMU_TIMES) + len(IMAGE_TIMES) + len(TEXT_TIMES)
            assert bag.message_count() == total
            assert bag.topics == {'/imu/data_raw': 'sensor_msgs/msg/Imu',
                                  '/camera/image_raw': 'sensor_msgs/msg/Image', '/notes': 'std_msgs/msg/String'}
            times = [m.log_time_ns for m in bag.messages()]
            assert times == sorted(IMU_TIMES + IMAGE_TIMES + TEXT_TIMES)
            assert [m.log_time_ns for m in bag.messages(['/imu/data_raw'])] == IMU_TIMES
            assert bag.start_ns == min(times) and bag.end_ns == max(times)
    recovered = [r.getMessage() for r in caplog.records if 'unfinished MCAP' in r.getMessage()]
    assert len(recovered) == 1 and recovered[0].startswith(f'recovered {total} messages from an unfinished MCAP')


def _write_with_flush_points(path: Path, seconds: float = 3.0, flush_every_s: float = 0.1, compression: str = 'zstd'):
    """100 Hz IMU through BagWriter with a periodic flush; returns the messages written and the
    (bytes on disk, messages written) after each flush: what a kill at that moment leaves."""
    points: list[tuple[int, int]] = []
    times = [T0 + i * 10 * MS for i in range(int(seconds * 100))]
    with BagWriter(path, flush_every_s=flush_every_s, chunk_size=1 << 30, compression=compression) as writer:
        for i, t in enumerate(times):
            writer.write('/imu/data_raw', t, imu(i, t))
            size = path.stat().st_size
            if size > (points[-1][0] if points else 0):
                points.append((size, writer.message_count))
    # close() wrote the rest as a last chunk; its end comes from the finished file's index.
    from mcap.reader import make_reader

    with open(path, 'rb') as f:
        last = make_reader(f).get_summary().chunk_indexes[-1]
    points.append((last.chunk_start_offset + last.chunk_length, len(times)))
    return times, points


@pytest.mark.parametrize('compression', ['zstd', 'lz4', 'none'])
@pytest.mark.parametrize('cut', ['50%', '90%', 'before the footer', 'inside the first chunk'])
def test_writer_killed_at_any_point_leaves_the_flushed_chunks_readable(tmp_path, cut, compression):
    times, points = _write_with_flush_points(tmp_path / 'whole.mcap', compression=compression)
    assert len(points) >= 25  # one flush per 0.1 s of log time, not one chunk for everything
    data = (tmp_path / 'whole.mcap').read_bytes()
    at = {'50%': len(data) // 2, '90%': int(len(data) * 0.9), 'before the footer': points[-1][0],
          'inside the first chunk': points[0][0] + 40}[cut]
    # What the complete chunks hold: everything flushed before the cut.
    expected = max(n for size, n in points if size <= at)
    path = tmp_path / 'killed.mcap'
    path.write_bytes(data[:at])
    with BagReader(path) as bag:
        assert bag.recovered is not None
        assert bag.message_count() == bag.message_count(['/imu/data_raw']) == expected
        read = list(bag.messages())
        assert [m.log_time_ns for m in read] == times[:expected]
        assert bag.deserialize(read[-1]).angular_velocity.x == pytest.approx(0.1 * (expected - 1))


@pytest.mark.parametrize('compression', ['lz4', 'none'])
def test_every_compression_is_read_by_rosbags_too(tmp_path, compression):
    """The run's default output (lz4) and uncompressed MCAPs: our reader and rosbags' read the
    same messages; an unknown compression is one BagError."""
    from rosbags.highlevel import AnyReader

    times, _ = _write_with_flush_points(tmp_path / 'c.mcap', seconds=0.5, compression=compression)
    with BagReader(tmp_path / 'c.mcap') as bag:
        assert [m.log_time_ns for m in bag.messages()] == times
    with AnyReader([tmp_path / 'c.mcap']) as reader:
        assert [t for _, t, _ in reader.messages()] == times
    with pytest.raises(BagError, match='unknown MCAP compression'):
        BagWriter(tmp_path / 'd.mcap', compression='brotli')


def test_flush_points_depend_on_log_time_only(tmp_path):
    """Two writes of the same messages give identical files (lockstep runs stay byte-identical)."""
    _write_with_flush_points(tmp_path / 'a.mcap')
    _write_with_flush_points(tmp_path / 'b.mcap')
    assert (tmp_path / 'a.mcap').read_bytes() == (tmp_path / 'b.mcap').read_bytes()


def test_unfinished_mcap_without_a_complete_chunk_is_one_error_line(tmp_path):
    from mcap.reader import make_reader

    _write_with_flush_points(tmp_path / 'whole.mcap')
    with open(tmp_path / 'whole.mcap', 'rb') as f:
        first = make_reader(f).get_summary().chunk_indexes[0]
    path = tmp_path / 'killed_early.mcap'
    path.write_bytes((tmp_path / 'whole.mcap').read_bytes()[: first.chunk_start_offset + first.chunk_length - 1])
    with pytest.raises(BagError) as exc:
        BagReader(path).open()
    assert_one_line_mentioning(exc, path)
    assert 'unfinished MCAP' in str(exc.value)


def test_static_transforms_are_read_without_ros(tmp_path):
    """/tf_static as StaticTransform: rotation takes child vectors into the parent, translation
    is the child origin in the parent; a later transform replaces an earlier one; invalid ones
    are skipped."""
    from ar_tracking.core.rotations import matrix_to_quat_xyzw, rot_z
    from ar_tracking.io.static_tf import static_transforms

    TFMessage = msg_class('tf2_msgs/msg/TFMessage')
    TransformStamped = msg_class('geometry_msgs/msg/TransformStamped')
    Transform = msg_class('geometry_msgs/msg/Transform')

    def tf(parent, child, R, p=(0.0, 0.0, 0.0), q=None):
        q = matrix_to_quat_xyzw(R) if q is None else q
        return TransformStamped(
            header=Header(stamp=ns_to_stamp(T0), frame_id=parent), child_frame_id=child,
            transform=Transform(translation=Vector3(x=p[0], y=p[1], z=p[2]),
                                rotation=Quaternion(x=q[0], y=q[1], z=q[2], w=q[3])))

    R1, R2 = rot_z(0.3), rot_z(-1.1)
    path = tmp_path / 'tf.mcap'
    with BagWriter(path) as w:
        w.write('/tf_static', T0, TFMessage(transforms=[tf('/imu', 'camera_optical', R1, (0.01, 0.02, 0.03)),
                                                        tf('base', 'bad', np.eye(3), q=(0.0, 0.0, 0.0, 0.0))]))
        w.write('/tf_static', T0 + MS, TFMessage(transforms=[tf('base', 'imu', R2)]))
        w.write('/tf_static', T0 + 2 * MS, TFMessage(transforms=[tf('imu', 'camera_optical', R2, (1.0, 0.0, 0.0))]))
        w.write('/notes', T0, String(data='no tf here'))
    with BagReader(path) as bag:
        found = {(t.parent, t.child): t for t in static_transforms(bag)}
    assert set(found) == {('imu', 'camera_optical'), ('base', 'imu')}  # the zero quaternion skipped
    cam = found[('imu', 'camera_optical')]  # the later one replaced the first
    np.testing.assert_allclose(cam.rotation, R2, atol=1e-12)
    np.testing.assert_allclose(cam.translation, [1.0, 0.0, 0.0])
    x_child = np.array([1.0, 0.0, 0.0])
    np.testing.assert_allclose(found[('base', 'imu')].rotation @ x_child, [np.cos(-1.1), np.sin(-1.1), 0.0], atol=1e-12)
    with BagReader(write_sample_bag(tmp_path / 'none.mcap')) as bag:
        assert static_transforms(bag) == []


@pytest.mark.parametrize('storage, name', [('mcap', 'b.mcap'), ('sqlite3', 'b')])
def test_topic_names_without_leading_slash_and_offered_qos(tmp_path, storage, name):
    """A converter's 'camera/camera_info' reads as '/camera/camera_info' (asked for either way);
    /tf_static is written with latched offered_qos_profiles, other topics volatile."""
    from ar_tracking.io.bags import BagReader, BagWriter, msg_class

    path = tmp_path / name
    with BagWriter(path, storage=storage) as w:
        w.write('/tf_static', 1, msg_class('tf2_msgs/msg/TFMessage')(transforms=[]))
        w.write('camera/camera_info', 2, msg_class('std_msgs/msg/String')(data='x'))
        w.add_topic('/panorama/image', 'std_msgs/msg/String')  # a latched product by default
        w.add_topic('/camera/other', 'std_msgs/msg/String', latched=True)
    with BagReader(w.path) as r:
        assert set(r.topics) == {'/tf_static', '/camera/camera_info', '/panorama/image', '/camera/other'}
        for asked in ('camera/camera_info', '/camera/camera_info'):
            assert [m.topic for m in r.messages([asked])] == ['/camera/camera_info']
            assert r.message_count([asked]) == 1
        assert r.latched_topics == {'/tf_static', '/panorama/image', '/camera/other'}
