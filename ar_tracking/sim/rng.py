"""Seeded random streams: every random draw of the simulator comes from one named stream.

Streams are derived from the seed and names with CRC32 (not Python's salted ``hash``), so the
same arguments give the same bags on every run and machine; a new stream never shifts an old one.
"""
from __future__ import annotations

import numpy as np


def rng_stream(seed: int, *names: str | int) -> np.random.Generator:
    """An independent, reproducible random stream for one purpose (no salted hashing)."""
    import zlib

    keys = [int(seed) & 0xFFFFFFFF]
    for n in names:
        keys.append(zlib.crc32(n.encode()) if isinstance(n, str) else int(n) & 0xFFFFFFFF)
    return np.random.default_rng(np.random.SeedSequence(keys))
