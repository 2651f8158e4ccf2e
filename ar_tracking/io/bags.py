"""Reading and writing bags without a ROS install.

Reading goes through ``rosbags`` (rosbag2 sqlite3 and mcap directories, bare ``.mcap`` files and
ROS 1 ``.bag`` files). Writing produces either a single ``.mcap`` file (ros2 profile, written with
the ``mcap`` package so that ``-o OUT.mcap`` is one file) or a rosbag2 sqlite3 directory (rosbags'
writer). Messages are handled as raw CDR bytes wherever possible so that a replay never pays a
deserialize/serialize round; ``deserialize`` turns them into rosbags message objects when the
caller needs the fields.

Every failure to open, parse or write a bag is raised as :class:`BagError` with one line that
says which file and what is wrong; the CLI prints that line and exits non-zero.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, Literal

from rosbags.typesys import Stores, get_typestore

from .errors import BagError
from .mcap_reader import read_indexed_mcap, read_mcap_summary
from .mcap_recovery import MCAP_MAGIC, RecoveredMcap, is_unfinished_mcap, scan_unfinished_mcap

__all__ = [
    'LATCHED_TOPICS', 'MCAP_MAGIC', 'TYPESTORE', 'BagError', 'BagMessage', 'BagReader',
    'BagWriter', 'RecoveredMcap', 'deserialize', 'is_unfinished_mcap', 'msg_class',
    'normalize_topic', 'ns_to_stamp', 'offered_qos', 'read_metadata', 'scan_unfinished_mcap', 'serialize',
    'stamp_to_ns',
]

logger = logging.getLogger(__name__)

#: The message definitions of ROS 2 Jazzy, used to (de)serialise and to describe topics in
#: written bags. It knows every standard message the package uses.
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

StorageFormat = Literal['mcap', 'sqlite3']


@dataclass(frozen=True)
class BagMessage:
    """One message of a bag: its topic, type, log time and serialised (CDR) bytes."""

    topic: str
    msgtype: str
    log_time_ns: int
    rawdata: bytes


def msg_class(msgtype: str) -> Any:
    """The rosbags dataclass for a ROS message type name such as ``sensor_msgs/msg/Imu``."""
    try:
        return TYPESTORE.types[msgtype]
    except KeyError as exc:
        raise BagError(f'unknown message type {msgtype!r}') from exc


def serialize(msg: Any) -> bytes:
    """CDR bytes of a rosbags message object (its type is taken from the object)."""
    return bytes(TYPESTORE.serialize_cdr(msg, msg.__msgtype__))


def deserialize(rawdata: bytes, msgtype: str) -> Any:
    """A rosbags message object from CDR bytes; :class:`BagError` if the bytes do not parse."""
    try:
        return TYPESTORE.deserialize_cdr(rawdata, msgtype)
    except Exception as exc:  # rosbags raises assorted errors on truncated or foreign data
        raise BagError(f'cannot decode a {msgtype} message: {exc}') from exc



#: Topics written as latched (reliable, transient local, depth 1) unless a writer is told
#: otherwise: a player that honours offered_qos_profiles (ros2 bag play, bag_replay) latches them again.
LATCHED_TOPICS = frozenset({
    '/tf_static', '/ground_truth/annotations',
    # the graph's latched products (nodes publish them reliable + transient local)
    '/panorama/image', '/panorama/tiles', '/slam/map_points', '/slam/keyframes', '/slam/path',
    '/annotations/markers',
})


def offered_qos(latched: bool) -> Any:
    """The rosbags Qos a publisher offers: reliable keep-last, transient local depth 1 when
    latched, volatile depth 10 otherwise (what rosbag2 records in offered_qos_profiles)."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(0, 0)  # RMW_DURATION_UNSPECIFIED: the default (infinite)
    return Qos(QosHistory.KEEP_LAST, 1 if latched else 10, QosReliability.RELIABLE,
               QosDurability.TRANSIENT_LOCAL if latched else QosDurability.VOLATILE,
               zero, zero, QosLiveliness.AUTOMATIC, zero, False)


def normalize_topic(topic: str) -> str:
    """The absolute topic name: rosbag2 writes '/camera/camera_info', some converters
    'camera/camera_info'; both are read as the former (and asked for either way)."""
    return topic if topic.startswith('/') else '/' + topic


def _wanted(topics: Iterable[str] | None) -> set[str] | None:
    return None if topics is None else {normalize_topic(t) for t in topics}


