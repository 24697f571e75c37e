"""A one-shot read's start-up (issue 41.9: at most 1.25 x ``python -c "import click"``,
bench/oneshot.py --instructions): it makes each shared option once, and it imports neither
the socket module nor the signal module, whose enums cost more than the read itself."""

from __future__ import annotations

import subprocess
import sys

import click
import pytest

from mbtool.cli.program import cli


def _imported_by_a_read(target: str) -> set[str]:
    code = (
        "import sys; from mbtool.cli import main; sys.argv = ['mbtool', 'read-holding-registers', '0', '3',"
        f" '-p', {target!r}, '-o', 'json', '-t', '0.3'];\n"
        "import atexit; atexit.register(lambda: print(' '.join(sorted(sys.modules)), file=sys.stderr))\n"
        "main()"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    return set(result.stderr.split())


@pytest.mark.parametrize("target", ["sim://", "tcp://127.0.0.1:1"])  # port 1: refused, after the connect
def test_a_one_shot_read_imports_neither_socket_nor_signal(target):
    imported = _imported_by_a_read(target)
    assert "mbtool.cli.commands.read" in imported
    assert "socket" not in imported and "signal" not in imported


def _command(name: str) -> click.Command:
    with click.Context(cli) as ctx:
        command = cli.get_command(ctx, name)
    assert command is not None
    return command


def _param(command: click.Command, name: str) -> click.Parameter:
    return next(param for param in command.params if param.name == name)


def test_the_commands_of_a_module_share_their_link_options_and_scan_keeps_its_own_timeout():
    read, coils, scan, ping = (
        _command(name) for name in ("read-holding-registers", "read-coils", "scan", "ping")
    )
    assert _param(read, "port") is _param(coils, "port")  # made once
    assert _param(read, "value_type") is _param(_command("read-input-registers"), "value_type")
    assert _param(scan, "timeout").default == 0.2 and "each unit's reply" in (
        _param(scan, "timeout").help or ""
    )
    for other in (read, coils, ping):  # scan's change is scan's alone
        assert _param(other, "timeout").default == 1.0
        assert "each unit's reply" not in (_param(other, "timeout").help or "")
