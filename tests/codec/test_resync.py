"""RTU resync through garbage (spec §2: an RTU frame has no start mark, only its length rule
and CRC tell where it is).  bench/resync.py measures the speed; issue 6.

The reply behind 1 to 65536 bytes of garbage is recovered with a bounded buffer, and so is a
request by the device's framer; offsets the framer leaves unjudged change nothing when no
request is outstanding, nor on the device's side; with one outstanding,
frames that could answer it (or be reported as mismatches) are still found amid garbage (and
endless garbage from a peer ends at the deadline: tests/e2e/test_flood.py).  Speed is measured, not asserted: the time bound here
only catches a return to quadratic time, which took seconds.
"""

from __future__ import annotations

import importlib.util
import random

import pytest
from helpers.frames import drain_events, settle_events
from helpers.run import REPO_ROOT

from mbtool.codec import data_access as da
from mbtool.codec import serial_line as sl
from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.codec.framer import Frame, Rejected
from mbtool.codec.rtu import RTU_MAX_ADU, DeviceRtuFramer, RtuFramer


def load(name: str, path: str):
    spec = importlib.util.spec_from_file_location(name, REPO_ROOT / path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


resync = load("resync", "bench/resync.py")
fuzz = load("fuzz", "scripts/fuzz.py")

REQUEST = ReadHoldingRegisters(0, 10)
UNIT = resync.UNIT


@pytest.mark.parametrize(("size", "chunk"), [(1, 1), (16, 3), (256, 1), (4096, 1), (65536, 256)])
def test_reply_behind_garbage_is_recovered_with_a_bounded_buffer(size, chunk):
    reply = RtuFramer().build(UNIT, bytes([3, 20]) + bytes(range(20)))
    stream = resync.garbage(random.Random(size), size, reply) + reply
    recovered, elapsed, peak = resync.feed(stream, chunk, REQUEST)
    assert recovered
    assert peak <= 2 * RTU_MAX_ADU + chunk
    assert elapsed < 2.0


@pytest.mark.parametrize(("size", "chunk"), [(1, 1), (300, 1), (4096, 7), (65536, 256)])
def test_request_behind_garbage_is_found_by_the_device_framer_with_a_bounded_buffer(size, chunk):
    # mbtool serve and sim:// read requests with it: garbage on the line must not hide the next poll.
    request = RtuFramer().build(UNIT, REQUEST.encode())
    stream = resync.garbage(random.Random(size), size, request) + request
    recovered, _, peak = resync.feed(stream, chunk, REQUEST, device=True)
    assert recovered
    assert peak <= 2 * RTU_MAX_ADU + chunk


# --- which offsets are judged -------------------------------------------------------------------


class EveryOffset(RtuFramer):
    """Judges every offset as a possible frame start, as the framer once did byte by byte."""

    def _can_start(self, code: int) -> bool:
        return True


def outline(events) -> list[tuple]:
    """Events as comparable values (errors compare by identity, their messages do not)."""
    return [
        ("frame", event.adu) if isinstance(event, Frame) else ("rejected", event.data, str(event.error))
        for event in events
    ]


def stream_of_frames(rng: random.Random, responses: bool) -> bytes:
    """Garbage, valid frames of several units and functions, and corrupted ones, mixed."""
    pdus = (
        [da.RegistersResponse(3, (1, 2, 3)).encode(), bytes.fromhex("83 02"), bytes.fromhex("06 0001 0003")]
        if responses
        else [REQUEST.encode(), da.WriteSingleRegister(1, 2).encode(), sl.ReadExceptionStatus().encode()]
    )
    out = bytearray()
    for _ in range(rng.randint(1, 8)):
        kind = rng.randrange(3)
        if kind == 0:
            out += rng.randbytes(rng.choice((1, 3, 40, 300)))
        else:
            frame = bytearray(RtuFramer().build(rng.choice((1, 0x11, 0x7F)), rng.choice(pdus)))
            if kind == 2:
                frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
            out += frame
    return bytes(out)


@pytest.mark.parametrize("responses", [True, False], ids=["replies", "requests"])
def test_offsets_left_unjudged_change_nothing_without_a_request(responses):
    # They are the offsets before a byte that is no function code: the front would reject
    # them one by one, so skipping them in one step must give the very same events.
    rng = random.Random(6)
    for _ in range(150):
        stream = stream_of_frames(rng, responses)
        cuts = sorted(rng.sample(range(1, len(stream)), min(3, len(stream) - 1)))
        pieces = [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True)]
        outlines = []
        for framer in (RtuFramer(responses), EveryOffset(responses)):
            events = []
            for piece in pieces:
                framer.feed(piece)
                events += drain_events(framer)
            outlines.append(outline(events + settle_events(framer)))
        assert outlines[0] == outlines[1], stream.hex(" ")


class EveryOffsetDevice(DeviceRtuFramer):
    """Judges every offset as a request start, an unknown function code's too, as the device's
    framer once did (each one pending until an ADU followed it)."""

    def _can_start(self, code: int) -> bool:
        return True