class BagReader:
    """Sequential reader of any bag that rosbags understands.

    Use as a context manager::

        with BagReader('run.mcap') as bag:
            for m in bag.messages(['/imu/data']):
                imu = bag.deserialize(m)
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._reader: Any = None
        #: Set when the bag is an unfinished MCAP read by streaming (see :attr:`recovered`).
        self._recovered: RecoveredMcap | None = None
        #: read a single indexed .mcap file with io.mcap_reader (False: rosbags, e.g. to compare)
        self.fast_mcap = True
        #: The MCAP summary for io.mcap_reader, read at the first :meth:`messages` of an open
        #: reader (a list holding it, so that a file without a summary is read once too).
        self._mcap_summary: list[Any] = []

    def __enter__(self) -> 'BagReader':
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Open the bag; :class:`BagError` with the reason if it cannot be read."""
        from .bag_typestores import CachedTypesReader

        if not self.path.exists():
            raise BagError(f'{self.path}: no such bag')
        self._mcap_summary = []
        if is_unfinished_mcap(self.path):
            try:
                self._recovered = scan_unfinished_mcap(self.path)
            except BagError:
                raise
            except Exception as exc:
                raise BagError(f'{self.path}: not a readable bag ({_reason(exc)})') from exc
            self._reader = self._recovered
            return
        try:
            reader = CachedTypesReader([self.path], default_typestore=TYPESTORE)
            reader.open()
        except Exception as exc:
            raise BagError(f'{self.path}: not a readable bag ({_reason(exc)})') from exc
        self._reader = reader

    def close(self) -> None:
        self._mcap_summary = []
        if self._recovered is not None:
            self._recovered = self._reader = None
            return
        if self._reader is not None:
            try:
                self._reader.close()
            finally:
                self._reader = None

    @property
    def recovered(self) -> RecoveredMcap | None:
        """The streaming scan when this bag is an unfinished MCAP (its writer was killed), else
        None: its messages are those of the complete chunks."""
        return self._recovered

    @property
    def _r(self) -> Any:
        if self._reader is None:
            raise BagError(f'{self.path}: bag is not open')
        return self._reader

    @property
    def latched_topics(self) -> set[str]:
        """Topics whose recorded publisher offered transient local durability (latched)."""
        from rosbags.interfaces import QosDurability

        if self._recovered is not None:
            return set()
        out = set()
        for c in self._r.connections:
            profiles = getattr(c.ext, 'offered_qos_profiles', None) or []
            if any(q.durability == QosDurability.TRANSIENT_LOCAL for q in profiles):
                out.add(normalize_topic(c.topic))
        return out

    @property
    def topics(self) -> dict[str, str]:
        """Topic name -> message type, for every topic in the bag (names absolute, see
        :func:`normalize_topic`)."""
        if self._recovered is not None:
            return {normalize_topic(topic): msgtype for topic, msgtype in self._recovered.channels.values()}
        return {normalize_topic(name): info.msgtype for name, info in self._r.topics.items() if info.msgtype}

    def message_count(self, topics: Iterable[str] | None = None) -> int:
        """Number of messages on the given topics (all topics when None)."""
        wanted = _wanted(topics)
        rec = self._recovered
        if rec is not None:
            return sum(n for cid, n in rec.counts.items() if wanted is None or normalize_topic(rec.channels[cid][0]) in wanted)
        return sum(
            c.msgcount for c in self._r.connections if wanted is None or normalize_topic(c.topic) in wanted
        )

    @property
    def start_ns(self) -> int:
        if self._recovered is not None:
            return self._recovered.start_ns
        return int(self._r.start_time)

    @property
    def end_ns(self) -> int:
        if self._recovered is not None:
            return self._recovered.end_ns
        return int(self._r.end_time)

    @property
    def duration_s(self) -> float:
        return max(0, self.end_ns - self.start_ns) * 1e-9

    def messages(
        self,
        topics: Iterable[str] | None = None,
        start_ns: int | None = None,
        stop_ns: int | None = None,
    ) -> Iterator[BagMessage]:
        """Messages in log-time order, optionally restricted to topics and a time window.

        A bag that turns out to be truncated or corrupt part-way raises :class:`BagError`
        after the messages that could be read.
        """
        wanted = _wanted(topics)
        if self._recovered is not None:
            yield from self._recovered_messages(wanted, start_ns, stop_ns)
            return
        conns = [c for c in self._r.connections if wanted is None or normalize_topic(c.topic) in wanted]
        if not conns:
            return
        # Over the whole bag the count is known: a damaged index can otherwise lose messages
        # silently (e.g. an MCAP whose writer was interrupted inside a chunk flush).
        whole = (start_ns is None or start_ns <= self.start_ns) and (
            stop_ns is None or stop_ns >= self.end_ns
        )
        expected = sum(c.msgcount for c in conns) if whole else None
        count = 0
        ros1 = not self._r.is2
        try:
            # rosbags' connection ids are the MCAP channel ids: the same channels and types
            source = read_indexed_mcap(self.path, self._summary(), {c.id: c.msgtype for c in conns}, start_ns, stop_ns,
                                       _bag_message) \
                if self.fast_mcap and self.path.is_file() and self.path.suffix == '.mcap' else None
            if source is not None:
                for message in source:
                    count += 1
                    yield message
            else:
                for conn, timestamp, rawdata in self._r.messages(
                    connections=conns, start=start_ns, stop=stop_ns
                ):
                    count += 1
                    if ros1 and conn.msgtype in TYPESTORE.types:
                        # ROS 1 serialisation -> ROS 2 CDR (rosbags converts between the ROS 2
                        # definitions of a type, dropping e.g. Header.seq).
                        rawdata = TYPESTORE.ros1_to_cdr(bytes(rawdata), conn.msgtype)
                    yield BagMessage(normalize_topic(conn.topic), conn.msgtype, int(timestamp), bytes(rawdata))
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f'{self.path}: bag is damaged ({_reason(exc)})') from exc
        if expected is not None and count < expected:
            raise BagError(
                f'{self.path}: bag is damaged (only {count} of {expected} messages readable)'
            )

    def _summary(self) -> Any | None:
        """The MCAP file's summary, read once per open reader: a bench that asks for each topic
        in turn would otherwise parse the footer and the whole summary on every call."""
        if not self._mcap_summary:
            self._mcap_summary.append(read_mcap_summary(self.path))
        return self._mcap_summary[0]

    def _recovered_messages(
        self, wanted: set[str] | None, start_ns: int | None, stop_ns: int | None
    ) -> Iterator[BagMessage]:
        """The complete messages of an unfinished MCAP, streamed (sorted in memory only if the
        writer did not write them in log-time order). ``stop_ns`` is exclusive, like rosbags."""
        from mcap.records import Message

        rec = self._r
        ids = {cid for cid, (topic, _) in rec.channels.items() if wanted is None or normalize_topic(topic) in wanted}
        if not ids:
            return
        out: Iterator[BagMessage] = (
            BagMessage(normalize_topic(rec.channels[r.channel_id][0]), rec.channels[r.channel_id][1], int(r.log_time), bytes(r.data))
            for r in rec.records()
            if isinstance(r, Message) and r.channel_id in ids
            and (start_ns is None or r.log_time >= start_ns) and (stop_ns is None or r.log_time < stop_ns)
        )
        if not rec.ordered:
            out = iter(sorted(out, key=lambda m: m.log_time_ns))
        yield from out

    def deserialize(self, message: BagMessage) -> Any:
        """Decode a message into a rosbags message object."""
        return deserialize(message.rawdata, message.msgtype)

    def read_all(self, topic: str) -> list[tuple[int, Any]]:
        """Every message of one topic as (log time ns, decoded message), in order."""
        return [(m.log_time_ns, self.deserialize(m)) for m in self.messages([topic])]


