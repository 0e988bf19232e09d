"""The compact chunk table of the MCAP scan behaves as the list of chunks it replaces."""

from __future__ import annotations

import pytest

from imunoise.daq.mcap_layout import ChunkInfo, ChunkTable


def _chunk(i: int, mi: dict[int, tuple[int, int]] | None = None) -> ChunkInfo:
    return ChunkInfo(1000 * i, 1000 * i + 900, 10**18 + i, 10**18 + i + 5, 4096 + i,
                     2**32 - 1 - i, "zstd" if i % 3 else "", 1000 * i + 50, 800,
                     {} if mi is None else mi, 1000 * i + 990, i % 2 == 0)


def test_round_trip_and_live_last_chunk():
    table = ChunkTable()
    chunks = [_chunk(i, {1: (i, 10 + i), 3: (2 * i, 7)} if i % 4 else {}) for i in range(3000)]
    for c in chunks:
        table.append(c)
    assert len(table) == 3000 and bool(table)
    assert list(table) == chunks
    assert list(reversed(table)) == chunks[::-1]
    assert table[5:9] == chunks[5:9] and table[-1] is chunks[-1]
    assert table.uncompressed_sizes() == [c.uncompressed_size for c in chunks]
    # the last chunk is live: the scan and the repair complete it in place
    table[-1].mi[9] = (123, 4)
    assert table[2999].mi[9] == (123, 4)
    # earlier chunks are copies: a change is stored back by assignment
    c = table[10]
    c.walked = False
    c.mi = {2: (5, 6)}
    assert table[10] == chunks[10] and table[10].walked
    table[10] = c
    assert table[10] == c and table[11] == chunks[11]
    with pytest.raises(IndexError):
        table[3000]
    assert len(ChunkTable()) == 0 and not ChunkTable()