def requests_amid_garbage(rng: random.Random) -> bytes:
    """Garbage (some of it longer than an ADU), valid and corrupted requests, and requests
    with function codes the codec does not know, which only silence ends."""
    pdus = [
        REQUEST.encode(),
        da.WriteMultipleRegisters(1, (2, 3)).encode(),
        bytes.fromhex("41 01 02"),
        b"\x64",
    ]
    out = bytearray()
    for _ in range(rng.randint(1, 6)):
        kind = rng.randrange(4)
        if kind == 0:
            out += rng.randbytes(rng.choice((1, 3, 40, 255, 256, 257, 300)))
        elif kind == 1:
            out += bytes(rng.choice((3, 0x10, 0x41, 0x17)) for _ in range(rng.randint(1, 40)))
        else:
            frame = bytearray(RtuFramer().build(rng.choice((1, UNIT)), rng.choice(pdus)))
            if kind == 3:
                frame[rng.randrange(len(frame))] ^= 1 << rng.randrange(8)
            out += frame
    return bytes(out)


def test_the_device_framer_leaves_unjudged_only_offsets_that_change_nothing():
    # An unknown function code never makes a whole frame before silence, so the framer never
    # judges it behind the front, and garbage is skipped over it in one step only where more
    # than an ADU follows it: the events must be those of judging every offset, byte by byte.
    rng = random.Random(7)
    for _ in range(150):
        stream = requests_amid_garbage(rng)
        cuts = sorted(rng.sample(range(1, len(stream)), min(4, len(stream) - 1)))
        pieces = [stream[a:b] for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True)]
        quiet = {index for index in range(len(pieces)) if rng.random() < 0.3}  # silence after these
        outlines = []
        for framer in (DeviceRtuFramer(), EveryOffsetDevice()):
            events = []
            for index, piece in enumerate(pieces):
                framer.feed(piece)
                events += drain_events(framer)
                while index in quiet and (event := framer.silence()) is not None:
                    events.append(event)
            outlines.append(outline(events + settle_events(framer)))
        assert outlines[0] == outlines[1], stream.hex(" ")


def expecting() -> RtuFramer:
    framer = RtuFramer()
    framer.expect = REQUEST
    framer.expect_unit = UNIT
    return framer


REPLY = RtuFramer().build(UNIT, bytes([3, 20]) + bytes(range(20)))
NOISE = bytes.fromhex("00 FF 20 5A")  # no unit 11, no 03 or 83: not one offset worth judging


@pytest.mark.parametrize(
    "other",
    [
        RtuFramer().build(0x12, bytes([3, 2, 0, 7])),  # the asked function from another unit
        RtuFramer().build(0x12, bytes([0x83, 2])),  # its exception from another unit
        RtuFramer().build(UNIT, bytes.fromhex("06 0001 0003")),  # our unit, another function
    ],
    ids=["other unit", "other unit's exception", "other function"],
)
def test_a_frame_that_may_concern_the_request_is_found_amid_garbage(other):
    framer = expecting()
    framer.feed(NOISE + other + NOISE + REPLY)
    events = drain_events(framer)
    assert [type(event) for event in events] == [Rejected, Frame, Rejected, Frame]
    assert [event.adu for event in events if isinstance(event, Frame)] == [other, REPLY]
    assert [event.data for event in events if isinstance(event, Rejected)] == [NOISE, NOISE]


def test_the_mismatch_behind_garbage_is_what_the_client_reports():
    other = RtuFramer().build(0x12, bytes([3, 2, 0, 7]))
    reply = RtuFramer().build(fuzz.UNIT, bytes([3, 20]) + bytes(range(20)))
    assert fuzz.through_client("rtu", REQUEST, [NOISE + other]) == "MismatchError"
    assert fuzz.through_client("rtu", REQUEST, [NOISE + other + NOISE + reply]) == "reply"


def test_a_frame_that_cannot_concern_the_request_is_garbage_while_it_is_outstanding():
    # Another unit, another function: it cannot answer, nor tell why the reply does not come.
    # Telling it from garbage would mean judging every offset in Python (issue 6: too slow).
    other = RtuFramer().build(0x20, bytes.fromhex("06 0001 0003"))
    framer = expecting()
    framer.feed(NOISE + other + REPLY)
    assert outline(drain_events(framer))[1:] == [("frame", REPLY)]
    framer = RtuFramer()  # with no request outstanding it is a frame like any other
    framer.feed(NOISE + other + REPLY)
    assert [event.adu for event in drain_events(framer) if isinstance(event, Frame)] == [other, REPLY]


def test_the_awaited_reply_starting_in_a_corrupted_frame_is_still_waited_for():
    # A corrupted frame (bad CRC) whose last bytes begin the reply: held, not skipped whole.
    bad = bytearray(RtuFramer().build(0x12, bytes([3, 4, 1, 2, 3, 4])))
    bad[-2] ^= 0xFF
    framer = expecting()
    framer.feed(bytes(bad[:-1]) + REPLY[:1])  # the reply's unit byte is the corrupted CRC's last
    assert drain_events(framer) == []
    assert framer.waiting_for_silence
    framer.feed(REPLY[1:])
    assert outline(drain_events(framer))[-1] == ("frame", REPLY)


# --- endless garbage --------------------------------------------------------------------------
