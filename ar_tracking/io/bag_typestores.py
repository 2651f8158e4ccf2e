"""rosbags' AnyReader with the typestore of a bag's message definitions built once per process,
and rosbags' QoS profiles parsed once per distinct text.

Opening a bag, AnyReader parses every connection's message definition (a PEG parser in pure
Python) and registers the resulting classes in a fresh typestore: ~0.1 s per open, most of
the open, although the package reads the same few kinds of bag again and again (an output bag
is opened by each area of an evaluation, by the report, the benches, the tests). The typestore
depends on nothing but the definitions (type names, their text and digests) and the ROS
version of the bag, so the reader keeps the one it built for each such set and uses it again.
A set whose typestore could not be built (a digest mismatch, a definition that does not
parse) is not kept: the next open raises the same error again.

rosbag2 records each topic's offered QoS profiles as a YAML text, which rosbags parses with
ruamel.yaml for every channel of every open (~10 ms each: a 15-topic output bag took 0.2 s to
open). The texts are few (latched or not, mostly); :func:`_parse_qos` keeps the parsed
profiles of each text (immutable named tuples, handed out in a new list each time).
"""
from __future__ import annotations

import functools
from typing import Any

from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import metadata, reader as rosbag2_reader, storage_mcap, storage_sqlite3

#: (ROS 2?, the connections' (type, definition format, definition, digest)) -> typestore
_TYPESTORES: dict[tuple[Any, ...], Any] = {}


@functools.lru_cache(maxsize=256)
def _parsed_qos(text: str) -> tuple[Any, ...]:
    return tuple(_PARSE_QOS(text))


def _parse_qos(dcts: Any) -> list[Any]:
    """rosbags.rosbag2.metadata.parse_qos, its result for a text kept (module docstring); a
    text that does not parse raises each time."""
    return list(_parsed_qos(dcts)) if isinstance(dcts, str) else _PARSE_QOS(dcts)


_PARSE_QOS = metadata.parse_qos
for _module in (rosbag2_reader, storage_mcap, storage_sqlite3):  # each imported it by name
    if getattr(_module, 'parse_qos', None) is _PARSE_QOS:
        _module.parse_qos = _parse_qos


class _Opened:
    """An already opened rosbags reader, entered again by AnyReader._open as a no-op."""

    def __init__(self, reader: Any) -> None:
        self.connections = reader.connections

    def __enter__(self) -> '_Opened':
        return self

    def __exit__(self, *exc: object) -> None:
        return None


class CachedTypesReader(AnyReader):
    """AnyReader whose typestore comes from the per-process cache when the same definitions
    were seen before (module docstring); everything else is AnyReader's."""

    def _open(self) -> None:
        for reader in self.readers:
            self.stack.enter_context(reader)
        connections = [c for reader in self.readers for c in reader.connections]
        key = (self.is2, id(self.default_typestore),
               tuple((c.msgtype, c.msgdef.format, c.msgdef.data, c.digest) for c in connections))
        typestore = _TYPESTORES.get(key)
        if typestore is not None:
            self.connections = connections
            self.typestore = typestore
            return
        readers = self.readers
        self.readers = [_Opened(r) for r in readers]  # AnyReader builds the typestore
        try:
            super()._open()
        finally:
            self.readers = readers
        _TYPESTORES[key] = self.typestore
