#!/usr/bin/env python3
"""How fast the RTU framer finds a valid reply behind garbage (issue 6: "Resync").

A reply to FC 03 (10 registers) preceded by 1, 16, 256, 4096 and 65536 bytes of
random garbage is fed to an RtuFramer that expects it, as the client sets it up,
in chunks of CHUNK bytes (a serial read delivers what has arrived).  For each:
was the reply recovered, how long did consuming everything take, and the peak
number of bytes the framer held.  Target: 64 KiB of garbage in well under 50 ms.

With --no-request the framer expects nothing (as when decoding a capture): every offset
before a known function code is judged then, not only those that may concern the
request, so it is slower.

With --device the device's framer (DeviceRtuFramer: mbtool serve, sim://) reads a valid
FC 03 request behind the garbage instead; it also holds a would-be frame with an unknown
function code until one maximal ADU follows it, since only silence could end it.  Target:
64 KiB of garbage in well under 100 ms.

Times are the best and the median of --repeat runs (the median says more on a busy machine).

    python bench/resync.py [--chunk 256] [--seed 1] [--repeat 5] [--no-request | --device]
"""

from __future__ import annotations

import argparse
import random
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mbtool.codec.data_access import ReadHoldingRegisters  # noqa: E402
from mbtool.codec.framer import Frame  # noqa: E402
from mbtool.codec.rtu import DeviceRtuFramer, RtuFramer  # noqa: E402

SIZES = (1, 16, 256, 4096, 65536)
UNIT = 0x11


def garbage(rng: random.Random, size: int, reply: bytes) -> bytes:
    data = bytearray(rng.randbytes(size))
    # Garbage that never completes a frame by chance: a stray copy of the reply would be "recovered" early.
    while reply in data:
        data = bytearray(rng.randbytes(size))
    return bytes(data)


def feed(stream: bytes, chunk: int, request, device: bool = False) -> tuple[bool, float, int]:
    """Feed the stream chunk by chunk, draining events after each, then silence: (was the frame
    from UNIT found, seconds taken, peak bytes held).  A device framer expects nothing."""
    framer = DeviceRtuFramer() if device else RtuFramer()
    if request is not None and not device:
        framer.expect = request
        framer.expect_unit = UNIT
    recovered, peak = False, 0
    start = time.perf_counter()
    for i in range(0, len(stream), chunk):
        framer.feed(stream[i : i + chunk])
        peak = max(peak, framer.buffered)
        while (event := framer.next_event()) is not None:
            recovered |= isinstance(event, Frame) and event.unit == UNIT
        peak = max(peak, framer.buffered)
    while (event := framer.silence()) is not None:
        recovered |= isinstance(event, Frame) and event.unit == UNIT
    return recovered, time.perf_counter() - start, peak


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--chunk", type=int, default=256, help="bytes per read")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--repeat", type=int, default=5, help="runs per size")
    side = parser.add_mutually_exclusive_group()
    side.add_argument("--no-request", action="store_true", help="the framer expects no reply")
    side.add_argument("--device", action="store_true", help="the device's framer reads a request")
    args = parser.parse_args()
    rng = random.Random(args.seed)
    request = None if args.no_request else ReadHoldingRegisters(0, 10)
    if args.device:
        wanted = RtuFramer().build(UNIT, request.encode())
        expecting = "device framer, an FC03 request behind the garbage"
    else:
        body = bytes([UNIT, 3, 20]) + bytes(range(20))
        wanted = RtuFramer().build(UNIT, body[1:])
        expecting = "no request" if request is None else "a reply to FC03 expected"
    ok = True
    print(f"RTU resync, {expecting}, chunks of {args.chunk} bytes, seed {args.seed}, {args.repeat} runs")
    for size in SIZES:
        stream = garbage(rng, size, wanted) + wanted
        runs = [feed(stream, args.chunk, request, args.device) for _ in range(args.repeat)]
        recovered = all(r for r, _, _ in runs)
        best = min(t for _, t, _ in runs)
        median = statistics.median(t for _, t, _ in runs)
        peak = max(p for _, _, p in runs)
        ok &= recovered
        print(
            f"garbage {size:6d} B: recovered {'yes' if recovered else 'NO '}  "
            f"best {best * 1000:8.2f} ms  median {median * 1000:8.2f} ms  "
            f"({size / median / 1e6 if median else 0:6.2f} MB/s)  peak buffer {peak} B"
        )
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
