#!/usr/bin/env python3
"""Fuzz the framers and the client's receive path with random and mutated reply frames (issue 6).

For each framing (RTU, ASCII, TCP), N random and N mutated frames go through

* the decoder: a framer reading replies, with ``expect`` set as the client sets it,
  fed in random chunks, then ended by silence; each Frame decoded as the reply;
* the receive path: a Client over a fake link that delivers the bytes in random
  chunks and then stays silent (a fake clock, so timeouts cost no real time).

Mutations start from valid replies to requests of every function code, built by
the codec and answered by the built-in device (sim://), exception replies too.
Every outcome must be a decoded reply or one of mbtool's own errors; anything else is a
crash, printed with its input (hex) so it can become a regression test.

    python scripts/fuzz.py --frames 2000 --seed 1            # every framer
    python scripts/fuzz.py --frames 1000000 --framer rtu     # the long run, one framing
"""

from __future__ import annotations

import argparse
import random
import sys
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from mbtool.codec.errors import ProtocolError  # noqa: E402
from mbtool.codec.framer import Frame  # noqa: E402
from mbtool.codec.framing import make_framer  # noqa: E402
from mbtool.codec.pdu import decode_request  # noqa: E402
from mbtool.errors import KNOWN_ERRORS  # noqa: E402
from mbtool.link.client import Client  # noqa: E402
from mbtool.link.transport import Transport  # noqa: E402

# One request of every function code, as PDUs; the built-in device answers them.
REQUESTS = [
    "01 0000 0010",
    "02 0000 0008",
    "03 0000 000A",
    "04 0010 0004",
    "05 00AD FF00",
    "06 0064 0005",
    "07",
    "08 0000 A537",
    "08 000B 0000",
    "08 0015 0003",
    "0B",
    "0C",
    "0F 0014 0004 01 0D",
    "10 0000 0002 04 0001 0002",
    "11",
    "14 0E 06 0004 0001 0002 06 0003 0009 0002",
    "15 09 06 0004 0007 0001 06AF",
    "16 0004 00F2 0025",
    "17 0000 0003 000A 0002 04 0007 0008",
    "18 00C8",
    "2B 0E 01 00",
    "2B 0E 03 00",
    "2B 0E 04 01",
]
UNIT = 1
PROGRESS_EVERY = 50_000  # frames between progress lines on stderr
TRANSACTION_ID = 1  # the id a new Client gives its first request


def seeds() -> list[tuple[object, bytes]]:
    """(request, reply PDU) pairs: the device's answer to each request, and an exception reply."""
    from mbtool.device.device import Device
    from mbtool.device.model import demo_model

    device = Device(demo_model())
    pairs = []
    for text in REQUESTS:
        pdu = bytes.fromhex(text)
        request = decode_request(pdu)
        reply = device.handle(UNIT, pdu)
        if reply is None:
            raise SystemExit(f"fuzz: the device does not answer {text}")
        pairs.append((request, reply))
        pairs.append((request, bytes([pdu[0] | 0x80, 0x02])))
    return pairs


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds


class Feed(Transport):
    """Delivers the fuzzed bytes in the chunks given, then silence: time passes, nothing comes."""

    def __init__(self, clock: FakeClock, chunks: list[bytes]) -> None:
        self.clock = clock
        self.chunks = chunks

    def write(self, data: bytes) -> None:
        pass

    def read(self, timeout: float) -> bytes:
        if self.chunks:
            return self.chunks.pop(0)
        self.clock.now += timeout
        return b""


# --- inputs ----------------------------------------------------------------------------------


def random_frame(rng: random.Random, framing: str) -> bytes:
    size = rng.choice((rng.randrange(0, 12), rng.randrange(0, 300), rng.randrange(250, 700)))
    if framing == "ascii" and rng.random() < 0.7:
        # Mostly the alphabet of an ASCII frame, so the parser gets past the ':' search.
        alphabet = b"0123456789ABCDEF:\r\n" + bytes([rng.randrange(256)])
        body = bytes(rng.choice(alphabet) for _ in range(size))
        return b":" + body if rng.random() < 0.5 else body
    if framing == "tcp" and rng.random() < 0.5:
        # A plausible MBAP header in front of random bytes: the length field decides.
        length = rng.choice((0, 1, 2, rng.randrange(0, 300), 254, 255, 0xFFFF))
        head = TRANSACTION_ID.to_bytes(2, "big") + b"\0\0" + length.to_bytes(2, "big") + bytes([UNIT])
        return head + rng.randbytes(size)
    return rng.randbytes(size)


