"""Success is no exception (issue 41.6): a run that ran -- read --interval, ping, scan, poll,
monitor, dump, sunspec, diff, restore, write -m --
returns its Verdict (the summary line and the exit code), which cli.program.main writes after
what the run wrote to stdout; an error is still raised."""

from __future__ import annotations

import pytest
from helpers.monitor import READ_REQ, READ_RSP
from helpers.run import REPO_ROOT
from helpers.served import serve

from mbtool.cli.program import cli, main, register_schemes
from mbtool.errors import ExitCode, Verdict


def ended(*args: str):
    """What the command returns, invoked as main invokes it."""
    register_schemes()
    with cli.make_context("mbtool", list(args)) as ctx:
        return cli.invoke(ctx)


def test_polling_returns_its_verdict(capsys):
    verdict = ended("read-holding-registers", "0", "2", "--polls", "2", "--interval", "0", "-p", "sim://")
    assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.OK
    assert str(verdict).startswith("polls 2, replies 2, partial 0, timeouts 0, errors 0, skipped 0, ")


def test_ping_returns_its_verdict(capsys):
    verdict = ended("ping", "-c", "2", "-i", "0", "-q", "-p", "sim://")
    assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.OK
    assert str(verdict).startswith("2 sent, 2 answered, 0% lost")


def test_scan_returns_its_verdict_and_a_scan_that_found_none_too(capsys):
    verdict = ended("scan", "-p", "sim://", "--units", "1")
    assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.OK
    assert str(verdict).startswith("scan: probes 1, answered 1")
    verdict = ended("scan", "-p", "sim://", "--units", "2", "-t", "0.05")
    assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.TIMEOUT


def test_main_writes_the_verdict_as_its_one_line_and_exits_with_its_code(capsys):
    with pytest.raises(SystemExit) as done:
        main(["ping", "-c", "1", "-q", "-p", "sim://"])
    assert done.value.code == 0
    assert capsys.readouterr().err.startswith("mbtool: 1 sent, 1 answered, 0% lost")


# --- the other runs that end with a line of counts: monitor, dump, sunspec, diff, restore, write -m


def test_monitor_returns_its_verdict(tmp_path, capsys):
    recording = tmp_path / "bus.bin"
    recording.write_bytes(READ_REQ + READ_RSP)
    verdict = ended("monitor", "--from-file", str(recording))
    assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.OK
    assert str(verdict).startswith("frames 2, requests 1, responses 1")


def test_dump_returns_its_verdict_complete_or_cut_short(tmp_path, capsys):
    verdict = ended("dump", str(tmp_path / "d.toml"), "-p", "sim://", "--max-requests", "1")
    assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.PARTIAL
    assert str(verdict).startswith("dump: ") and "stopped after 1 request (--max-requests)" in str(verdict)


def test_diff_and_restore_return_their_verdicts(tmp_path, capsys):
    data = tmp_path / "saved.toml"
    data.write_text("sparse = true\n[holding_registers]\n5 = [900]\n")
    verdict = ended("diff", str(data), "-p", "sim://")
    assert isinstance(verdict, Verdict) and verdict.exit_code == 1 and str(verdict) == "1 difference"
    verdict = ended("restore", str(data), "-p", "sim://")
    assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.OK
    assert str(verdict).startswith("restore: wrote 1 holding register in 1 request; read back and confirmed")


def test_a_write_or_restore_that_stops_part_way_returns_its_verdict(tmp_path, capsys):
    data, saved, points = tmp_path / "device.toml", tmp_path / "saved.toml", tmp_path / "map.toml"
    data.write_text("sparse = true\n[holding_registers]\n0 = [0, 0]\n20 = [0]\n")  # no register 10
    saved.write_text("sparse = true\n[holding_registers]\n0 = [5, 6]\n10 = [7]\n")
    points.write_text('[points.a]\nref = 40001\naccess = "rw"\n\n[points.b]\nref = 40011\naccess = "rw"\n')
    with serve("--data", str(data)) as device:
        verdict = ended("restore", str(saved), "-p", device.target)
        assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.EXCEPTION
        assert str(verdict).startswith("restore stopped at holding 10: exception 02 Illegal Data Address")
        verdict = ended("write", "-m", str(points), "a=1", "b=2", "-p", device.target)
        assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.EXCEPTION
        assert str(verdict).startswith("write stopped at b (40011): exception 02 Illegal Data Address")


def test_sunspec_returns_its_verdict_when_it_read_part(capsys):
    quirk = REPO_ROOT / "tests" / "data" / "sunspec" / "zero-length-models.toml"
    with serve("--data", str(quirk)) as device:
        verdict = ended("sunspec", "-p", device.target, "-o", "json")
    assert isinstance(verdict, Verdict) and verdict.exit_code == ExitCode.PARTIAL
