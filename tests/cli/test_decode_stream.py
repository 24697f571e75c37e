"""decode reads a stream (issues 12.5, 13.7, 12.17): every line decoded as it comes, a bad line
reported with its number and passed over, the TX/RX lines of --hex accepted."""

from __future__ import annotations

import json
import random
import select
import subprocess
import sys
import time

import pytest
from helpers.checks import assert_one_error_line
from helpers.frames import crc16
from helpers.run import REPO_ROOT, mbtool_env, run_cli, run_mbtool

pytestmark = pytest.mark.timeout(120)

REQUEST = "01 03 00 00 00 02 C4 0B"
REPLY = "01 03 04 00 01 00 02 2A 32"


def test_each_line_is_decoded_as_it_comes():
    """tail -f log | mbtool decode: a frame's decoding shows before the next line is written."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "mbtool", "decode", "-o", "json"],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        cwd=REPO_ROOT, env=mbtool_env(),
    )  # fmt: skip
    try:
        for expected_kind, line in (("request", REQUEST), ("response", REPLY)):
            proc.stdin.write(f"{line}\n".encode())
            proc.stdin.flush()
            ready, _, _ = select.select([proc.stdout], [], [], 10)
            assert ready, "no output before the next line"
            record = json.loads(proc.stdout.readline())
            assert (record["kind"], record["raw"]) == (expected_kind, line)
    finally:
        proc.stdin.close()
        assert proc.wait(timeout=10) == 0
        proc.stdout.close()
        proc.stderr.close()


BAD_CRC = "01 03 04 00 01 00 02 2A 33"  # a reply


def test_bad_lines_are_named_and_decoding_goes_on():
    lines = [REQUEST, "zz", "01 03", "", "# a comment", BAD_CRC, REPLY]
    res = run_mbtool("decode", input="\n".join(lines) + "\n")
    assert res.returncode == 5, str(res)  # the frame with a bad CRC, not the lines that are none
    assert res.stdout.count("raw ") == 3  # every frame, those after the bad lines too
    errors = res.stderr.splitlines()
    assert errors[0] == "mbtool: line 2: not a frame, passed over: zz is not hex"
    assert errors[1].startswith("mbtool: line 3: not a frame, passed over: RTU frame too short")
    assert errors[2] == "mbtool: line 6: CRC 2A 33 BAD, expected 2A 32"
    assert errors[3] == "mbtool: 1 of 3 frames failed; the first: line 6: CRC 2A 33 BAD, expected 2A 32"


def test_bad_frames_in_json_are_records_with_an_error():
    res = run_mbtool("decode", "-o", "json", input=f"{REQUEST}\nzz\n{BAD_CRC}\n{REPLY}\n")
    records = [json.loads(line) for line in res.stdout.splitlines()]
    assert [r.get("line") for r in records[:3]] == [1, 3, 4]  # line 2 is no frame: stderr names it
    assert records[1]["kind"] == "response" and records[1]["checksum"]["ok"] is False
    assert records[2]["kind"] == "response" and records[2]["error"] is None
    assert records[3]["exit_code"] == 5 and res.returncode == 5
    assert res.stderr.splitlines()[0] == "mbtool: line 2: not a frame, passed over: zz is not hex"


@pytest.mark.long  # 6 s of mbtool's CPU, 25-45 s on a busy machine: started first (tests/conftest.py)
def test_100000_lines_with_garbage_every_valid_frame_decoded(tmp_path):
    rnd = random.Random(5)
    lines, valid, bad = [], 0, 0
    for i in range(100_000):
        r = rnd.random()
        if r < 0.05:
            lines.append("garbage!")
        elif r < 0.1:
            lines.append("01 03")
        elif r < 0.11:
            lines.append(BAD_CRC)
            bad += 1
        else:
            lines.append(REQUEST if i % 2 == 0 else REPLY)
            valid += 1
    start = time.monotonic()
    # A log file decoded into a file, as a user would: 15 MB through pipes cost the test's process
    # 1.2 s of CPU woken for every line flushed, and mbtool 1 s more.
    res = run_mbtool("decode", "-o", "plain", input="\n".join(lines) + "\n", timeout=110, files=tmp_path)
    assert res.returncode == 5
    assert res.stdout.count("frame rtu ") == valid + bad
    assert len(res.stderr.splitlines()) == 100_000 - valid + 1
    assert res.stderr.splitlines()[-1].startswith(f"mbtool: {bad} of {valid + bad} frames failed")
    print(f"\n100,000 lines decoded in {time.monotonic() - start:.1f} s")


def test_a_saved_hex_trace_decodes():
    trace = run_cli("read-holding-registers", "0", "2", "-p", "sim://", "--hex").stderr
    assert trace.startswith("TX ") and "\nRX " in trace
    res = run_mbtool("decode", "-o", "json", input=trace)
    assert res.returncode == 0, str(res)
    records = [json.loads(line) for line in res.stdout.splitlines()]
    assert [r["kind"] for r in records] == ["request", "response"]
    assert records[1]["name"] == "Read Holding Registers" and records[1]["error"] is None


# --- what decode reads: monitor's lines, socat -x dumps; only frames decide the exit (issue 28) ----


def test_text_that_is_not_hex_is_quoted_as_typed():

    line = assert_one_error_line(run_cli("decode", "2024-05-26T00:12:34.567+02:00", "01", "03"), 2)
    assert line == "mbtool: 2024-05-26T00:12:34.567+02:00 is not hex"
    line = assert_one_error_line(run_cli("decode", "01 03 0:0G"), 2)
    assert line == "mbtool: 0:0G is not hex"


def _monitor_recording(tmp_path, fmt: str) -> str:
    """monitor's own output (-o plain or json) for a recording of a request and its reply."""
    request = bytes.fromhex(REQUEST.replace(" ", ""))
    reply = bytes.fromhex(REPLY.replace(" ", ""))
    exception = bytes([0x01, 0x83, 0x02]) + crc16(bytes([0x01, 0x83, 0x02]))
    path = tmp_path / "bus.bin"
    path.write_bytes(request + reply + request + exception + b"\x55\x55")  # and 2 garbage bytes
    res = run_cli("monitor", "--from-file", path, "-o", fmt)
    assert res.returncode == 0 and res.stdout, str(res)
    return res.stdout


