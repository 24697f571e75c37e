"""Read commands: coils, discrete inputs, holding and input registers (FC 01-04)."""

from __future__ import annotations

import click

from mbtool.cli.options import ADDRESS, COUNT, VALUE_TYPES, Number, PositiveFloat, device_command
from mbtool.cli.session import execute, show
from mbtool.link.connection import Connection

POLL_HELP = """

    \b
    Polling: --interval SECONDS repeats the read over one link until interrupted
    (with --polls N, N times); --polls alone polls every 1 s. Each poll is stamped
    with the time; a failed poll is reported on stderr and polling goes on. At the
    end a summary line goes to stderr; exit 0 if every poll got its reply, else the
    code of the last failure (130 only if interrupted before any poll finished).
    """


def polling_options(function):
    """--interval and --polls, for the read commands, and what they do in --help."""
    function.__doc__ = (function.__doc__ or "").rstrip() + POLL_HELP
    function = click.option(
        "--polls",
        type=Number(0, 10**9, "polls"),
        help="Poll N times (0: until interrupted); interval 1 s unless --interval.",
    )(function)
    return click.option(
        "--interval",
        type=PositiveFloat(zero_ok=True),
        help="Poll every SECONDS over one open link (until interrupted unless --polls); "
        "0 polls back to back.",
    )(function)


def _run(connection: Connection, request, to_result, interval, polls) -> None:
    if (interval is None and polls is None) or getattr(connection, "dry_run", False):
        show(connection, to_result(execute(connection, request)))
        return
    from mbtool.cli.poll_output import Deferred, Output
    from mbtool.cli.render import default_format
    from mbtool.cli.session import trace_for
    from mbtool.link.polling import poll

    shown = Deferred(Output(connection.output_format or default_format()), to_result)
    poll(connection, request, shown, interval, polls, trace_for(connection))


# --- reads: FC 01-04 -------------------------------------------------------------------


def _read_bits(connection: Connection, kind, address: int, count: int, interval=None, polls=None) -> None:
    from mbtool.cli.render import Result

    def to_result(reply):
        items = [(address + i, bit) for i, bit in enumerate(reply.bits)]
        return Result(connection.unit, kind.function_code, kind.name, address, items)

    _run(connection, kind(address, count), to_result, interval, polls)


def _read_registers(
    connection: Connection,
    kind,
    address: int,
    count: int,
    value_type: str,
    order: str,
    interval=None,
    polls=None,
) -> None:
    from mbtool.cli.render import Result
    from mbtool.codec.values import decode_values, registers_needed

    def to_result(reply):
        items = [
            (address + offset, value) for offset, value in decode_values(reply.registers, value_type, order)
        ]
        return Result(
            connection.unit, kind.function_code, kind.name, address, items, value_type, list(reply.registers)
        )

    _run(connection, kind(address, registers_needed(value_type, count)), to_result, interval, polls)


@device_command("read-coils")
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
@polling_options
def read_coils(connection, address, count, interval, polls):
    """Read coils (FC 01). COUNT (default 1, at most 2000) bits from ADDRESS."""
    from mbtool.codec.data_access import ReadCoils

    _read_bits(connection, ReadCoils, address, count, interval, polls)


@device_command("read-discrete-inputs")
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
@polling_options
def read_discrete_inputs(connection, address, count, interval, polls):
    """Read discrete inputs (FC 02). COUNT (default 1, at most 2000) bits from ADDRESS."""
    from mbtool.codec.data_access import ReadDiscreteInputs

    _read_bits(connection, ReadDiscreteInputs, address, count, interval, polls)


@device_command("read-holding-registers", types=VALUE_TYPES)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
@polling_options
def read_holding_registers(connection, address, count, value_type, order, interval, polls):
    """Read holding registers (FC 03). COUNT (default 1) from ADDRESS, at most 125.

    With --type, COUNT counts values of that type (float32: 2 registers each);
    for --type string it counts registers (2 characters each).
    """
    from mbtool.codec.data_access import ReadHoldingRegisters

    _read_registers(connection, ReadHoldingRegisters, address, count, value_type, order, interval, polls)


@device_command("read-input-registers", types=VALUE_TYPES)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
@polling_options
def read_input_registers(connection, address, count, value_type, order, interval, polls):
    """Read input registers (FC 04). COUNT (default 1) from ADDRESS, at most 125.

    With --type, COUNT counts values of that type (float32: 2 registers each);
    for --type string it counts registers (2 characters each).
    """
    from mbtool.codec.data_access import ReadInputRegisters

    _read_registers(connection, ReadInputRegisters, address, count, value_type, order, interval, polls)
