"""mbtool scan: which unit ids answer, at which serial settings (issue 5).

Peers: pymodbus's server on a pseudo-terminal and on TCP (several unit ids),
sim:// (the built-in device, unit 1 only), and small misbehaving TCP peers from
tests/helpers/sockets.py (silent, answering with a bad CRC, answering as another unit, answering
late).  Every run ends within the test's timeout, and every wait below has a deadline.
"""

from __future__ import annotations

import json
import os
import select
import signal
import struct
import subprocess
import sys
import time

import pytest
from helpers.checks import assert_one_error_line, expect_ok
from helpers.devices import HOLDING, start_device
from helpers.frames import crc16, rtu
from helpers.ptys import PTY_SERIAL_OPTS
from helpers.run import REPO_ROOT, mbtool_env, run_cli, start_mbtool

FAST = ("-t", "0.1")  # a short per-unit timeout keeps the silent units cheap
# For peers that answer (nearly) every unit id, as pymodbus does (see below): a generous
# timeout costs little there and keeps a loaded machine's slow reply from turning "late".
GENEROUS = ("-t", "1")
SETTLE = 0.1  # seconds for bytes in flight to reach a peer before "nothing was sent" is judged


def scan_json(res) -> dict:
    lines = res.lines
    assert len(lines) == 1, f"-o json prints one object\n{res}"
    return json.loads(lines[0])


def by_unit(data: dict) -> dict[int, dict]:
    return {entry["unit"]: entry for entry in data["units"]}


# --- a pseudo-terminal bus with several units (pymodbus) --------------------------------------


@pytest.fixture(scope="module")
def rtu_bus():
    """pymodbus RTU on a pty serving units 1, 3 and 7."""
    with start_device(tcp=False, framer="rtu", units="1,3,7") as dev:
        yield dev


def test_scan_finds_the_units_of_an_rtu_bus(rtu_bus):
    res = expect_ok(
        run_cli("scan", "-p", rtu_bus.target, *PTY_SERIAL_OPTS, "--units", "1-8", *GENEROUS, "-o", "json")
    )
    data = scan_json(res)
    units = by_unit(data)
    replies = {unit for unit, entry in units.items() if entry["answer"] == "reply"}
    assert replies == {1, 3, 7}, res
    for unit in (1, 3, 7):
        assert units[unit]["values"] == [HOLDING[0]], res
        assert units[unit]["ms"] >= 0
        assert "baud" not in units[unit]  # no sweep: no settings per unit
    # pymodbus 3.16 answers ids it does not serve with exception 04 instead of staying
    # silent as a device on a real bus would; an exception still counts as "there".
    for unit, entry in units.items():
        if unit not in (1, 3, 7):
            assert entry["answer"] == "exception" and entry["exception"] != 0x0B, res
    assert data["probed"] == 8
    assert data["function"] == 3 and data["garbled"] == [] and data["interrupted"] is False
    assert "probes 8" in res.stderr


def test_plain_output_is_one_line_per_unit_found(rtu_bus):
    res = expect_ok(
        run_cli("scan", "-p", rtu_bus.target, *PTY_SERIAL_OPTS, "--units", "1,3", *GENEROUS, "-o", "plain")
    )
    assert res.lines == [f"1 reply registers {HOLDING[0]}", f"3 reply registers {HOLDING[0]}"], res


def test_exception_answers_count_as_present(rtu_bus):
    # Address 5000 is past pymodbus's tables: exception 02, which proves the unit is there.
    res = expect_ok(
        run_cli(
            "scan",
            "-p",
            rtu_bus.target,
            *PTY_SERIAL_OPTS,
            "-u",
            "3",
            "--address",
            "5000",
            *GENEROUS,
            "-o",
            "json",
        )
    )
    (entry,) = scan_json(res)["units"]
    assert entry["unit"] == 3 and entry["answer"] == "exception"
    assert entry["exception"] == 2 and entry["exception_name"] == "Illegal Data Address"


