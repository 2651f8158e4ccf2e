"""Recovery of an unfinished MCAP: a single ``.mcap`` file whose writer was killed before it
wrote the summary (SIGKILL, out of memory, power loss).

Index-based readers refuse such a file; a streaming read finds every complete chunk (CRC
checked) and what it holds. :class:`~ar_tracking.io.bags.BagReader` and
:func:`~ar_tracking.io.bags.read_metadata` use this module; both names below are re-exported
by :mod:`ar_tracking.io.bags`.
"""
from __future__ import annotations

import logging
import os
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from .errors import BagError

# The bag module's logger: the recovery warning is the bag reader's message.
logger = logging.getLogger('ar_tracking.io.bags')

#: The 8 bytes an MCAP file starts and (when its writer finished it) ends with.
MCAP_MAGIC = b'\x89MCAP0\r\n'


def is_unfinished_mcap(path: str | Path) -> bool:
    """True for a single ``.mcap`` file that starts like an MCAP but lacks the end magic: its
    writer was killed (SIGKILL, out of memory, power loss) before writing the summary, so
    index-based readers (rosbags, ``mcap.reader.make_reader`` over a seekable file) refuse it.
    """
    path = Path(path)
    try:
        if not path.is_file() or path.stat().st_size < 2 * len(MCAP_MAGIC):
            return False
        with open(path, 'rb') as f:
            head = f.read(len(MCAP_MAGIC))
            f.seek(-len(MCAP_MAGIC), os.SEEK_END)
            tail = f.read(len(MCAP_MAGIC))
    except OSError:
        return False
    return head == MCAP_MAGIC and tail != MCAP_MAGIC


class _ExactReads:
    """A file wrapper whose ``read(n)`` returns n bytes or raises EOFError, so that the mcap
    stream reader stops at a record cut by the truncation instead of parsing a short read."""

    def __init__(self, f: Any) -> None:
        self._f = f

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        if n is not None and n > 0 and len(data) < n:
            raise EOFError('end of an unfinished MCAP')
        return data


@dataclass
class RecoveredMcap:
    """What a streaming read finds in an unfinished MCAP: every complete chunk's channels,
    schemas and message counts, and the metadata records (see :func:`scan_unfinished_mcap`)."""

    path: Path
    #: channel id -> (topic, message type)
    channels: dict[int, tuple[str, str]] = field(default_factory=dict)
    #: channel id -> number of recoverable messages
    counts: dict[int, int] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    #: True when the file holds the messages in non-decreasing log time (then reading streams).
    ordered: bool = True
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    #: bytes of the file after the last complete record (what the kill cut off mid-write)
    lost_tail_bytes: int = 0

    @property
    def message_count(self) -> int:
        return sum(self.counts.values())

    def records(self) -> Iterator[Any]:
        """The records of the complete part of the file, in file order (chunks opened, their
        CRCs checked: a chunk cut by the kill yields nothing)."""
        from mcap.stream_reader import StreamReader

        with open(self.path, 'rb') as f:
            reader = StreamReader(_ExactReads(f), validate_crcs=True)  # type: ignore[arg-type]
            try:
                yield from reader.records
            except Exception as exc:  # the truncation (EOF, bad CRC, cut zstd frame)
                logger.debug('%s: stream read stops: %s', self.path, exc)


#: Scans of unfinished MCAPs by (path, size, mtime): evaluate opens one bag many times.
_recovered_cache: dict[tuple[str, int, int], RecoveredMcap] = {}
_recovered_lock = threading.Lock()


def scan_unfinished_mcap(path: str | Path) -> RecoveredMcap:
    """Stream through an unfinished MCAP and index what can be recovered.

    Logs one warning per file (per process): 'recovered N messages from an unfinished MCAP (the
    writer was killed)'. Raises :class:`BagError` when not one complete message is left.
    """
    from mcap.records import Channel, Chunk, Message, Metadata, Schema

    path = Path(path)
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    with _recovered_lock:
        cached = _recovered_cache.get(key)
    if cached is not None:
        return cached
    rec = RecoveredMcap(path)
    schemas: dict[int, str] = {}
    pending_channels: dict[int, Any] = {}
    last_time = None
    end_of_good = 0
    from mcap.stream_reader import StreamReader

    with open(path, 'rb') as f:
        reader = StreamReader(_ExactReads(f), validate_crcs=True, emit_chunks=True)  # type: ignore[arg-type]
        from mcap.stream_reader import breakup_chunk

        try:
            for record in reader.records:
                inner = breakup_chunk(record, validate_crc=True) if isinstance(record, Chunk) else [record]
                for r in inner:
                    if isinstance(r, Schema):
                        schemas[r.id] = r.name
                    elif isinstance(r, Channel):
                        pending_channels[r.id] = r
                    elif isinstance(r, Message):
                        if r.channel_id not in rec.channels:
                            ch = pending_channels.get(r.channel_id)
                            if ch is None or ch.schema_id not in schemas:
                                continue  # a message whose channel was lost: nothing to decode it with
                            rec.channels[r.channel_id] = (ch.topic, schemas[ch.schema_id])
                        t = int(r.log_time)
                        rec.counts[r.channel_id] = rec.counts.get(r.channel_id, 0) + 1
                        if last_time is None:
                            rec.start_ns = rec.end_ns = t
                        else:
                            rec.ordered = rec.ordered and t >= last_time
                            rec.start_ns = min(rec.start_ns, t)
                            rec.end_ns = max(rec.end_ns, t)
                        last_time = t
                    elif isinstance(r, Metadata):
                        rec.metadata[r.name] = dict(r.metadata)
                end_of_good = f.tell()
        except Exception as exc:  # the truncation: EOF inside a record, a cut chunk
            logger.debug('%s: stream read stops after %d bytes: %s', path, end_of_good, exc)
    rec.lost_tail_bytes = max(0, st.st_size - end_of_good)
    if rec.message_count == 0:
        raise BagError(
            f'{path}: not a readable bag (an unfinished MCAP without one complete chunk: '
            'its writer was killed before the first flush)'
        )
    logger.warning(
        'recovered %d messages from an unfinished MCAP (the writer was killed): %s',
        rec.message_count, path,
    )
    with _recovered_lock:
        _recovered_cache[key] = rec
    return rec

