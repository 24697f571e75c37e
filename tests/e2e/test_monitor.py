"""mbtool monitor: a passive bus monitor (sans-IO splitter, the command on ptys and bridges, pcap).

The sans-IO tests feed recorded byte streams with their arrival times and compare the
frame list; the end-to-end tests write into one end of a pseudo-terminal (or a TCP
"serial bridge") with pauses made by sleeping, run the real CLI on the other end, and
check that it wrote nothing.  The pcap is read back with tshark (when installed) and
parsed here with struct, independently of mbtool.
"""

from __future__ import annotations

import contextlib
import json
import random
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from datetime import datetime

import pytest
from helpers import (
    REPO_ROOT,
    Line,
    Result,
    ascii_frame,
    assert_one_error_line,
    bad_crc,
    crc16,
    finish,
    json_lines,
    mbtool_env,
    rtu,
    start_monitor,
)

from mbtool.monitor.bus import BusFrame, BusMonitor, Tally, Unanswered

DEADLINE = 20.0  # seconds for any one monitor run


READ_REQ = rtu(bytes.fromhex("11 03 00 6B 00 03"))  # spec §8: unit 17, read 3 registers at 107
READ_RSP = rtu(bytes.fromhex("11 03 06 AE 41 56 52 43 40"))
WRITE_REQ = rtu(bytes.fromhex("01 06 00 01 00 03"))  # its response is an echo
COILS_REQ = rtu(bytes.fromhex("02 01 00 00 00 08"))
INPUT_REQ = rtu(bytes.fromhex("01 04 00 00 00 01"))
EXCEPTION_RSP = rtu(bytes.fromhex("01 84 02"))
DAMAGED_REQ = bad_crc(rtu(bytes.fromhex("01 03 00 00 00 01")))
GARBAGE = bytes.fromhex("FF FF 00")


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


# --- the splitter, sans-IO ------------------------------------------------------------------


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


# --- the command ------------------------------------------------------------------------------


def run_cli(*args: str, timeout: float = DEADLINE) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "mbtool", "monitor", *args],
        cwd=REPO_ROOT,
        env=mbtool_env(),
        capture_output=True,
        text=True,
        timeout=timeout,
        stdin=subprocess.DEVNULL,
    )


def test_from_file_plain_and_json(tmp_path):
    recording = tmp_path / "bus.bin"
    recording.write_bytes(READ_REQ + READ_RSP + GARBAGE + INPUT_REQ + EXCEPTION_RSP)
    plain = run_cli("--from-file", str(recording))
    assert plain.returncode == 0, plain.stderr
    lines = plain.stdout.splitlines()
    assert len(lines) == 5
    assert (
        " #1 request unit=17 FC 03 (0x03) [11 03 00 6B 00 03 76 87] CRC 76 87 ok | Read Holding Registers:"
        in lines[0]
    )
    assert "starting_address=107 quantity=3" in lines[0]
    assert " #2 response unit=17 FC 03 (0x03) " in lines[1] and "request=#1" in lines[1]
    assert " #3 garbage 3 bytes [FF FF 00]" in lines[2]
    assert lines[4].endswith("| flags=exception")
    assert plain.stderr.splitlines() == [
        "mbtool: frames 4, requests 2, responses 2, unanswered 0, exceptions 1, checksum errors 0, "
        f"garbage bytes 3; {recording} is raw bytes with no time stamps: no time, gap or latency"
    ]
    records = json_lines(run_cli("--from-file", str(recording), "-o", "json").stdout)
    assert [(r["event"], r["direction"], r["unit"], r["function"]) for r in records] == [
        ("frame", "request", 17, 3),
        ("frame", "response", 17, 3),
        ("garbage", "garbage", None, None),
        ("frame", "request", 1, 4),
        ("frame", "response", 1, 0x84),
    ]
    assert records[1]["request"] == 1 and records[1]["checksum"] == {"ok": True, "verdict": "CRC 49 AD ok"}
    assert records[4]["flags"] == ["exception"]
    assert {
        "name": "exception_code",
        "bytes": "02",
        "value": 2,
        "text": "02 Illegal Data Address",
    } in records[4]["fields"]