@pytest.mark.parametrize("fmt", ["plain", "json"])
def test_monitor_lines_decode(tmp_path, fmt):
    lines = _monitor_recording(tmp_path, fmt)
    res = run_mbtool("decode", "-o", "json", input=lines)
    assert res.returncode == 0, str(res)
    assert res.stderr == ""
    records = [json.loads(line) for line in res.stdout.splitlines()]
    assert [r["kind"] for r in records] == ["request", "response", "request", "exception"]
    assert [r["raw"] for r in records[:2]] == [REQUEST, REPLY]
    assert all(r["error"] is None for r in records)
    assert [r["line"] for r in records] == [1, 2, 3, 4]


def test_a_frame_socat_saw_in_pieces_is_joined():
    # A serial line read in pieces: socat shows each read as a block of its own.
    dump = (
        "> 2026/01/02 10:00:00.000100  length=3 from=0 to=2\n 01 03 00\n--\n"
        "> 2026/01/02 10:00:00.000900  length=5 from=3 to=7\n 00 00 02 c4 0b\n--\n"
        "< 2026/01/02 10:00:00.010000  length=9 from=0 to=8\n 01 03 04 00 01 00 02 2a 32\n--\n"
    )
    res = run_mbtool("decode", "-o", "json", input=dump)
    assert res.returncode == 0, str(res)
    records = [json.loads(line) for line in res.stdout.splitlines()]
    assert [(r["line"], r["kind"], r["raw"]) for r in records] == [
        (1, "request", REQUEST),
        (7, "response", REPLY),
    ]


def test_lines_that_are_no_frames_are_named_and_do_not_fail_the_run():
    # What 2>&1 mixes in with --hex's lines: values read and mbtool's own lines.
    trace = run_cli("read-holding-registers", "0", "2", "-p", "sim://", "--hex")
    mixed = trace.stderr + trace.stdout + "mbtool: a line of mbtool's own\n"
    res = run_mbtool("decode", input=mixed)
    assert res.returncode == 0, str(res)
    assert res.stdout.count("raw ") == 2
    notes = res.stderr.splitlines()
    assert notes and all(" not a frame, passed over" in note for note in notes), res.stderr
