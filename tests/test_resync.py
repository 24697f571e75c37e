"""RTU resync through garbage stays linear and bounded (bench/resync.py measures it; issue 6).

Before each offset was judged once, every garbage byte rescanned the buffer and
64 KiB took about a second; the bound here is loose enough for a loaded CI box.
"""

from __future__ import annotations

import importlib.util
import random
from pathlib import Path

import pytest

from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.codec.framing import RTU_MAX_ADU, RtuFramer

spec = importlib.util.spec_from_file_location(
    "resync", Path(__file__).resolve().parent.parent / "bench/resync.py"
)
resync = importlib.util.module_from_spec(spec)
spec.loader.exec_module(resync)


@pytest.mark.parametrize(("size", "chunk"), [(1, 1), (16, 3), (256, 1), (4096, 1), (65536, 256)])
def test_reply_behind_garbage_is_recovered_with_a_bounded_buffer(size, chunk):
    reply = RtuFramer().build(resync.UNIT, bytes([3, 20]) + bytes(range(20)))
    stream = resync.garbage(random.Random(size), size, reply) + reply
    recovered, elapsed, peak = resync.feed(stream, chunk, ReadHoldingRegisters(0, 10))
    assert recovered
    assert peak <= 2 * RTU_MAX_ADU + chunk
    assert elapsed < 2.0