def _pcap(packets, order="<", magic=0xA1B2C3D4, linktype=147, scale=1_000_000) -> bytes:
    """A classic pcap written here by hand: (time, bytes) packets, raw on a user link type."""
    out = struct.pack(order + "IHHiIII", magic, 2, 4, 0, 0, 65535, linktype)
    for when, data in packets:
        seconds = int(when)
        out += struct.pack(order + "IIII", seconds, round((when - seconds) * scale), len(data), len(data))
        out += data
    return out


T0 = 1_700_000_000.0


@pytest.mark.parametrize(
    ("order", "magic", "scale"),
    [("<", 0xA1B2C3D4, 1_000_000), (">", 0xA1B2C3D4, 1_000_000), ("<", 0xA1B23C4D, 1_000_000_000)],
    ids=["little-endian-us", "big-endian-us", "nanoseconds"],
)
def test_from_file_pcap_keeps_its_time_stamps(tmp_path, order, magic, scale):
    """A pcap replays with its timing: gaps, latency and an unanswered request, all from the
    packets' time stamps (each a frame's first byte)."""
    recording = tmp_path / "bus.pcap"
    recording.write_bytes(
        _pcap(
            [
                (T0, READ_REQ),
                (T0 + 0.0123, READ_RSP),
                (T0 + 0.5, GARBAGE),
                (T0 + 1.0, INPUT_REQ),  # never answered: the next request comes 2 s later
                (T0 + 3.0, INPUT_REQ),
                (T0 + 3.0081, EXCEPTION_RSP),
            ],
            order,
            magic,
            scale=scale,
        )
    )
    result = run_cli("--from-file", str(recording), "-o", "json")
    assert result.returncode == 0, result.stderr
    records = json_lines(result.stdout)
    assert [(r["event"], r.get("direction")) for r in records] == [
        ("frame", "request"),
        ("frame", "response"),
        ("garbage", "garbage"),
        ("frame", "request"),
        ("unanswered", None),
        ("frame", "request"),
        ("frame", "response"),
    ]
    assert records[1]["latency_ms"] == 12.3 and records[1]["gap_ms"] == 12.3
    assert records[6]["latency_ms"] == 8.1 and records[6]["flags"] == ["exception"]
    assert records[5]["gap_ms"] == 2000.0
    assert records[4]["request"] == 4 and records[4]["reason"] == "no response within 1000 ms"
    assert [datetime.fromisoformat(r["time"]).timestamp() for r in records] == pytest.approx(
        [T0, T0 + 0.012, T0 + 0.5, T0 + 1.0, T0 + 2.0, T0 + 3.0, T0 + 3.008], abs=0.0011
    )
    assert result.stderr.splitlines() == [
        "mbtool: frames 5, requests 3, responses 2, unanswered 1, exceptions 1, checksum errors 0, garbage bytes 3"
    ]


def test_a_capture_replays_as_the_frames_it_recorded(tmp_path):
    """--capture's file read back by --from-file: the same frames, bytes and verdicts."""
    raw, capture = tmp_path / "bus.bin", tmp_path / "bus.pcap"
    raw.write_bytes(READ_REQ + READ_RSP + GARBAGE + INPUT_REQ + EXCEPTION_RSP + READ_RSP[:-1] + b"\x00")
    first = run_cli("--from-file", str(raw), "--capture", str(capture), "-o", "json")
    assert first.returncode == 0, first.stderr
    again = run_cli("--from-file", str(capture), "-o", "json")
    assert again.returncode == 0, again.stderr

    def seen(stdout):
        return [(r["event"], r.get("direction"), r.get("frame"), r.get("flags")) for r in json_lines(stdout)]

    assert seen(again.stdout) == seen(first.stdout)
    assert again.stderr.rstrip() == first.stderr.split(";")[0]  # the raw bytes' note aside


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (struct.pack("<I", 0x0A0D0D0A) + bytes(28), "pcapng"),
        (_pcap([(T0, READ_REQ)])[:-3], "truncated after 0 packets"),
    ],
    ids=["pcapng", "truncated"],
)
def test_a_pcap_that_cannot_be_read_is_one_line_and_exit_2(tmp_path, content, words):
    recording = tmp_path / "bus.pcap"
    recording.write_bytes(content)
    args = ("--from-file", str(recording))
    line = assert_one_error_line(_as_result(run_cli(*args), args), 2)
    assert words in line


