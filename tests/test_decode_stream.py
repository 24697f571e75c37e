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
from conftest import REPO_ROOT, mbtool_env, run_mbtool

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


def test_bad_lines_are_named_and_decoding_goes_on():
    lines = [REQUEST, "zz", "01 03", "", "# a comment", REPLY]
    res = run_mbtool("decode", input="\n".join(lines) + "\n")
    assert res.returncode == 5, str(res)
    assert res.stdout.count("raw ") == 2  # both frames, the one after the bad lines too
    errors = res.stderr.splitlines()
    assert errors[0] == "mbtool: line 2: zz is not hex"
    assert errors[1].startswith("mbtool: line 3: RTU frame too short")
    assert errors[2] == "mbtool: 2 of 4 lines failed; the first: line 2: zz is not hex"


def test_bad_lines_in_json_are_records_with_an_error():
    res = run_mbtool("decode", "-o", "json", input=f"{REQUEST}\nzz\n{REPLY}\n")
    records = [json.loads(line) for line in res.stdout.splitlines()]
    assert [r.get("line") for r in records[:3]] == [1, 2, 3]
    assert records[1] == {"line": 2, "input": "zz", "error": "zz is not hex", "exit_code": 5}
    assert records[2]["kind"] == "response" and records[2]["error"] is None
    assert records[3]["exit_code"] == 5 and res.returncode == 5


def test_100000_lines_with_garbage_every_valid_frame_decoded():
    rnd = random.Random(5)
    lines, valid = [], 0
    for i in range(100_000):
        r = rnd.random()
        if r < 0.05:
            lines.append("garbage!")
        elif r < 0.1:
            lines.append("01 03")
        else:
            lines.append(REQUEST if i % 2 == 0 else REPLY)
            valid += 1
    start = time.monotonic()
    res = run_mbtool("decode", "-o", "plain", input="\n".join(lines) + "\n", timeout=110)
    assert res.returncode == 5
    assert res.stdout.count("frame rtu ") == valid
    assert len(res.stderr.splitlines()) == 100_000 - valid + 1
    print(f"\n100,000 lines decoded in {time.monotonic() - start:.1f} s")


def test_a_saved_hex_trace_decodes():
    trace = run_mbtool("read-holding-registers", "0", "2", "-p", "sim://", "--hex").stderr
    assert trace.startswith("TX ") and "\nRX " in trace
    res = run_mbtool("decode", "-o", "json", input=trace)
    assert res.returncode == 0, str(res)
    records = [json.loads(line) for line in res.stdout.splitlines()]
    assert [r["kind"] for r in records] == ["request", "response"]
    assert records[1]["name"] == "Read Holding Registers" and records[1]["error"] is None
