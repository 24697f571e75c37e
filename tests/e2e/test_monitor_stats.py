"""``mbtool monitor --stats`` (issue 32): per unit, what a bus with two units carried, counted
exactly as the test put it on the line.

The test plays the master and units 1 and 2, writing raw frames into one end of a
pseudo-terminal with chosen gaps (requests, replies, an exception, a reply with a bad CRC, a
request nobody answers, a reply written hard on its request, breaking the t3.5 silence, and
a burst of noise); the monitor listens on the other end.  The same counts come back from the
capture it wrote, replayed with --from-file.
"""

from __future__ import annotations

import json
import time

import pytest
from helpers.checks import assert_one_error_line, json_lines
from helpers.frames import bad_crc, rtu
from helpers.monitor import Line, finish, start_monitor
from helpers.run import run_cli

pytestmark = pytest.mark.timeout(60)

BAUD = 19200  # 8N1: a character is 10 bits, t3.5 is 1.82 ms
CHAR = 10 / BAUD
PAUSE = 0.5  # between exchanges: far above --silence and t3.5 even on a loaded machine
SILENCE = "0.1"  # ends the damaged reply (its length cannot be trusted)
# A request is unanswered after this: longer than a turnaround and the silence that ends a
# damaged reply, so only the request nobody answers counts; 0.4 s past a turnaround, for a
# monitor (or this test's writer) a loaded machine runs late.
RESPONSE_TIMEOUT = 0.6
TURNAROUND = 0.2  # a unit's time to answer: two reads apart even on a loaded machine

READ_1 = rtu(bytes.fromhex("01 03 00 00 00 01"))
REPLY_1 = rtu(bytes.fromhex("01 03 02 00 2A"))
READ_2 = rtu(bytes.fromhex("02 03 00 10 00 02"))
REPLY_2 = rtu(bytes.fromhex("02 03 04 00 01 00 02"))
EXCEPTION_2 = rtu(bytes.fromhex("02 83 02"))
NOISE = bytes.fromhex("FF FF FF")

# (pause before, the bytes written at once)
PLAY = [
    (0.0, READ_1),
    (TURNAROUND, REPLY_1),  # unit 1 answers
    (PAUSE, READ_2),
    (TURNAROUND, EXCEPTION_2),  # unit 2 refuses: exception 02
    (PAUSE, READ_1),
    (TURNAROUND, bad_crc(REPLY_1)),  # unit 1's reply, damaged on the wire
    (PAUSE, READ_2),  # nobody answers
    (PAUSE + RESPONSE_TIMEOUT, READ_1 + REPLY_1),  # unit 1 answers at once: its reply breaks t3.5
    (PAUSE, NOISE),  # 3 bytes of garbage
    (PAUSE, READ_2),
    (TURNAROUND, REPLY_2),  # unit 2 answers
]
ON_THE_LINE = sum(len(data) for _, data in PLAY) * CHAR  # seconds of bytes

EXPECTED_UNITS = [
    {
        "unit": 1,
        "requests": 3,
        "replies": 2,
        "exceptions_by_code": {},
        "unanswered": 0,
        "corrupt": 1,
        "t35_breaks": 1,
    },
    {
        "unit": 2,
        "requests": 3,
        "replies": 1,
        "exceptions_by_code": {"02": 1},
        "unanswered": 1,
        "corrupt": 0,
        "t35_breaks": 0,
    },
]


def play(line: Line) -> float:
    """Write the traffic; the seconds it took."""
    started = time.monotonic()
    for pause, data in PLAY:
        time.sleep(pause)
        line.send(data)
    return time.monotonic() - started


def check(stats: dict, played: float | None) -> None:
    units = [{k: v for k, v in unit.items() if k != "response_seconds"} for unit in stats["units"]]
    assert units == EXPECTED_UNITS, json.dumps(stats, indent=1)
    assert stats["frames"] == 11 and stats["garbage_bytes"] == 3 and stats["t35_breaks"] == 1
    one, two = (unit["response_seconds"] for unit in stats["units"])
    # Unit 1: the reply written with its request (read with it: no time at all) and one after
    # TURNAROUND; the damaged reply is corrupt, not a response time.  The times are when the
    # monitor read the bytes, so a loaded machine that read a request late shortens its
    # response time: only the bounds that holds to are checked.
    assert one["min"] == 0 < one["max"] < TURNAROUND + PAUSE
    assert 0 < two["min"] <= two["max"] < TURNAROUND + PAUSE  # the exception and the reply
    if played is not None:
        assert stats["seconds"] >= played - 0.1
        assert 0 < stats["utilisation"] <= ON_THE_LINE / (played - 0.1)