def mutate(rng: random.Random, adu: bytes, others: list[bytes]) -> bytes:
    data = bytearray(adu)
    for _ in range(rng.randint(1, 4)):
        op = rng.randrange(9)
        at = rng.randrange(len(data) + 1)
        if op == 0 and data:  # flip a bit
            i = rng.randrange(len(data))
            data[i] ^= 1 << rng.randrange(8)
        elif op == 1 and data:  # set a byte to a boundary value
            data[rng.randrange(len(data))] = rng.choice((0, 1, 0x7F, 0x80, 0xFE, 0xFF, rng.randrange(256)))
        elif op == 2:  # insert bytes
            data[at:at] = rng.randbytes(rng.randint(1, 8))
        elif op == 3 and data:  # delete bytes
            del data[at : at + rng.randint(1, 8)]
        elif op == 4:  # truncate
            del data[at:]
        elif op == 5 and data:  # repeat a slice
            start = rng.randrange(len(data))
            data[at:at] = data[start : start + rng.randint(1, 16)]
        elif op == 6:  # splice another valid frame in
            data[at:at] = rng.choice(others)
        elif op == 7:  # garbage before or after
            garbage = rng.randbytes(rng.randint(1, 32))
            data = bytearray(garbage) + data if rng.random() < 0.5 else data + garbage
        elif op == 8 and len(data) > 5:  # a lying byte count or MBAP length field
            i = rng.choice((2, 4, 5)) if len(data) > 6 else 2
            data[i] = rng.choice((0, 1, 2, 0xFF, rng.randrange(256)))
    return bytes(data)


def chunks(rng: random.Random, data: bytes) -> list[bytes]:
    if rng.random() < 0.3:
        return [data]
    out, i = [], 0
    while i < len(data):
        n = rng.choice((1, rng.randint(1, 16), rng.randint(1, 300)))
        out.append(data[i : i + n])
        i += n
    return out


# --- the two paths under test ----------------------------------------------------------------


def through_decoder(framing: str, request, parts: list[bytes]) -> str:
    framer = make_framer(framing)
    framer.expect = request
    framer.expect_unit = UNIT
    outcome = "no frame"
    events = []
    for part in parts:
        framer.feed(part)
        while (event := framer.next_event()) is not None:
            events.append(event)
    while (event := framer.silence()) is not None:
        events.append(event)
    for event in events:
        if isinstance(event, Frame):
            try:
                request.decode_response(event.pdu)
                outcome = "decoded"
            except ProtocolError as error:
                outcome = type(error).__name__
        elif outcome == "no frame":
            outcome = "rejected"
    return outcome


def through_client(framing: str, request, parts: list[bytes]) -> str:
    clock = FakeClock()
    client = Client(
        Feed(clock, list(parts)), make_framer(framing), timeout=0.5, clock=clock, sleep=clock.sleep
    )
    try:
        client.execute(UNIT, request)
    except KNOWN_ERRORS as error:
        return type(error).__name__
    return "reply"


def run(framing: str, frames: int, seed: int, progress=None) -> dict:
    """Fuzz one framing; the counts of outcomes per path and kind, and the crashing inputs.

    ``progress(kind, done, crashes)``, if given, is called every PROGRESS_EVERY frames and
    at once on a crash: a long run is watched from its log, not only judged at its end.
    """
    rng = random.Random(f"{seed}/{framing}")
    pairs = seeds()
    framer = make_framer(framing)
    valid = [(request, framer.build(UNIT, reply, TRANSACTION_ID)) for request, reply in pairs]
    adus = [adu for _, adu in valid]
    outcomes: dict[str, Counter] = {}
    crashes: list[tuple[str, str, str, str]] = []
    for kind in ("random", "mutated"):
        for done in range(frames):
            if progress and done and done % PROGRESS_EVERY == 0:
                progress(kind, done, crashes)
            request, adu = rng.choice(valid)
            data = random_frame(rng, framing) if kind == "random" else mutate(rng, adu, adus)
            parts = chunks(rng, data)
            for path, through in (("decoder", through_decoder), ("client", through_client)):
                try:
                    outcome = through(framing, request, parts)
                except Exception as error:  # the very thing this harness hunts for
                    outcome = "CRASH"
                    crashes.append((path, bytes(request.encode()).hex(" "), data.hex(" "), repr(error)))
                    if progress:
                        progress(kind, done, crashes)
                outcomes.setdefault(f"{kind} {path}", Counter())[outcome] += 1
    return {"outcomes": outcomes, "crashes": crashes}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--frames", type=int, default=2000, help="random frames, and as many mutated, per framer"
    )
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument(
        "--framer", choices=("rtu", "ascii", "tcp"), action="append", help="default: all three"
    )
    args = parser.parse_args()
    failed = False
    for framing in args.framer or ("rtu", "ascii", "tcp"):
        start = time.perf_counter()

        def progress(kind: str, done: int, crashes: list, framing=framing, start=start) -> None:
            print(
                f"{framing}: {kind} {done}/{args.frames}, {time.perf_counter() - start:.0f} s,"
                f" {len(crashes)} crashes" + (f"; last: {crashes[-1]}" if crashes else ""),
                file=sys.stderr,
                flush=True,
            )

        result = run(framing, args.frames, args.seed, progress)
        elapsed = time.perf_counter() - start
        print(
            f"{framing}: {args.frames} random + {args.frames} mutated frames, seed {args.seed},"
            f" {elapsed:.1f} s, {len(result['crashes'])} crashes"
        )
        for key, counts in sorted(result["outcomes"].items()):
            print(f"  {key}: " + ", ".join(f"{name} {n}" for name, n in counts.most_common()))
        for path, request, data, error in result["crashes"][:10]:
            print(f"  CRASH {path}: request {request} input {data}: {error}")
        failed |= bool(result["crashes"])
        sys.stdout.flush()
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