def test_report_id_probe_carries_the_identity(rtu_bus):
    res = expect_ok(
        run_cli(
            "scan",
            "-p",
            rtu_bus.target,
            *PTY_SERIAL_OPTS,
            "--units",
            "7",
            "--function",
            "report-id",
            *GENEROUS,
            "-o",
            "json",
        )
    )
    data = scan_json(res)
    (entry,) = data["units"]
    assert data["function"] == 17
    assert entry["unit"] == 7 and entry["answer"] == "reply"
    assert "PM-TEST" in entry["extra_text"] and isinstance(entry["run_indicator"], bool)


def test_hex_shows_one_probe_per_unit(rtu_bus):
    res = expect_ok(
        run_cli("scan", "-p", rtu_bus.target, *PTY_SERIAL_OPTS, "--units", "1-3", *GENEROUS, "--hex")
    )
    sent = [line for line in res.stderr.splitlines() if line.startswith("TX ")]
    assert [line.split()[1] for line in sent] == ["01", "02", "03"], res
    frame = rtu(bytes([2, 3, 0, 0, 0, 1]))
    assert f"TX {frame.hex(' ').upper()}" in res.stderr


# --- sweeping serial settings ---------------------------------------------------------------
#
# pymodbus ignores the baud rate on a pty, and a pty has no baud rate of its own, so a
# sweep over a pty finds the device at every baud.  These tests check the sweep's shape
# (a link per combination, settings in the JSON, refused settings reported and skipped,
# --first stopping), not that it finds the right baud: that needs a real serial line.


def test_sweep_reports_the_settings_of_each_answer(rtu_bus):
    res = expect_ok(
        run_cli(
            "scan",
            "-p",
            rtu_bus.target,
            "--units",
            "1-2",
            "--bauds",
            "9600,19200",
            "--parities",
            "N",
            *GENEROUS,
            "-o",
            "json",
        )
    )
    data = scan_json(res)
    answers = {(e["unit"], e["baud"], e["parity"]): e["answer"] for e in data["units"]}
    assert {key for key, answer in answers.items() if answer == "reply"} == {(1, 9600, "N"), (1, 19200, "N")}
    assert [(s["baud"], s["parity"]) for s in data["settings"]] == [(9600, "N"), (19200, "N")]
    assert all("error" not in s for s in data["settings"])
    assert data["probed"] == 4


def _scan_in_process(monkeypatch, refused: str, *args: str) -> tuple[int, str, str]:
    """Run mbtool scan in this process, with a port that refuses the parities in ``refused``.

    Linux ptys refuse some settings (EINVAL) but not consistently (it depends on the
    settings they had before), so the refusal is made here, where pyserial's is raised.
    """
    import mbtool.link.transport as transport
    from mbtool.errors import ConnectionFailed

    real = transport.open_transport

    def open_transport(target, settings, timeout, framer, tls=None):
        if settings.parity in refused:
            raise ConnectionFailed(f"cannot open {target}: it refused {settings}: Invalid argument")
        return real(target, settings, timeout, framer, tls)

    monkeypatch.setattr(transport, "open_transport", open_transport)
    res = run_cli("scan", *args)
    return res.returncode, res.stdout, res.stderr


def test_sweep_skips_a_setting_the_port_refuses(monkeypatch, rtu_bus):
    code, out, err = _scan_in_process(
        monkeypatch,
        "E",
        "-p",
        rtu_bus.target,
        "-u",
        "1",
        "--bauds",
        "9600",
        "--parities",
        "E,N",
        *GENEROUS,
        "-o",
        "json",
    )
    assert code == 0, err
    data = json.loads(out)
    first, second = data["settings"]
    assert first["parity"] == "E" and "refused" in first["error"]
    assert second["parity"] == "N" and "error" not in second
    assert [(e["unit"], e["parity"]) for e in data["units"]] == [(1, "N")]
    assert data["probed"] == 1
    assert "mbtool: 9600 8E1: cannot open" in err and "settings opened 1 of 2" in err


def test_sweep_stops_at_the_first_unit_found(rtu_bus):
    res = expect_ok(
        run_cli(
            "scan",
            "-p",
            rtu_bus.target,
            "--units",
            "1-8",
            "--bauds",
            "9600,19200,38400",
            "--parities",
            "N",
            "--first",
            *GENEROUS,
            "-o",
            "plain",
        )
    )
    assert res.lines == [f"1 reply 9600 N registers {HOLDING[0]}"], res
    assert "probes 1," in res.stderr and "settings opened 1 of 1" in res.stderr