def test_a_pcap_replays_only_as_rtu(tmp_path):
    recording = tmp_path / "bus.pcap"
    recording.write_bytes(_pcap([(T0, READ_REQ)]))
    args = ("--from-file", str(recording), "--framer", "ascii")
    line = assert_one_error_line(_as_result(run_cli(*args), args), 2)
    assert "holds RTU frames" in line


def test_frames_option_stops_after_n_frames(tmp_path):
    recording = tmp_path / "bus.bin"
    recording.write_bytes(READ_REQ + READ_RSP + INPUT_REQ + EXCEPTION_RSP)
    result = run_cli("--from-file", str(recording), "--frames", "3", "-o", "json")
    assert result.returncode == 0, result.stderr
    assert [r["number"] for r in json_lines(result.stdout)] == [1, 2, 3]
    assert result.stderr.startswith("mbtool: frames 3, ")


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (("--framer", "tcp", "-p", "/dev/null"), "tcp"),
        (("-p", "tcp://127.0.0.1:502"), "serial line"),
        (("-p", "sim://"), "serial line"),
        ((), "no port given"),
        (("-p", "/dev/null", "--duration", "0"), "more than 0"),
        (("-p", "/dev/null", "--frames", "0"), "out of range"),
        (("--from-file", "/nonexistent/bus.bin"), "does not exist"),
        (("-p", "/dev/ttyS99", "--from-file", __file__), "not both"),
        (("--from-file", __file__, "--capture", "/nonexistent/dir/x.pcap"), "cannot write capture file"),
        # Options a recording leaves nothing to do (issue 28: no command takes an option it ignores).
        (("--from-file", __file__, "--duration", "5"), "--duration is for listening"),
        (("--from-file", __file__, "--silence", "0.1"), "--silence measures time, and"),
        (("--from-file", __file__, "--response-timeout", "2"), "is raw bytes with no time stamps"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(args, words):
    result = run_cli(*args)
    line = assert_one_error_line(_as_result(result, args), 2)
    assert words in line


def test_a_port_that_cannot_be_opened_is_exit_6():
    result = run_cli("-p", "/dev/mbtool-no-such-port")
    line = assert_one_error_line(_as_result(result, ()), 6)
    assert "cannot open /dev/mbtool-no-such-port" in line


def _as_result(completed: subprocess.CompletedProcess, args):
    return Result(list(args), completed.returncode, completed.stdout, completed.stderr, 0.0)


# --- listening on a pseudo-terminal ------------------------------------------------------------


@pytest.fixture
def line():
    pair = Line()
    yield pair
    pair.close()


# The pty test's traffic: (pause before, bytes written at once).  The pauses are far above
# --silence 0.15 where silence must end something (damaged frame, garbage); the pieces of
# one frame are written 10 ms apart, far below it even on a loaded machine.
SILENCE = "0.15"
PAUSE = 0.4


def _play(line: Line) -> None:
    line.send(READ_REQ[:3])
    time.sleep(0.01)
    line.send(READ_REQ[3:])  # one frame in two reads
    time.sleep(0.05)
    line.send(READ_RSP)
    time.sleep(PAUSE)
    line.send(WRITE_REQ, WRITE_REQ)  # request and echo back to back
    time.sleep(PAUSE)
    line.send(DAMAGED_REQ)
    time.sleep(PAUSE)
    line.send(GARBAGE)
    time.sleep(PAUSE)
    line.send(COILS_REQ)  # never answered
    time.sleep(PAUSE)
    line.send(INPUT_REQ)
    time.sleep(0.05)
    line.send(EXCEPTION_RSP)


EXPECTED = [
    ("frame", "request", 17, 3, READ_REQ, []),
    ("frame", "response", 17, 3, READ_RSP, []),
    ("frame", "request", 1, 6, WRITE_REQ, []),
    ("frame", "response", 1, 6, WRITE_REQ, []),
    ("frame", "request", 1, 3, DAMAGED_REQ, ["bad-checksum"]),
    ("garbage", "garbage", None, None, GARBAGE, ["garbage"]),
    ("frame", "request", 2, 1, COILS_REQ, []),
    ("unanswered", None, 2, 1, None, None),
    ("frame", "request", 1, 4, INPUT_REQ, []),
    ("frame", "response", 1, 0x84, EXCEPTION_RSP, ["exception"]),
]


def _shape(record: dict) -> tuple:
    if record["event"] == "unanswered":
        return ("unanswered", None, record["unit"], record["function"], None, None)
    wire = bytes.fromhex(record["frame"])
    return (record["event"], record["direction"], record["unit"], record["function"], wire, record["flags"])


def test_pty_stream_frames_gaps_capture_and_nothing_sent(line, tmp_path):
    capture = tmp_path / "bus.pcap"
    proc = start_monitor(
        "-p", line.path, "--parity", "N", "--baud", "9600", "--silence", SILENCE,
        "--frames", "8", "--duration", "15", "-o", "json", "--capture", str(capture),
    )  # fmt: skip
    _play(line)
    code, out, err = finish(proc)
    assert code == 0, err
    records = json_lines(out)
    assert [_shape(r) for r in records] == EXPECTED, out
    frames = [r for r in records if r["event"] != "unanswered"]
    # Gaps and latency: the sleeps are lower bounds; a loaded machine reads late, not early.
    assert frames[1]["latency_ms"] >= 30 and frames[1]["request"] == 1
    assert frames[3]["gap_ms"] < 100 and frames[3]["request"] == 3  # the echo, same write
    assert all(frames[index]["gap_ms"] >= 200 for index in (2, 4, 5, 6, 7))  # after the pauses
    assert records[7]["request"] == 7 and records[7]["reason"].startswith("another request followed")
    assert err.splitlines()[-1] == (
        "mbtool: frames 8, requests 5, responses 3, unanswered 1, exceptions 1, checksum errors 1, garbage bytes 3"
    )
    assert line.written_by_monitor() == b""
    packets = read_pcap(capture.read_bytes())
    assert [wire for _, _, wire in packets] == [bytes.fromhex(r["frame"]) for r in frames]
    assert [name for _, name, _ in packets] == ["mbrtu"] * 5 + ["data"] + ["mbrtu"] * 3
    # Packet times are the frames' times, to the millisecond shown.
    for (when, _, _), frame in zip(packets, frames, strict=True):
        shown = time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(when)) + f".{int(when * 1000) % 1000:03d}"
        assert frame["time"].startswith(shown)
    _check_with_tshark(capture)