def _bag_message(topic: str, msgtype: str, log_time_ns: int, data: bytes) -> BagMessage:
    return BagMessage(normalize_topic(topic), msgtype, log_time_ns, data)


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


#: Chunk compressions of MCAP output -> the ``mcap.writer.CompressionType`` member that writes
#: them (by name: importing mcap.writer loads zstandard and lz4, ~50 ms, so only a writer does).
#: zstd packs tighter, lz4 costs a quarter of its time (raw camera-sized images: ~1.2 vs ~5 ms
#: per MB on this machine; 2.8x vs 4.6x smaller).
MCAP_COMPRESSION_TYPES = {'zstd': 'ZSTD', 'lz4': 'LZ4', 'none': 'NONE'}
#: The compression names, in the order of :data:`MCAP_COMPRESSION_TYPES`.
MCAP_COMPRESSIONS = tuple(MCAP_COMPRESSION_TYPES)


class BagWriter:
    """Writes a bag as one ``.mcap`` file (default) or a rosbag2 sqlite3 directory.

    Topics are declared on first use from the message type; messages may be rosbags message
    objects or raw CDR bytes. The bag is always finalised by ``close`` (also on an exception
    inside the ``with`` block), so what was written stays readable.

    A process that is killed (SIGKILL, out of memory) never reaches ``close``: an MCAP then lacks
    its summary, and :class:`BagReader` recovers the chunks that reached the file. With
    ``flush_every_s`` the MCAP writer closes its chunk and flushes the file whenever the log
    time has advanced that far since the last flush, so at most that much bag time is at risk.
    The flush points depend only on the log times (not on the wall clock), so two writes of the
    same messages still give identical files.
    """

    def __init__(
        self,
        path: str | Path,
        storage: StorageFormat | None = None,
        overwrite: bool = False,
        *,
        flush_every_s: float | None = None,
        chunk_size: int = 1024 * 1024,
        latched_topics: Iterable[str] = LATCHED_TOPICS,
        compression: str = 'zstd',
    ) -> None:
        self.path = Path(path)
        if compression not in MCAP_COMPRESSIONS:
            raise BagError(f'unknown MCAP compression {compression!r} (use {", ".join(MCAP_COMPRESSIONS)})')
        self.compression = compression
        self.latched_topics = {normalize_topic(t) for t in latched_topics}
        if storage is None:
            storage = 'mcap' if self.path.suffix in ('.mcap', '') else 'sqlite3'
            if self.path.suffix == '.db3':
                storage = 'sqlite3'
        if storage not in ('mcap', 'sqlite3'):
            raise BagError(f'unknown bag storage {storage!r} (use mcap or sqlite3)')
        self.storage: StorageFormat = storage
        self.overwrite = overwrite
        self._channels: dict[str, tuple[Any, str]] = {}
        self._impl: Any = None
        self._file: Any = None
        self._count = 0
        self.chunk_size = int(chunk_size)
        self._flush_every_ns = None if flush_every_s is None else int(flush_every_s * 1e9)
        self._last_flush_ns: int | None = None

    def __enter__(self) -> 'BagWriter':
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def message_count(self) -> int:
        return self._count

    def open(self) -> None:
        target = self.path
        if target.exists():
            if not self.overwrite:
                raise BagError(f'{target}: already exists (choose another name or overwrite)')
            if target.is_dir():
                import shutil

                shutil.rmtree(target)
            else:
                target.unlink()
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            if self.storage == 'mcap':
                from mcap.writer import CompressionType, Writer

                if target.suffix != '.mcap':
                    target = self.path = target.with_suffix('.mcap')
                self._file = open(target, 'wb')
                kind = CompressionType[MCAP_COMPRESSION_TYPES[self.compression]]
                self._impl = Writer(self._file, compression=kind, chunk_size=self.chunk_size)
                self._impl.start(profile='ros2', library='ar_tracking')
            else:
                from rosbags.rosbag2 import StoragePlugin, Writer as Rosbag2Writer

                self._impl = Rosbag2Writer(target, version=9, storage_plugin=StoragePlugin.SQLITE3)
                self._impl.open()
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f'{target}: cannot create bag ({_reason(exc)})') from exc

    def add_topic(self, topic: str, msgtype: str, latched: bool | None = None) -> None:
        """Declare a topic; a topic may have only one type. Its offered_qos_profiles say
        latched (``latched``; default: the topic is one of ``latched_topics``) or volatile."""
        if topic in self._channels:
            if self._channels[topic][1] != msgtype:
                raise BagError(
                    f'{self.path}: topic {topic} already has type {self._channels[topic][1]}'
                )
            return
        try:
            msg_class(msgtype)  # unknown types fail here with a clear message
        except BagError as exc:
            raise BagError(f'{self.path}: {exc}') from exc
        qos = offered_qos(normalize_topic(topic) in self.latched_topics if latched is None else latched)
        if self.storage == 'mcap':
            import io

            import yaml
            from rosbags.rosbag2.metadata import dump_qos_v9

            msgdef, _ = TYPESTORE.generate_msgdef(msgtype, ros_version=2)
            schema_id = self._impl.register_schema(
                name=msgtype, encoding='ros2msg', data=msgdef.encode()
            )
            text = io.StringIO()
            yaml.safe_dump(dump_qos_v9([qos]), text, sort_keys=False)
            channel = self._impl.register_channel(
                topic=topic, message_encoding='cdr', schema_id=schema_id,
                metadata={'offered_qos_profiles': text.getvalue().strip()},
            )
        else:
            channel = self._impl.add_connection(topic, msgtype, typestore=TYPESTORE, offered_qos_profiles=[qos])
        self._channels[topic] = (channel, msgtype)

    def write(self, topic: str, log_time_ns: int, msg: Any, msgtype: str | None = None) -> None:
        """Append one message (rosbags object, or CDR bytes together with ``msgtype``)."""
        if self._impl is None:
            raise BagError(f'{self.path}: bag is not open for writing')
        if isinstance(msg, (bytes, bytearray, memoryview)):
            if msgtype is None and topic not in self._channels:
                raise BagError(f'{topic}: raw data needs a message type')
            rawdata = bytes(msg)
        else:
            msgtype = msgtype or msg.__msgtype__
            rawdata = serialize(msg)
        if msgtype is not None:
            self.add_topic(topic, msgtype)  # declares the topic, or checks it keeps one type
        channel, _ = self._channels[topic]
        log_time_ns = int(log_time_ns)
        if self.storage == 'mcap':
            self._impl.add_message(
                channel_id=channel,
                log_time=log_time_ns,
                data=rawdata,
                publish_time=log_time_ns,
                sequence=self._count & 0xFFFFFFFF,
            )
            if self._flush_every_ns is not None:
                if self._last_flush_ns is None:
                    self._last_flush_ns = log_time_ns
                elif log_time_ns - self._last_flush_ns >= self._flush_every_ns:
                    self.flush()
                    self._last_flush_ns = log_time_ns
        else:
            self._impl.write(channel, log_time_ns, rawdata)
        self._count += 1

    def flush(self) -> None:
        """Close the MCAP chunk in progress and flush the file to the OS (so that a kill of
        this process loses nothing written so far); a no-op for sqlite3."""
        if self._impl is None:
            raise BagError(f'{self.path}: bag is not open for writing')
        if self.storage == 'mcap':
            try:
                self._impl.flush()
            except Exception as exc:
                raise BagError(f'{self.path}: cannot flush bag ({_reason(exc)})') from exc

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """Attach a named string map to the bag (MCAP metadata record; ignored for sqlite3).

        The graph runner records where an output bag came from, so that ``evaluate`` can find
        the input bag again (e.g. to re-run a core on its images)."""
        if self._impl is None:
            raise BagError(f'{self.path}: bag is not open for writing')
        if self.storage == 'mcap':
            self._impl.add_metadata(name, {str(k): str(v) for k, v in data.items()})

    def close(self) -> None:
        """Finalise the bag (index, summary, metadata). Safe to call twice."""
        if self._impl is None:
            return
        impl, self._impl = self._impl, None
        try:
            if self.storage == 'mcap':
                impl.finish()
            else:
                impl.close()
        except Exception as exc:  # e.g. a writer left inconsistent by an interrupted write
            raise BagError(f'{self.path}: cannot finalise bag ({_reason(exc)})') from exc
        finally:
            if self._file is not None:
                self._file.close()
                self._file = None


def stamp_to_ns(stamp: Any) -> int:
    """Integer nanoseconds of a builtin_interfaces/Time (rosbags or rclpy object)."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def ns_to_stamp(ns: int) -> Any:
    """A rosbags builtin_interfaces/Time for integer nanoseconds (non-negative)."""
    Time = msg_class('builtin_interfaces/msg/Time')
    ns = int(ns)
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def read_metadata(path: str | Path, name: str) -> dict[str, str] | None:
    """The metadata record ``name`` of an MCAP file (None if absent or not an MCAP file)."""
    path = Path(path)
    if path.suffix != '.mcap' or not path.is_file():
        return None
    if is_unfinished_mcap(path):
        try:
            return scan_unfinished_mcap(path).metadata.get(name)
        except BagError as exc:
            logger.debug('%s: no metadata (%s)', path, exc)
            return None
    try:
        from mcap.reader import make_reader

        with open(path, 'rb') as f:
            for record in make_reader(f).iter_metadata():
                if record.name == name:
                    return dict(record.metadata)
    except Exception as exc:  # a damaged file: no metadata, the readers will say why
        logger.debug('%s: no metadata (%s)', path, exc)
    return None
