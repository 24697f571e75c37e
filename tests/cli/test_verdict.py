"""Success is no exception (issue 41.6): a run that ran -- read --interval, ping, scan, poll --
returns its Verdict (the summary line and the exit code), which cli.program.main writes after
what the run wrote to stdout; an error is still raised."""

from __future__ import annotations

import pytest

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
