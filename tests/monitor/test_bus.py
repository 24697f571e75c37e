"""The bus monitor's splitter (mbtool.monitor.bus), sans-IO: recorded byte streams with their
arrival times in, the frame list out, compared with what the spec says each is."""

from __future__ import annotations

import random
import time

import pytest
from helpers.frames import ascii_frame, crc16, rtu
from helpers.monitor import (
    COILS_REQ,
    DAMAGED_REQ,
    EXCEPTION_RSP,
    GARBAGE,
    INPUT_REQ,
    READ_REQ,
    READ_RSP,
    WRITE_REQ,
)

from mbtool.monitor.bus import BusFrame, BusMonitor, Tally, Unanswered


def run(monitor: BusMonitor, chunks: list[tuple[float, bytes | None]], end: float) -> list:
    """Feed (time, bytes) chunks; None means a read that returned nothing at that time."""
    seen = []
    for when, data in chunks:
        seen += monitor.feed(when, data) if data else monitor.idle(when)
    return seen + monitor.finish(end)


def frames_of(seen: list) -> list[tuple]:
    """What a test compares: (direction, wire, flags) per frame, ("unanswered", number) per note."""
    out = []
    for item in seen:
        if isinstance(item, Unanswered):
            out.append(("unanswered", item.request.number))
        else:
            out.append((item.direction, item.wire, item.flags))
    return out


def test_whole_frames_pair_request_and_response_with_latency():
    seen = run(BusMonitor(silence=0.02), [(10.0, READ_REQ), (10.030, READ_RSP)], end=10.5)
    assert frames_of(seen) == [("request", READ_REQ, ()), ("response", READ_RSP, ())]
    request, response = seen
    assert (request.number, request.unit, request.function, request.gap) == (1, 17, 3, None)
    assert response.request == 1 and response.latency == pytest.approx(0.030)
    assert response.gap == pytest.approx(0.030)
    assert request.checksum == "CRC 76 87 ok" and request.checksum_ok
    assert request.described.name == "Read Holding Registers"
    assert [f.value for f in response.described.fields if f.name.startswith("register")] == [
        0xAE41,
        0x5652,
        0x4340,
    ]


def test_frames_split_across_reads_are_joined_by_their_implicit_length():
    chunks = [(1.000, READ_REQ[:1]), (1.004, READ_REQ[1:5]), (1.009, READ_REQ[5:]), (1.050, READ_RSP[:4])]
    chunks += [(1.060, READ_RSP[4:9]), (1.070, READ_RSP[9:])]
    seen = run(BusMonitor(silence=0.02), chunks, end=1.5)
    assert frames_of(seen) == [("request", READ_REQ, ()), ("response", READ_RSP, ())]
    # A frame's time is its first byte's, its end its last byte's: the latency runs between.
    assert (seen[0].time, seen[0].end) == (1.000, 1.009)
    assert seen[1].latency == pytest.approx(0.041)


def test_two_frames_back_to_back_and_with_a_gap():
    # The echo of a write comes in the same read as the request: split by length alone.
    chunks = [(5.0, WRITE_REQ + WRITE_REQ), (5.25, COILS_REQ)]
    seen = run(BusMonitor(silence=0.02, response_timeout=10), chunks, end=5.3)
    assert frames_of(seen) == [
        ("request", WRITE_REQ, ()),
        ("response", WRITE_REQ, ()),
        ("request", COILS_REQ, ()),
    ]
    assert seen[1].gap == 0 and seen[1].request == 1
    assert seen[2].gap == pytest.approx(0.25)


def test_a_bad_crc_is_flagged_and_silence_ends_it():
    chunks = [(1.0, DAMAGED_REQ), (1.01, None), (1.05, None), (1.3, READ_REQ)]
    seen = run(BusMonitor(silence=0.02), chunks, end=1.31)
    assert frames_of(seen) == [("request", DAMAGED_REQ, ("bad-checksum",)), ("request", READ_REQ, ())]
    assert seen[0].checksum == "CRC 84 F5 BAD, expected 84 0A"
    # A slave ignores a frame with a bad CRC (spec §2): nothing waits for its response.
    assert not any(isinstance(item, Unanswered) for item in seen)


def test_a_bad_crc_right_before_a_good_frame_is_a_damaged_frame_not_garbage():
    seen = run(BusMonitor(silence=0.02), [(1.0, DAMAGED_REQ + READ_REQ)], end=1.01)
    assert frames_of(seen) == [("request", DAMAGED_REQ, ("bad-checksum",)), ("request", READ_REQ, ())]


def test_garbage_before_a_frame_and_alone():
    chunks = [(1.0, GARBAGE + READ_REQ), (1.5, GARBAGE), (1.51, None), (1.6, None)]
    seen = run(BusMonitor(silence=0.02, response_timeout=10), chunks, end=1.7)
    assert frames_of(seen) == [
        ("garbage", GARBAGE, ("garbage",)),
        ("request", READ_REQ, ()),
        ("garbage", GARBAGE, ("garbage",)),
    ]
    assert seen[2].gap == pytest.approx(0.5)


