"""The MCAP compressions are named once (io.bags.MCAP_COMPRESSION_TYPES): the tuple the CLI
and the writer check against is that table's keys, and each names a CompressionType member."""
from __future__ import annotations

import pytest
from mcap.writer import CompressionType

from ar_tracking.io.bags import MCAP_COMPRESSION_TYPES, MCAP_COMPRESSIONS, BagError, BagWriter


def test_the_tuple_is_the_table():
    assert MCAP_COMPRESSIONS == ('zstd', 'lz4', 'none')
    assert MCAP_COMPRESSIONS == tuple(MCAP_COMPRESSION_TYPES)
    assert {CompressionType[v] for v in MCAP_COMPRESSION_TYPES.values()} == set(CompressionType)


def test_unknown_compression_names_the_known_ones(tmp_path):
    with pytest.raises(BagError, match='zstd, lz4, none'):
        BagWriter(tmp_path / 'b.mcap', compression='gzip')