def test_sweep_that_cannot_open_any_setting_is_exit_6(monkeypatch, pty_pair):
    code, out, err = _scan_in_process(
        monkeypatch,
        "EO",
        "-p",
        pty_pair.mbtool_path,
        "-u",
        "1",
        "--bauds",
        "9600",
        "--parities",
        "E,O",
        *FAST,
        "-o",
        "plain",
    )
    assert code == 6, err
    assert out == ""
    assert err.count("cannot open") == 2 and "no setting could be opened" in err
    assert pty_pair.sent_by_mbtool(SETTLE) == b""


# --- Modbus TCP and sim:// -----------------------------------------------------------------


def test_scan_over_tcp(tcp_device):
    res = expect_ok(run_cli("scan", "-p", tcp_device.target, "--units", "1-3", "-t", "0.5", "-o", "json"))
    units = by_unit(scan_json(res))
    assert {u for u, e in units.items() if e["answer"] == "reply"} == {1, 2}, res
    assert units[1]["values"] == [HOLDING[0]]
    assert units.get(3, {}).get("answer") != "reply"


def test_scan_of_the_built_in_device():
    # sim:// serves unit 1 only and stays silent for the others, as a device on a bus does.
    res = expect_ok(run_cli("scan", "-p", "sim://", "--units", "1-4", "-t", "0.05", "-o", "json"))
    data = scan_json(res)
    assert [(e["unit"], e["answer"], e["values"]) for e in data["units"]] == [(1, "reply", [0])]
    assert data["probed"] == 4 and data["silent"] == 3


def test_csv_has_a_header_and_a_row_per_unit():
    res = expect_ok(
        run_cli(
            "scan",
            "-p",
            "sim://",
            "--units",
            "1-2",
            "-t",
            "0.05",
            "--function",
            "read-coils",
            "--count",
            "3",
            "-o",
            "csv",
        )
    )
    assert res.lines[0] == "unit,answer,detail,ms"
    assert res.lines[1].startswith("1,reply,bits 1 0 1,"), res
    assert len(res.lines) == 2


def test_table_lists_the_units_found():
    res = expect_ok(run_cli("scan", "-p", "sim://", "--units", "1-2", "-t", "0.05", "-o", "table"))
    assert "Read Holding Registers" in res.stdout and "sim://" in res.stdout
    rows = [line for line in res.stdout.splitlines() if "registers 0" in line]
    assert len(rows) == 1 and rows[0].split()[1] == "1", res


def test_nobody_answering_is_exit_3(pty_pair):
    res = run_cli(
        "scan", "-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, "--units", "1-3", "-t", "0.05", "-o", "json"
    )
    line = assert_one_error_line(res, 3)
    assert "no unit answered" in line and "silent 3" in line
    data = scan_json(res)
    assert data["units"] == [] and data["probed"] == 3
    assert len(pty_pair.sent_by_mbtool()) == 3 * 8  # one 8-byte probe per unit


# --- garbled, foreign and late answers (TCP peers that misbehave on purpose) -------------------


def _mbap_reply(request: bytes, unit: int | None = None) -> bytes:
    """Read-holding-registers reply 42 to an MBAP request, from ``unit`` (default: the one asked)."""
    tid = request[:2]
    unit = request[6] if unit is None else unit
    return tid + struct.pack(">HHB", 0, 5, unit) + bytes([3, 2, 0, 42])


def test_bad_crc_answers_are_garbled_not_found(raw_responder):
    def reply(request: bytes) -> bytes:
        frame = rtu(bytes([request[0], 3, 2, 0, 42]))
        return frame[:-1] + bytes([frame[-1] ^ 0xFF])  # a wrong CRC

    srv = raw_responder(reply)
    res = run_cli("scan", "-p", srv.socket_target, "--units", "1-2", *GENEROUS, "-o", "json")
    assert res.returncode == 5, res
    data = scan_json(res)
    assert data["units"] == []
    assert [(e["unit"], e["answer"]) for e in data["garbled"]] == [(1, "garbled"), (2, "garbled")]
    assert "CRC" in data["garbled"][0]["error"]
    assert "no unit answered cleanly" in res.stderr


