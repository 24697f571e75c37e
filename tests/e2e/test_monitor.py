"""mbtool monitor, a passive bus monitor, listening: the tests write into one end of a
pseudo-terminal (or a TCP "serial bridge") with pauses made by sleeping, run the real CLI on
the other end, and check that it wrote nothing.  The pcap is read back with tshark (when
installed) and parsed here with struct, independently of mbtool.  tests/monitor/test_bus.py
has the splitter sans-IO, tests/cli/test_monitor_files.py the command on recordings.
"""

from __future__ import annotations

import contextlib
import json
import select
import shutil
import signal
import socket
import struct
import subprocess
import threading
import time

import pytest
from helpers.checks import json_lines
from helpers.frames import ascii_frame, rtu
from helpers.monitor import (
    COILS_REQ,
    DAMAGED_REQ,
    EXCEPTION_RSP,
    GARBAGE,
    INPUT_REQ,
    MONITOR_DEADLINE,
    READ_REQ,
    READ_RSP,
    WRITE_REQ,
    Line,
    finish,
    start_monitor,
)

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
        end = time.monotonic() + MONITOR_DEADLINE
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
    server.settimeout(MONITOR_DEADLINE)
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
