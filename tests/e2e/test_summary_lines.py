"""Every summary line a command prints counts in words that agree with the count (issue 39
item 21): ``wrote 1 holding register in 1 request``, never ``in 1 requests``; ``2 requests``,
never ``2 request``.  Each command is run so that its counts are 1, then 2: restore (and its
dry run, and what it skips), diff, dump, scan's dry run, poll, decode, fifo, monitor --stats,
sunspec --map, and serve's and bridge's last line after clients came through them.

Peers: sim://, and mbtool serve and bridge as processes, read by mbtool itself.
"""

from __future__ import annotations

import re

import pytest
from helpers.run import REPO_ROOT, run_cli, run_mbtool
from helpers.served import bridge, serve

from mbtool.words import counted

pytestmark = pytest.mark.timeout(60)

COUNTS = (1, 2)


def _said(res, phrase: str) -> None:
    text = res.stdout + res.stderr
    assert "Traceback" not in text, str(res)
    assert phrase in text, f"{phrase!r} not in:\n{res}"
    # No count of one beside a plural of any noun here, nor another count beside a singular.
    assert not re.search(r"\b1 (requests|registers|values|differences|devices|frames|entries|models)\b", text)


def test_counted_is_singular_for_one_alone():
    assert [counted(n, "request") for n in (0, 1, 2)] == ["0 requests", "1 request", "2 requests"]
    assert counted(1, "entry", "entries") == "1 entry" and counted(3, "entry", "entries") == "3 entries"


def _data_file(tmp_path, holding: int, inputs: int = 0):
    """A dump with ``holding`` holding registers to change on sim:// (each alone: one request
    a register) and ``inputs`` input registers restore cannot write."""
    lines = ["sparse = true", "[holding_registers]"]
    lines += [f"{10 * i + 5} = {900 + i}" for i in range(holding)]
    if inputs:
        lines += ["[input_registers]"] + [f"{i} = 1" for i in range(inputs)]
    path = tmp_path / f"dump-{holding}-{inputs}.toml"
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("n", COUNTS)
def test_restore_and_diff(tmp_path, n):
    data = _data_file(tmp_path, n, inputs=n)
    dry = run_cli("restore", data, "-p", "sim://", "--dry-run")
    _said(dry, f"nothing was sent: {counted(n, 'request')} would write {counted(n, 'value')}")
    _said(run_cli("diff", _data_file(tmp_path, n), "-p", "sim://"), f"mbtool: {counted(n, 'difference')}\n")
    res = run_cli("restore", data, "-p", "sim://")
    _said(res, f"restore: wrote {counted(n, 'holding register')} in {counted(n, 'request')}; ")
    _said(res, f"skipped {counted(n, 'input register')} (read-only)")


@pytest.mark.parametrize("n", COUNTS)
def test_dump_stopped_by_max_requests(tmp_path, n):
    res = run_cli("dump", tmp_path / "d.toml", "-p", "sim://", "--max-requests", str(n))
    _said(res, f"; {counted(n, 'request')} in ")
    _said(res, f"stopped after {counted(n, 'request')} (--max-requests)")


@pytest.mark.parametrize("n", COUNTS)
def test_scan_dry_run(n):
    res = run_cli("scan", "-p", "sim://", "-u", f"1-{n}", "--dry-run")
    _said(res, f"({counted(n, 'probe')})")


@pytest.mark.parametrize("n", COUNTS)
def test_poll_verdict(tmp_path, n):
    devices = "".join(f'[devices.d{i}]\nlink = "a"\nread = ["4000{i + 1}"]\n' for i in range(n))
    inventory = tmp_path / "plant.toml"
    inventory.write_text(f'[links.a]\ntarget = "sim://"\n{devices}')
    _said(run_cli("poll", inventory, "--once"), f"{n} of {counted(n, 'device')} answered")


@pytest.mark.parametrize("n", COUNTS)
def test_decode_of_bad_frames(n):
    res = run_mbtool("decode", "-", input="01 03 00 00 00 01 84 0B\n" * n)
    _said(res, f"{n} of {counted(n, 'frame')} failed")


@pytest.mark.parametrize("n", COUNTS)
def test_fifo_entries(tmp_path, n):
    data = tmp_path / "fifo.toml"
    data.write_text(f"sparse = true\n[holding_registers]\n300 = [{n}, {', '.join(['7'] * n)}]\n")
    with serve("--data", str(data)) as device:
        res = run_cli("fifo", "300", "-p", device.target, "-o", "table")
    _said(res, f"{counted(n, 'entry', 'entries')} queued")


@pytest.mark.parametrize("n", COUNTS)
def test_monitor_statistics(tmp_path, n):
    recording = tmp_path / "bus.bin"
    recording.write_bytes(bytes.fromhex("01 03 00 00 00 01 84 0A") * n + b"\xff" * n)
    res = run_cli("monitor", "--from-file", recording, "--stats")
    _said(res, f"bus: {counted(n, 'frame')}, {counted(n, 'garbage byte')}")


@pytest.mark.parametrize("n", COUNTS)
def test_sunspec_map(tmp_path, n):
    models = ("--model", "1", "--model", "103")[: 2 * n]
    with serve("--data", str(REPO_ROOT / "examples" / "sunspec-twin.toml")) as device:
        res = run_cli("sunspec", "-p", device.target, "--map", tmp_path / "m.toml", *models, "-o", "json")
    _said(res, f"points of {counted(n, 'model')}\n")


@pytest.mark.parametrize("n", COUNTS)
def test_serve_and_bridge_last_lines(n):
    with serve(quiet=False) as server:
        with bridge("-p", server.target, "-q") as relay:
            for _ in range(n):
                assert run_cli("read-holding-registers", "0", "-p", relay.target).returncode == 0
            code, _, bridge_err = relay.stop()
        code, serve_out, _ = server.stop()
    assert code == 0
    said = f"{counted(n, 'transaction')}: {counted(n, 'reply', 'replies')}, 0 exceptions from devices"
    assert said in bridge_err and f"; {counted(n, 'connection')}" in bridge_err, bridge_err
    # The bridge keeps its one connection to the device.
    assert f"stopped: {counted(n, 'request')}, {counted(n, 'reply', 'replies')}, 1 connection" in serve_out, (
        serve_out
    )
