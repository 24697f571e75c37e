"""``mbtool ping`` end to end (issue 32): against pymodbus's device over TCP and a
pseudo-terminal, ``mbtool serve`` with its faults, raw responders on loopback and
``mbtool bridge`` answering 0B for a unit that is not on its bus.

One line for each request (``unit 1: seq=3 time=4.2 ms`` or what went wrong), and the
summary on stderr: sent, answered, lost, rtt min/avg/max/mdev, and every transaction's
outcome.  An exception is the device answering; a gateway's 0B is not.  Exit 0 when any
reply came, 3 when none did.
"""

from __future__ import annotations

import re
import signal
import struct
import time

import pytest
from helpers.checks import assert_one_error_line
from helpers.frames import rtu
from helpers.ptys import PTY_SERIAL_OPTS
from helpers.run import run_cli, start_mbtool
from helpers.served import bridge, serve
from helpers.sockets import CLOSE

pytestmark = pytest.mark.timeout(60)

LINE = re.compile(r"^unit (\d+): seq=(\d+) (.*)$")


def pinged(*args: str) -> tuple[list[tuple[int, str]], str, int]:
    """(seq, what) of each line, the summary line and the exit code of ``mbtool ping ARGS``."""
    res = run_cli("ping", *args)
    assert "Traceback" not in res.stderr, str(res)
    lines = [ln for ln in res.stdout.splitlines() if ln.strip()]
    assert lines and lines[0].startswith("PING "), str(res)
    seen = []
    for line in lines[1:]:
        match = LINE.match(line)
        assert match, f"not a ping line: {line!r}\n{res}"
        seen.append((int(match.group(2)), match.group(3)))
    errors = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert len(errors) == 1 and errors[0].startswith("mbtool: "), str(res)
    return seen, errors[0], res.returncode


def times(seen: list[tuple[int, str]]) -> list[float]:
    return [float(m.group(1)) for _, what in seen if (m := re.search(r"time=([\d.]+) ms", what))]


def outcomes(summary: str) -> dict[str, int]:
    """The summary's counts of each outcome: answered, exception, ... link lost."""
    counts = summary.split("transactions ", 1)[1]
    names = r"(answered|exception|timeout|corrupt|not ours|link lost|retries recovered) (\d+)"
    return {m.group(1): int(m.group(2)) for m in re.finditer(names, counts)}


# --- a device that answers --------------------------------------------------------------


def test_pymodbus_over_tcp_answers_every_ping_with_its_time(tcp_device):
    seen, summary, code = pinged("-p", tcp_device.target, "-c", "3", "-i", "0.1")
    assert code == 0
    assert [seq for seq, _ in seen] == [1, 2, 3]
    assert all(re.fullmatch(r"time=[\d.]+ ms", what) for _, what in seen), seen
    assert "3 sent, 3 answered, 0% lost, rtt min/avg/max/mdev " in summary
    low, avg, high, mdev = map(
        float, re.search(r"mdev ([\d.]+)/([\d.]+)/([\d.]+)/([\d.]+) ms", summary).groups()
    )
    assert low <= avg <= high and min(times(seen)) == pytest.approx(low, rel=0.01, abs=0.001)
    assert max(times(seen)) == pytest.approx(high, rel=0.01, abs=0.001)
    assert outcomes(summary) == {
        "answered": 3, "exception": 0, "timeout": 0, "corrupt": 0, "not ours": 0, "link lost": 0,
        "retries recovered": 0,
    }  # fmt: skip


def test_pymodbus_on_a_serial_line_answers_every_ping(serial_rtu_device):
    seen, summary, code = pinged(
        "-p", serial_rtu_device.target, *PTY_SERIAL_OPTS, "-u", "2", "-c", "2", "-i", "0"
    )
    assert code == 0
    assert [seq for seq, _ in seen] == [1, 2] and len(times(seen)) == 2
    assert summary.startswith("mbtool: 2 sent, 2 answered, 0% lost")


def test_the_echo_of_fc08_carries_each_sequence_number():
    with serve() as server:
        seen, summary, code = pinged("-p", server.target, "--function", "08", "-c", "3", "-i", "0")
    assert code == 0 and len(times(seen)) == 3
    assert "3 sent, 3 answered" in summary


def test_the_register_read_is_the_one_at_address(tcp_device):
    # pymodbus's tables end at 999: a read at 5000 is refused, and the refusal is an answer.
    seen, summary, code = pinged("-p", tcp_device.target, "--address", "5000", "-c", "1")
    assert code == 0
    assert seen[0][1].startswith("exception 02 Illegal Data Address time=")


# --- serve's faults ---------------------------------------------------------------------


def test_an_exception_is_the_device_answering():
    with serve("--exception", "3:2") as server:
        seen, summary, code = pinged("-p", server.target, "-c", "3", "-i", "0")
    assert code == 0
    assert all(what.startswith("exception 02 Illegal Data Address time=") for _, what in seen), seen
    assert "3 sent, 3 answered, 0% lost" in summary
    assert "exception 3 (02:3)" in summary


def test_silence_is_lost_and_exit_3():
    with serve("--drop", "1") as server:
        seen, summary, code = pinged("-p", server.target, "-c", "2", "-i", "0", "-t", "0.2")
    assert code == 3
    assert [what for _, what in seen] == ["timeout: no response from unit 1 within 0.2 s"] * 2
    assert "2 sent, 0 answered, 100% lost; " in summary and "rtt" not in summary.split(";")[0]
    assert outcomes(summary)["timeout"] == 2


