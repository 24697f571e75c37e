"""serve, bridge and the exporter print a line when they are ready (``serving ...``,
``bridging ...``, ``exporting on ...``), and a supervisor or a test may stop them with SIGTERM
as soon as it reads it: that is a clean stop (exit 0), not a run interrupted (exit 130)."""

from __future__ import annotations

import signal

import click
import pytest
from helpers.run import first_line, run_cli, start_mbtool

from mbtool.cli import program
from mbtool.device.server import Server


def handlers_when_ready(monkeypatch, ready: str) -> list:
    """The SIGTERM handler in force each time a line starting with ``ready`` is written; the
    server itself stops at once (its loop is not run)."""
    seen = []
    echo = click.echo

    def watched(message=None, *args, **kwargs):
        if isinstance(message, str) and message.startswith(ready):
            seen.append(signal.getsignal(signal.SIGTERM))
        return echo(message, *args, **kwargs)

    monkeypatch.setattr(click, "echo", watched)
    monkeypatch.setattr(Server, "run", lambda self, tick=None: None)
    return seen


def test_serve_is_stoppable_cleanly_once_it_says_it_is_serving(monkeypatch):
    seen = handlers_when_ready(monkeypatch, "serving ")
    res = run_cli("serve", "-p", "tcp://127.0.0.1:0", "-q")
    assert res.returncode == 0, res
    assert len(seen) == 1 and seen[0] is not program._terminate, seen


def test_bridge_is_stoppable_cleanly_once_it_says_it_is_bridging(monkeypatch):
    seen = handlers_when_ready(monkeypatch, "bridging ")
    res = run_cli("bridge", "--listen", "tcp://127.0.0.1:0", "-p", "sim://", "-q")
    assert res.returncode == 0, res
    assert len(seen) == 1 and seen[0] is not program._terminate, seen


def test_exporter_stops_cleanly_on_a_sigterm_right_after_its_first_line(monkeypatch, tmp_path):
    """The exporter's stop is the KeyboardInterrupt the program's SIGTERM handler raises: one
    raised as soon as ``exporting on ...`` is written (where a signal may land) is exit 0."""
    echo = click.echo

    def interrupted_after(message=None, *args, **kwargs):
        echo(message, *args, **kwargs)
        if isinstance(message, str) and message.startswith("exporting on "):
            raise KeyboardInterrupt  # what program._terminate raises on SIGTERM

    monkeypatch.setattr(click, "echo", interrupted_after)
    res = run_cli(
        "exporter", "--listen", "127.0.0.1:0", "--maps", tmp_path, "--allow-target", "tcp://127.0.0.1:*"
    )
    assert res.returncode == 0, res
    assert res.stdout.startswith("exporting on http://127.0.0.1:"), res


@pytest.mark.parametrize("command", ["serve", "bridge"])
def test_a_hang_up_stops_serve_and_bridge_as_sigterm_does(command):
    """SIGHUP (the terminal or the ssh session gone; the signals campaign of issue 40): it
    killed them, or with SIGHUP taken as an interruption, ended them as a run interrupted
    (130) instead of the clean stop SIGTERM is, clients closed and the bridge's summary."""
    if command == "serve":
        proc = start_mbtool("serve", "-p", "tcp://127.0.0.1:0", "-q")
        first_line(proc, "serving ")
    else:
        proc = start_mbtool("bridge", "--listen", "tcp://127.0.0.1:0", "-p", "sim://")
        first_line(proc, "bridging ", proc.stderr)
    proc.send_signal(signal.SIGHUP)
    _, err = proc.communicate(timeout=10)
    assert proc.returncode == 0, err
    assert "interrupted" not in err, err