def read_pcap(data: bytes) -> list[tuple[float, str, bytes]]:
    """(time, dissector name, payload) of each packet of a classic pcap of exported PDUs."""
    magic, major, minor, _, _, snaplen, linktype = struct.unpack_from("<IHHiIII", data)
    assert (magic, major, minor, linktype) == (0xA1B2C3D4, 2, 4, 252)
    packets, at = [], 24
    while at < len(data):
        seconds, micros, captured, original = struct.unpack_from("<IIII", data, at)
        assert captured == original <= snaplen
        packet = data[at + 16 : at + 16 + captured]
        assert len(packet) == captured
        at += 16 + captured
        name, offset = None, 0
        while True:
            tag, length = struct.unpack_from(">HH", packet, offset)
            value = packet[offset + 4 : offset + 4 + length]
            offset += 4 + length
            if tag == 0:
                break
            if tag == 12:
                name = value.rstrip(b"\0").decode()
        packets.append((seconds + micros / 1e6, name, packet[offset:]))
    return packets


def _check_with_tshark(capture) -> None:
    if shutil.which("tshark") is None:
        pytest.skip("tshark is not installed (.ci/run installs it)")
    result = subprocess.run(
        ["tshark", "-r", str(capture), "-T", "fields", "-E", "separator=,", "-e", "frame.protocols",
         "-e", "mbrtu.unit_id", "-e", "modbus.func_code", "-e", "modbus.exception_code", "-e", "data.data"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert result.returncode == 0, result.stderr
    rows = [row.split(",") for row in result.stdout.splitlines()]
    assert rows == [
        ["exported_pdu:mbrtu:modbus", "17", "3", "", ""],
        ["exported_pdu:mbrtu:modbus", "17", "3", "", ""],
        ["exported_pdu:mbrtu:modbus", "1", "6", "", ""],
        ["exported_pdu:mbrtu:modbus", "1", "6", "", ""],
        ["exported_pdu:mbrtu:modbus", "1", "3", "", ""],
        ["exported_pdu:data", "", "", "", "ffff00"],
        ["exported_pdu:mbrtu:modbus", "2", "1", "", ""],
        ["exported_pdu:mbrtu:modbus", "1", "4", "", ""],
        ["exported_pdu:mbrtu:modbus", "1", "4", "2", ""],
    ], result.stdout
    # Wireshark pairs the read's response with its request, as mbtool did.
    paired = subprocess.run(
        ["tshark", "-r", str(capture), "-T", "fields", "-e", "modbus.request_frame", "-Y", "frame.number == 2"],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert paired.stdout.strip() == "1"


def test_ascii_on_a_pty(line, tmp_path):
    request = ascii_frame(0x11, bytes.fromhex("03 00 6B 00 03"))
    response = ascii_frame(0x11, bytes.fromhex("03 06 AE 41 56 52 43 40"))
    capture = tmp_path / "ascii.pcap"
    proc = start_monitor(
        "-p", line.path, "--parity", "N", "--framer", "ascii", "--frames", "2", "--duration", "15",
        "-o", "json", "--capture", str(capture),
    )  # fmt: skip
    line.send(request[:9])
    time.sleep(0.05)
    line.send(request[9:])
    time.sleep(0.1)
    line.send(response)
    code, out, err = finish(proc)
    assert code == 0, err
    records = json_lines(out)
    assert [(r["direction"], r["frame"], r["flags"]) for r in records] == [
        ("request", request.decode(), []),
        ("response", response.decode(), []),
    ]
    assert records[1]["latency_ms"] >= 50
    # Wireshark has no Modbus ASCII dissector: the capture holds the same unit and PDU as RTU.
    assert [payload for _, _, payload in read_pcap(capture.read_bytes())] == [
        rtu(bytes.fromhex("11 03 00 6B 00 03")),
        rtu(bytes.fromhex("11 03 06 AE 41 56 52 43 40")),
    ]
    assert line.written_by_monitor() == b""


def test_plain_lines_and_duration(line):
    proc = start_monitor("-p", line.path, "--parity", "N", "--duration", "1.5", "--silence", SILENCE)
    line.send(READ_REQ)
    time.sleep(0.05)
    line.send(READ_RSP)
    code, out, err = finish(proc)
    assert code == 0, err
    lines = out.splitlines()
    assert len(lines) == 2 and " #1 request " in lines[0] and " #2 response " in lines[1]
    assert err.splitlines()[-1].startswith("mbtool: frames 2, requests 1, responses 1, unanswered 0")
    assert line.written_by_monitor() == b""


@pytest.mark.parametrize(("options", "settings"), [((), "9600 8N1"), (("-b", "19200"), "19200 8N1")])
def test_a_device_profile_gives_the_line_and_options_override_it(line, tmp_path, options, settings):
    config = tmp_path / "config.toml"
    # A device's profile: monitor takes the line settings and passes over unit and timeout.
    config.write_text(
        f'[profiles.bus]\nport = "{line.path}"\nbaud = 9600\nparity = "N"\nunit = 17\ntimeout = 0.5\n'
    )
    proc = start_monitor(
        "-P",
        "bus",
        *options,
        "--duration",
        "1.5",
        "--silence",
        SILENCE,
        "-o",
        "json",
        env={"MBTOOL_CONFIG": str(config)},
    )
    assert f"listening on {line.path} ({settings}, rtu" in proc.listening
    line.send(READ_REQ)
    time.sleep(0.05)
    line.send(READ_RSP)
    code, out, err = finish(proc)
    assert code == 0, err
    assert [json.loads(text)["direction"] for text in out.splitlines()] == ["request", "response"]
    assert line.written_by_monitor() == b""


@pytest.mark.parametrize(("frames", "code"), [(0, 130), (1, 0)])
def test_sigterm_stops_cleanly_with_a_summary(line, frames, code):
    proc = start_monitor("-p", line.path, "--parity", "N", "--silence", SILENCE, "-o", "json")
    if frames:
        line.send(READ_REQ)
        end = time.monotonic() + DEADLINE
        while not select.select([proc.stdout], [], [], 0.1)[0]:  # the frame was shown
            assert time.monotonic() < end, "no frame shown"
    proc.send_signal(signal.SIGTERM)
    returncode, out, err = finish(proc)
    assert returncode == code, err
    assert len(json_lines(out)) == frames
    assert "Traceback" not in err
    assert err.splitlines()[-1].startswith(f"mbtool: interrupted; frames {frames}, ")


# --- listening on a serial bridge (socket://) -------------------------------------------------


def test_socket_bridge_is_only_read(tmp_path):
    """A ser2net-like bridge pushes the bus traffic; mbtool reads it and sends nothing back."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    server.settimeout(DEADLINE)
    received = bytearray()
    done = threading.Event()

    def bridge() -> None:
        with contextlib.suppress(OSError):
            conn, _ = server.accept()
            with conn:
                time.sleep(0.3)
                conn.sendall(READ_REQ[:4])
                time.sleep(0.01)
                conn.sendall(READ_REQ[4:] + READ_RSP)
                conn.settimeout(0.1)
                while not done.is_set():
                    with contextlib.suppress(TimeoutError):
                        data = conn.recv(4096)
                        if not data:
                            break
                        received.extend(data)

    thread = threading.Thread(target=bridge, daemon=True)
    thread.start()
    try:
        proc = start_monitor(
            "-p",
            f"socket://127.0.0.1:{server.getsockname()[1]}",
            "--frames",
            "2",
            "--duration",
            "15",
            "-o",
            "json",
        )
        code, out, err = finish(proc)
    finally:
        done.set()
        thread.join(timeout=5)
        server.close()
    assert code == 0, err
    assert [(r["direction"], r["unit"]) for r in json_lines(out)] == [("request", 17), ("response", 17)]
    assert bytes(received) == b""


def test_crc_helper_matches_spec():
    assert crc16(bytes.fromhex("11 03 00 6B 00 03")) == bytes.fromhex("76 87")


def test_raw_bytes_from_a_file_say_they_have_no_timing(tmp_path):
    """Raw bytes keep no time stamps: no time, gap or latency is made up for them (issue 28)."""
    recording = tmp_path / "bus.bin"
    recording.write_bytes(READ_REQ + READ_RSP + INPUT_REQ + INPUT_REQ + EXCEPTION_RSP)
    plain = run_cli("--from-file", str(recording))
    assert plain.returncode == 0, plain.stderr
    lines = plain.stdout.splitlines()
    assert [line.split(" ", 2)[:2] for line in lines if " gap=" in line] == [["-", "gap=-"]] * 5
    assert "latency=" not in plain.stdout and "0.0ms" not in plain.stdout
    assert " #2 response unit=17 FC 03 (0x03) " in lines[1] and lines[1].endswith("request=#1")
    assert (
        "- unanswered #3 unit=1 FC 04 (0x04) Read Input Registers | another request followed" in plain.stdout
    )
    (summary,) = plain.stderr.splitlines()
    assert summary.startswith("mbtool: frames 5, ")
    assert summary.endswith(f"; {recording} is raw bytes with no time stamps: no time, gap or latency")
    records = json_lines(run_cli("--from-file", str(recording), "-o", "json").stdout)
    assert {(r["time"], r.get("gap_ms"), r.get("latency_ms")) for r in records} == {(None, None, None)}
    assert [r["request"] for r in records if r["event"] == "frame"] == [None, 1, None, None, 4]