def test_a_bad_crc_is_corrupt():
    with serve("--framer", "rtu", "--corrupt", "1") as server:
        seen, summary, code = pinged("-p", server.socket_target, "-c", "2", "-i", "0", "-t", "0.3")
    assert code == 3
    assert all(what.startswith("corrupt: ") and "CRC" in what for _, what in seen), seen
    assert outcomes(summary)["corrupt"] == 2


def test_a_reply_that_took_retries_is_shown_with_them_and_counted_as_recovered():
    with serve("--drop", "0.5", "--seed", "3") as server:
        seen, summary, code = pinged(
            "-p", server.target, "-c", "12", "-i", "0", "-t", "0.2", "--retries", "4"
        )
    assert code == 0
    retried = [what for _, what in seen if re.search(r"\(after \d+ retr(y|ies)\)$", what)]
    assert retried, f"seed 3 dropped no reply a retry then got: {seen}"
    assert outcomes(summary)["retries recovered"] == len(retried)
    answered = sum(what.startswith("time=") for _, what in seen)
    assert outcomes(summary)["answered"] == answered
    assert f"12 sent, {answered} answered" in summary


# --- raw responders: not ours, a link that goes ---------------------------------------------


def test_a_reply_with_another_transaction_id_is_not_ours(raw_responder):
    def wrong_id(request: bytes) -> bytes:
        tid = struct.unpack(">H", request[:2])[0]
        return struct.pack(">HHHB", (tid + 1) & 0xFFFF, 0, 5, 1) + bytes.fromhex("03020064")

    srv = raw_responder(wrong_id)
    seen, summary, code = pinged("-p", srv.tcp_target, "-c", "2", "-i", "0", "-t", "0.3")
    assert code == 3
    assert all(what.startswith("not ours: reply has transaction id") for _, what in seen), seen
    assert outcomes(summary)["not ours"] == 2


def test_a_reply_from_another_unit_is_not_ours(raw_responder):
    srv = raw_responder(rtu(bytes.fromhex("0203020064")))
    seen, summary, code = pinged("-p", srv.socket_target, "-c", "1", "-t", "0.3")
    assert code == 3
    assert seen[0][1].startswith("not ours: reply from unit 2, expected unit 1")


def test_a_link_that_closes_is_lost_and_opened_again_for_the_next(raw_responder):
    srv = raw_responder(lambda request: CLOSE)
    seen, summary, code = pinged("-p", srv.tcp_target, "-c", "3", "-i", "0", "-t", "0.2")
    assert code == 3
    assert [seq for seq, _ in seen] == [1, 2, 3]
    assert all(what.startswith("link lost: ") for _, what in seen), seen
    assert outcomes(summary)["link lost"] == 3
    assert srv.connections == 3  # each ping on a link of its own


# --- a gateway ------------------------------------------------------------------------------


def test_exception_0B_from_a_gateway_is_lost(pty_pair):
    # mbtool bridge in front of a bus with nobody on it: unit 1 is not there.
    with bridge("-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, "-t", "0.3", "-q") as running:
        seen, summary, code = pinged("-p", running.target, "-c", "2", "-i", "0", "-t", "3")
    assert code == 3
    assert all(
        what.startswith("lost: exception 0B Gateway Target Failed to Respond from the gateway time=")
        for _, what in seen
    ), seen
    assert "2 sent, 0 answered, 100% lost; " in summary
    assert "exception 2 (0B:2)" in summary


# --- how it ends ----------------------------------------------------------------------------


def test_without_count_it_pings_until_interrupted_and_exits_0_after_replies(tcp_device):
    proc = start_mbtool("ping", "-p", tcp_device.target, "-i", "0.05")
    try:
        deadline = time.monotonic() + 20
        lines = []
        while len(lines) < 3 and time.monotonic() < deadline:
            lines.append(proc.stdout.readline())
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=5)
    assert proc.returncode == 0, err
    sent = int(re.search(r"interrupted; (\d+) sent, (\d+) answered", err).group(1))
    assert sent >= 2
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_quiet_prints_only_the_summary(tcp_device):
    res = run_cli("ping", "-p", tcp_device.target, "-c", "2", "-i", "0", "-q")
    assert res.returncode == 0 and res.stdout == ""
    assert "2 sent, 2 answered, 0% lost" in res.stderr


@pytest.mark.parametrize(
    "args, says",
    [
        (["-c", "0"], "count 0 is out of range"),
        (["--function", "08", "--address", "5"], "--address is the register FC 03 reads"),
        (["--function", "16"], "'16' is not one of"),
        (["-i", "-1"], "must be 0 or more seconds"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(raw_responder, args, says):
    srv = raw_responder(rtu(bytes.fromhex("0103020064")))
    res = run_cli("ping", "-p", srv.socket_target, *args)
    assert says in assert_one_error_line(res, 2)
    assert srv.received_bytes() == b""  # nothing was sent


def test_unit_0_on_a_serial_line_is_refused_before_anything_is_sent(raw_responder):
    srv = raw_responder(rtu(bytes.fromhex("0103020064")))
    res = run_cli("ping", "-p", srv.socket_target, "-u", "0", "-c", "1")
    assert "unit 0 is broadcast" in assert_one_error_line(res, 2)
    assert srv.received_bytes() == b""


def test_a_device_that_cannot_be_reached_is_exit_6(refused_port):
    res = run_cli("ping", "-p", f"tcp://127.0.0.1:{refused_port}", "-c", "1")
    assert_one_error_line(res, 6)