def test_an_answer_from_another_unit_is_not_credited_to_the_one_asked(raw_responder):
    srv = raw_responder(lambda request: _mbap_reply(request, unit=1))  # whoever is asked, unit 1 answers
    res = expect_ok(run_cli("scan", "-p", srv.tcp_target, "--units", "1-2", "-t", "0.5", "-o", "json"))
    data = scan_json(res)
    assert [(e["unit"], e["values"]) for e in data["units"]] == [(1, [42])], res
    assert data["garbled"] == [] and data["silent"] == 1


def test_a_gateway_saying_the_unit_is_unreachable_is_not_a_device(raw_responder):
    def reply(request: bytes) -> bytes:
        if request[6] == 1:
            return _mbap_reply(request)
        # exception 0B, Gateway Target Failed to Respond (spec §3): nobody behind it answered
        return request[:2] + struct.pack(">HHB", 0, 3, request[6]) + bytes([0x83, 0x0B])

    srv = raw_responder(reply)
    res = expect_ok(run_cli("scan", "-p", srv.tcp_target, "--units", "1-3", *GENEROUS, "-o", "json"))
    data = scan_json(res)
    assert [e["unit"] for e in data["units"]] == [1], res
    assert data["gateway"] == 2 and "unreachable behind the gateway 2" in res.stderr


def test_a_late_reply_is_credited_to_its_unit(raw_responder):
    def reply(request: bytes) -> bytes | None:
        if request[6] != 2:
            return None  # only unit 2 is there
        # Longer than the scan's timeout: the reply comes during a later probe, 0.35 s past unit
        # 2's (a loaded machine may wake the scan late) and as long before unit 10's ends.
        time.sleep(0.45)
        return _mbap_reply(request)

    srv = raw_responder(reply)
    res = expect_ok(run_cli("scan", "-p", srv.tcp_target, "--units", "1-10", *FAST, "-o", "json"))
    data = scan_json(res)
    (entry,) = data["units"]
    assert entry["unit"] == 2 and entry["late"] is True and entry["values"] == [42], res
    assert "ms" not in entry
    assert data["silent"] == 9


def test_the_summary_counts_every_probe_by_its_outcome(raw_responder):
    """Each probe is one transaction, classified as every summary of mbtool counts them
    (issue 32): in the stderr line and in -o json's "transactions"."""

    def reply(request: bytes) -> bytes | None:
        unit = request[0]
        if unit == 1:
            return rtu(bytes([1, 3, 2, 0, 42]))
        if unit == 2:
            frame = rtu(bytes([2, 3, 2, 0, 42]))
            return frame[:-1] + bytes([frame[-1] ^ 0xFF])  # a wrong CRC: the wire
        if unit == 3:
            return rtu(bytes([3, 0x83, 2]))  # exception 02
        if unit == 4:
            return rtu(bytes([9, 3, 2, 0, 42]))  # a whole frame from unit 9: not ours
        return None  # unit 5: nobody

    srv = raw_responder(reply)
    res = expect_ok(run_cli("scan", "-p", srv.socket_target, "--units", "1-5", "-t", "0.3", "-o", "json"))
    counts = scan_json(res)["transactions"]
    assert {k: counts[k] for k in ("transactions", "answered", "exception", "timeout", "corrupt", "not_ours")} == {
        "transactions": 5, "answered": 1, "exception": 1, "timeout": 1, "corrupt": 1, "not_ours": 1,
    }  # fmt: skip
    assert counts["exceptions_by_code"] == {"02": 1} and counts["link_lost"] == 0
    assert counts["rtt_seconds"]["max"] < 0.3  # the reply's and the exception's round trips
    assert (
        "transactions 5: answered 1, exception 1 (02:1), timeout 1, corrupt 1, not ours 1, link lost 0, connection 0; "
        "retries recovered 0; rtt min/avg/p95/max " in res.stderr
    ), res


# --- bad input: exit 2, one line, nothing sent -------------------------------------------------