def test_unanswered_requests_by_another_request_and_by_timeout_and_a_late_response():
    chunks = [(1.0, COILS_REQ), (1.2, READ_REQ), (2.0, None), (2.3, None), (2.5, READ_RSP)]
    seen = run(BusMonitor(silence=0.02, response_timeout=1.0), chunks, end=3.0)
    assert frames_of(seen) == [
        ("request", COILS_REQ, ()),
        ("unanswered", 1),
        ("request", READ_REQ, ()),
        ("unanswered", 2),
        ("response", READ_RSP, ("late",)),
    ]
    assert "another request followed after 200 ms" in seen[1].reason
    assert seen[3].reason == "no response within 1000 ms" and seen[3].time == pytest.approx(2.2)
    assert seen[4].request == 2


def test_an_exception_response_and_a_response_to_no_request():
    chunks = [(1.0, READ_RSP), (1.5, INPUT_REQ), (1.52, EXCEPTION_RSP)]
    seen = run(BusMonitor(silence=0.02), chunks, end=2.0)
    assert frames_of(seen) == [
        ("response", READ_RSP, ("unsolicited",)),
        ("request", INPUT_REQ, ()),
        ("response", EXCEPTION_RSP, ("exception",)),
    ]
    assert seen[2].described.name == "exception to Read Input Registers"


def test_broadcast_expects_no_response():
    broadcast = rtu(bytes.fromhex("00 06 00 05 00 00"))
    seen = run(BusMonitor(silence=0.02, response_timeout=0.1), [(1.0, broadcast), (2.0, None)], end=3.0)
    assert frames_of(seen) == [("request", broadcast, ("broadcast",))]


def test_an_unknown_function_code_is_ended_by_silence():
    odd = rtu(bytes.fromhex("05 41 01 02 03"))
    seen = run(BusMonitor(silence=0.02), [(1.0, odd), (1.01, None), (1.05, None)], end=1.1)
    assert frames_of(seen) == [("request", odd, ())]
    assert seen[0].described.kind == "unknown"


def test_a_frame_cut_short_by_silence_is_garbage():
    seen = run(BusMonitor(silence=0.02), [(1.0, READ_REQ[:5]), (1.1, READ_RSP)], end=1.2)
    assert [item.direction for item in seen] == ["garbage", "response"]
    assert seen[0].note == "a frame cut short by silence"


def test_ascii_frames_bad_lrc_and_garbage():
    request = ascii_frame(0x11, bytes.fromhex("03 00 6B 00 03"))
    response = ascii_frame(0x11, bytes.fromhex("03 06 AE 41 56 52 43 40"))
    damaged = request.replace(b"7E\r", b"7F\r")
    assert damaged != request
    chunks = [(1.0, request[:7]), (1.2, request[7:]), (1.3, b"xx" + response), (2.0, damaged), (4.0, None)]
    seen = run(BusMonitor("ascii", silence=1.0, response_timeout=10), chunks, end=4.0)
    assert frames_of(seen) == [
        ("request", request, ()),
        ("garbage", b"xx", ("garbage",)),
        ("response", response, ()),
        ("request", damaged, ("bad-checksum",)),
    ]
    assert seen[2].latency == pytest.approx(0.1) and seen[3].checksum == "LRC 7F BAD, expected 7E"


def test_every_byte_comes_out_once_in_order():
    """Whatever the stream, frames and garbage together are exactly the bytes fed."""
    rng = random.Random(5)
    pieces = [READ_REQ, READ_RSP, WRITE_REQ, DAMAGED_REQ, EXCEPTION_RSP, GARBAGE, COILS_REQ]
    for _ in range(50):
        stream = b"".join(rng.choice(pieces) if rng.random() < 0.8 else rng.randbytes(3) for _ in range(12))
        monitor = BusMonitor(silence=0.02)
        seen, at, when = [], 0, 0.0
        while at < len(stream):
            size = rng.randint(1, 12)
            when += rng.choice((0.001, 0.005, 0.05))
            seen += monitor.feed(when, stream[at : at + size])
            at += size
        seen += monitor.finish(when + 1)
        frames = [item for item in seen if isinstance(item, BusFrame)]
        assert b"".join(frame.wire for frame in frames) == stream
        assert [frame.number for frame in frames] == list(range(1, len(frames) + 1))


def test_garbage_costs_linear_time():
    monitor = BusMonitor(silence=0.02)
    noise = random.Random(1).randbytes(32 * 1024)
    started = time.process_time()
    seen = []
    for at in range(0, len(noise), 16):
        seen += monitor.feed(1.0 + at * 1e-6, noise[at : at + 16])
    seen += monitor.finish(2.0)
    assert time.process_time() - started < 10
    assert sum(len(item.wire) for item in seen if isinstance(item, BusFrame)) == len(noise)


def test_the_tally():
    seen = run(
        BusMonitor(silence=0.02),
        [
            (1.0, INPUT_REQ),
            (1.01, EXCEPTION_RSP),
            (1.5, DAMAGED_REQ + GARBAGE),
            (1.6, COILS_REQ),
            (1.7, READ_REQ),
        ],
        end=1.8,
    )
    tally = Tally()
    for item in seen:
        tally.count(item)
    assert str(tally) == (
        "frames 5, requests 4, responses 1, unanswered 1, exceptions 1, checksum errors 1, garbage bytes 3"
    )


def test_crc_helper_matches_spec():
    assert crc16(bytes.fromhex("11 03 00 6B 00 03")) == bytes.fromhex("76 87")