def test_monitor_stats_count_exactly_what_was_on_a_bus_with_two_units(tmp_path):
    line = Line()
    capture = tmp_path / "bus.pcap"
    try:
        proc = start_monitor(
            "-p", line.path, "--baud", str(BAUD), "--parity", "N", "--silence", SILENCE,
            "--response-timeout", str(RESPONSE_TIMEOUT), "--stats", "-o", "json", "--capture", str(capture),
        )  # fmt: skip
        played = play(line)
        time.sleep(0.5)  # the last frame's silence
        proc.send_signal(__import__("signal").SIGTERM)
        code, out, err = finish(proc)
    finally:
        line.close()
    assert code == 0, err
    records = json_lines(out)
    assert [record["event"] for record in records] == ["stats"], out  # no frame lines: the statistics
    check(records[0], played)
    assert "frames 11" in err.splitlines()[-1]  # the summary line is as ever

    # The capture replayed: the same counts, timed by its time stamps.
    replayed = run_cli("monitor", "--from-file", str(capture), "--response-timeout", str(RESPONSE_TIMEOUT), "--stats",
                          "-o", "json", "--baud", str(BAUD), "--parity", "N")  # fmt: skip
    assert replayed.returncode == 0, replayed
    (again,) = json_lines(replayed.stdout)
    check(again, None)
    assert again["time"] and again["time"] <= records[0]["time"]  # as of the last frame recorded

    # And as a table.
    shown = run_cli("monitor", "--from-file", str(capture), "--response-timeout", str(RESPONSE_TIMEOUT), "--stats",
                       "--baud", str(BAUD), "--parity", "N", "-o", "plain")  # fmt: skip
    rows = [row.split() for row in shown.stdout.splitlines()]
    assert rows[0][:7] == ["unit", "requests", "replies", "exceptions", "unanswered", "corrupt", "t3.5"]
    assert rows[1][:7] == ["1", "3", "2", "0", "0", "1", "1"], shown
    assert rows[2][:7] == ["2", "3", "1", "02:1", "1", "0", "0"], shown
    assert shown.stdout.splitlines()[-1].startswith(
        "bus: 11 frames, 3 garbage bytes, 1 t3.5 break, utilisation "
    )


def test_stats_interval_prints_them_as_they_grow():
    line = Line()
    try:
        proc = start_monitor(
            "-p", line.path, "--parity", "N", "--stats", "--stats-interval", "0.3", "-o", "json"
        )
        for _ in range(4):
            line.send(READ_1)
            time.sleep(TURNAROUND)
            line.send(REPLY_1)
            time.sleep(0.3)
        proc.send_signal(__import__("signal").SIGTERM)
        code, out, err = finish(proc)
    finally:
        line.close()
    assert code == 0, err
    records = json_lines(out)
    assert len(records) >= 3 and all(r["event"] == "stats" for r in records), out
    requests = [r["units"][0]["requests"] if r["units"] else 0 for r in records]
    assert requests == sorted(requests) and requests[-1] == 4  # cumulative, the last one on exit
    seconds = [r["seconds"] for r in records]
    assert seconds == sorted(seconds)


def test_raw_bytes_with_no_time_stamps_have_no_times_to_count(tmp_path):
    recording = tmp_path / "bus.bin"
    recording.write_bytes(READ_1 + REPLY_1 + READ_2 + EXCEPTION_2)
    res = run_cli("monitor", "--from-file", str(recording), "--stats", "-o", "json")
    assert res.returncode == 0, res
    (stats,) = json_lines(res.stdout)
    assert stats["t35_breaks"] is None and stats["utilisation"] is None and stats["seconds"] is None
    assert stats["time"] is None
    assert [(u["unit"], u["requests"], u["replies"], u["exceptions_by_code"]) for u in stats["units"]] == [
        (1, 1, 1, {}),
        (2, 1, 0, {"02": 1}),
    ]
    assert all(u["response_seconds"] is None and u["t35_breaks"] is None for u in stats["units"])


@pytest.mark.parametrize(
    "args, words",
    [
        (["--stats-interval", "5"], "--stats-interval goes with --stats"),
        (["--stats", "--stats-interval", "0"], "more than 0"),
    ],
)
def test_bad_stats_options_are_one_line_and_exit_2(args, words):
    res = run_cli("monitor", "-p", "/dev/null-no-such-port", *args)
    assert words in assert_one_error_line(res, 2)
