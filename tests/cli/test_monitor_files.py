"""mbtool monitor on recordings, in-process: raw bytes and pcap files (their time stamps kept), a
capture read back, --frames, and the options refused with one line."""

from __future__ import annotations

import struct
from datetime import datetime

import pytest
from helpers.checks import assert_one_error_line, json_lines
from helpers.monitor import EXCEPTION_RSP, GARBAGE, INPUT_REQ, READ_REQ, READ_RSP
from helpers.run import Result, run_cli


def monitor(*args: str) -> Result:
    return run_cli("monitor", *args)


def test_from_file_plain_and_json(tmp_path):
    recording = tmp_path / "bus.bin"
    recording.write_bytes(READ_REQ + READ_RSP + GARBAGE + INPUT_REQ + EXCEPTION_RSP)
    plain = monitor("--from-file", str(recording))
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
    records = json_lines(monitor("--from-file", str(recording), "-o", "json").stdout)
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
    result = monitor("--from-file", str(recording), "-o", "json")
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
    first = monitor("--from-file", str(raw), "--capture", str(capture), "-o", "json")
    assert first.returncode == 0, first.stderr
    again = monitor("--from-file", str(capture), "-o", "json")
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
    line = assert_one_error_line(monitor(*args), 2)
    assert words in line


def test_a_pcap_replays_only_as_rtu(tmp_path):
    recording = tmp_path / "bus.pcap"
    recording.write_bytes(_pcap([(T0, READ_REQ)]))
    args = ("--from-file", str(recording), "--framer", "ascii")
    line = assert_one_error_line(monitor(*args), 2)
    assert "holds RTU frames" in line


def test_frames_option_stops_after_n_frames(tmp_path):
    recording = tmp_path / "bus.bin"
    recording.write_bytes(READ_REQ + READ_RSP + INPUT_REQ + EXCEPTION_RSP)
    result = monitor("--from-file", str(recording), "--frames", "3", "-o", "json")
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
    result = monitor(*args)
    line = assert_one_error_line(result, 2)
    assert words in line


def test_a_port_that_cannot_be_opened_is_exit_6():
    result = monitor("-p", "/dev/mbtool-no-such-port")
    line = assert_one_error_line(result, 6)
    assert "cannot open /dev/mbtool-no-such-port" in line


def test_raw_bytes_from_a_file_say_they_have_no_timing(tmp_path):
    """Raw bytes keep no time stamps: no time, gap or latency is made up for them (issue 28)."""
    recording = tmp_path / "bus.bin"
    recording.write_bytes(READ_REQ + READ_RSP + INPUT_REQ + INPUT_REQ + EXCEPTION_RSP)
    plain = monitor("--from-file", str(recording))
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
    records = json_lines(monitor("--from-file", str(recording), "-o", "json").stdout)
    assert {(r["time"], r.get("gap_ms"), r.get("latency_ms")) for r in records} == {(None, None, None)}
    assert [r["request"] for r in records if r["event"] == "frame"] == [None, 1, None, None, 4]
