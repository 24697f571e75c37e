"""A one-shot read's start-up (issue 41.9: at most 1.25 x ``python -c "import click"``,
bench/oneshot.py --instructions): it makes each shared option once."""

from __future__ import annotations

import click

from mbtool.cli.program import cli


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