@pytest.mark.parametrize(
    "args",
    [
        ("--units", "0"),
        ("--units", "0-5"),
        ("-u", "5-1"),
        ("--units", "1,,3"),
        ("--units", "x"),
        ("--units", "256"),
        ("--bauds", "0"),
        ("--bauds", "9600,fast"),
        ("--parities", "N,X"),
        ("--count", "0"),
        ("--count", "126"),
        ("--function", "report-id", "--address", "5"),
        ("--function", "write-register"),
        ("-t", "0"),
    ],
    ids=lambda args: " ".join(args),
)
def test_bad_input_sends_nothing(pty_pair, args):
    res = run_cli("scan", "-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, *args)
    assert_one_error_line(res, 2)
    assert pty_pair.sent_by_mbtool(SETTLE) == b""


@pytest.mark.parametrize("target", ["tcp", "socket", "sim"])
def test_sweep_needs_a_serial_line(silent_server, target):
    port = {"tcp": silent_server.tcp_target, "socket": silent_server.socket_target, "sim": "sim://"}[target]
    res = run_cli("scan", "-p", port, "--bauds", "9600,19200")
    line = assert_one_error_line(res, 2)
    assert "serial settings" in line
    assert silent_server.received_bytes(SETTLE) == b"" and silent_server.connections == 0


def test_no_port_is_exit_2():
    res = run_cli("scan", "--units", "1")
    assert "no port given" in assert_one_error_line(res, 2)


def test_unreadable_port_is_exit_6():
    res = run_cli("scan", "-p", "/dev/mbtool-no-such-port", "--units", "1", *FAST)
    assert "cannot open" in assert_one_error_line(res, 6)


def test_dry_run_shows_the_first_probe_and_opens_nothing(pty_pair):
    res = expect_ok(
        run_cli(
            "scan",
            "-p",
            pty_pair.mbtool_path,
            *PTY_SERIAL_OPTS,
            "--units",
            "5-7,9",
            "--dry-run",
            "-o",
            "plain",
        )
    )
    assert (
        "slave_address 5" in res.lines
        and f"crc {crc16(bytes([5, 3, 0, 0, 0, 1])).hex(' ').upper()} ok" in res.lines
    )
    assert "units 5-7,9 (4 probes)" in res.stderr
    assert pty_pair.sent_by_mbtool(SETTLE) == b""


# --- Ctrl-C and the progress bar -------------------------------------------------------------


def _wait_for(stream, needle: bytes, deadline: float) -> bytes:
    seen = b""
    end = time.monotonic() + deadline
    while needle not in seen:
        left = end - time.monotonic()
        assert left > 0, f"{needle!r} did not appear within {deadline} s; saw {seen!r}"
        ready, _, _ = select.select([stream], [], [], left)
        if ready:
            chunk = os.read(stream.fileno(), 4096)
            assert chunk, f"stream ended before {needle!r}; saw {seen!r}"
            seen += chunk
    return seen


def test_ctrl_c_stops_and_still_prints_what_was_found():
    proc = start_mbtool("scan", "-p", "sim://", "-t", "0.5", "--hex", "-o", "json", text=False)
    try:
        early = _wait_for(proc.stderr, b"TX 02 03", 20)  # unit 1 has answered, unit 2 is being probed
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=5)
    err = (early + err).decode()
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    data = json.loads(out)
    assert data["interrupted"] is True and [e["unit"] for e in data["units"]] == [1]
    assert "mbtool: interrupted; probes" in err


def test_progress_bar_on_a_terminal_leaves_stdout_clean():
    main, secondary = os.openpty()
    try:
        res = subprocess.run(
            [sys.executable, "-m", "mbtool", "scan", "-p", "sim://", "--units", "1-3", "-t", "0.05"],
            cwd=REPO_ROOT,
            env=mbtool_env({"TERM": "xterm"}),
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=secondary,
            timeout=20,
        )
        os.close(secondary)
        secondary = None
        shown = b""
        while select.select([main], [], [], 0.2)[0]:
            try:
                chunk = os.read(main, 65536)
            except OSError:  # EIO: the terminal's other side is closed and drained
                break
            if not chunk:
                break
            shown += chunk
    finally:
        if secondary is not None:
            os.close(secondary)
        os.close(main)
    assert res.returncode == 0
    assert res.stdout.decode().splitlines() == ["1 reply registers 0"]  # plain in a pipe, no bar
    assert b"unit" in shown and b"probes 3" in shown  # the bar and the summary went to the terminal
