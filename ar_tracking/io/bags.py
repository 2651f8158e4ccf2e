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

logger = logging.getLogger(__name__)

#: The message definitions of ROS 2 Jazzy, used to (de)serialise and to describe topics in
#: written bags. It knows every standard message the package uses.
TYPESTORE = get_typestore(Stores.ROS2_JAZZY)

StorageFormat = Literal['mcap', 'sqlite3']


class BagError(Exception):
    """A bag cannot be opened, read or written. The message is one line meant for the user."""


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

    def __enter__(self) -> 'BagReader':
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Open the bag; :class:`BagError` with the reason if it cannot be read."""
        from rosbags.highlevel import AnyReader

        if not self.path.exists():
            raise BagError(f'{self.path}: no such bag')
        try:
            reader = AnyReader([self.path], default_typestore=TYPESTORE)
            reader.open()
        except Exception as exc:
            raise BagError(f'{self.path}: not a readable bag ({_reason(exc)})') from exc
        self._reader = reader

    def close(self) -> None:
        if self._reader is not None:
            try:
                self._reader.close()
            finally:
                self._reader = None

    @property
    def _r(self) -> Any:
        if self._reader is None:
            raise BagError(f'{self.path}: bag is not open')
        return self._reader

    @property
    def topics(self) -> dict[str, str]:
        """Topic name -> message type, for every topic in the bag."""
        return {name: info.msgtype for name, info in self._r.topics.items() if info.msgtype}

    def message_count(self, topics: Iterable[str] | None = None) -> int:
        """Number of messages on the given topics (all topics when None)."""
        wanted = None if topics is None else set(topics)
        return sum(
            c.msgcount for c in self._r.connections if wanted is None or c.topic in wanted
        )

    @property
    def start_ns(self) -> int:
        return int(self._r.start_time)

    @property
    def end_ns(self) -> int:
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
        wanted = None if topics is None else set(topics)
        conns = [c for c in self._r.connections if wanted is None or c.topic in wanted]
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
            for conn, timestamp, rawdata in self._r.messages(
                connections=conns, start=start_ns, stop=stop_ns
            ):
                count += 1
                if ros1 and conn.msgtype in TYPESTORE.types:
                    # ROS 1 serialisation -> ROS 2 CDR (rosbags converts between the ROS 2
                    # definitions of a type, dropping e.g. Header.seq).
                    rawdata = TYPESTORE.ros1_to_cdr(bytes(rawdata), conn.msgtype)
                yield BagMessage(conn.topic, conn.msgtype, int(timestamp), bytes(rawdata))
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f'{self.path}: bag is damaged ({_reason(exc)})') from exc
        if expected is not None and count < expected:
            raise BagError(
                f'{self.path}: bag is damaged (only {count} of {expected} messages readable)'
            )

    def deserialize(self, message: BagMessage) -> Any:
        """Decode a message into a rosbags message object."""
        return deserialize(message.rawdata, message.msgtype)

    def read_all(self, topic: str) -> list[tuple[int, Any]]:
        """Every message of one topic as (log time ns, decoded message), in order."""
        return [(m.log_time_ns, self.deserialize(m)) for m in self.messages([topic])]


def _reason(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return text[0] if text else type(exc).__name__


class BagWriter:
    """Writes a bag as one ``.mcap`` file (default) or a rosbag2 sqlite3 directory.

    Topics are declared on first use from the message type; messages may be rosbags message
    objects or raw CDR bytes. The bag is always finalised by ``close`` (also on an exception
    inside the ``with`` block), so what was written stays readable.
    """

    def __init__(
        self,
        path: str | Path,
        storage: StorageFormat | None = None,
        overwrite: bool = False,
    ) -> None:
        self.path = Path(path)
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
                self._impl = Writer(self._file, compression=CompressionType.ZSTD)
                self._impl.start(profile='ros2', library='ar_tracking')
            else:
                from rosbags.rosbag2 import StoragePlugin, Writer as Rosbag2Writer

                self._impl = Rosbag2Writer(target, version=9, storage_plugin=StoragePlugin.SQLITE3)
                self._impl.open()
        except BagError:
            raise
        except Exception as exc:
            raise BagError(f'{target}: cannot create bag ({_reason(exc)})') from exc

    def add_topic(self, topic: str, msgtype: str) -> None:
        """Declare a topic; a topic may have only one type."""
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
        if self.storage == 'mcap':
            msgdef, _ = TYPESTORE.generate_msgdef(msgtype, ros_version=2)
            schema_id = self._impl.register_schema(
                name=msgtype, encoding='ros2msg', data=msgdef.encode()
            )
            channel = self._impl.register_channel(
                topic=topic, message_encoding='cdr', schema_id=schema_id
            )
        else:
            channel = self._impl.add_connection(topic, msgtype, typestore=TYPESTORE)
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
        else:
            self._impl.write(channel, log_time_ns, rawdata)
        self._count += 1

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
    try:
        from mcap.reader import make_reader

        with open(path, 'rb') as f:
            for record in make_reader(f).iter_metadata():
                if record.name == name:
                    return dict(record.metadata)
    except Exception as exc:  # a damaged file: no metadata, the readers will say why
        logger.debug('%s: no metadata (%s)', path, exc)
    return None
