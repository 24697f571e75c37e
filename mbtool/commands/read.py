"""Read commands: coils, discrete inputs, holding and input registers (FC 01-04)."""

from __future__ import annotations

import click

from mbtool.connection import Connection, execute, show
from mbtool.options import ADDRESS, COUNT, VALUE_TYPES, device_command

# --- reads: FC 01-04 -------------------------------------------------------------------


def _read_bits(connection: Connection, kind, address: int, count: int) -> None:
    from mbtool.render import Result

    reply = execute(connection, kind(address, count))
    items = [(address + i, bit) for i, bit in enumerate(reply.bits)]
    show(connection, Result(connection.unit, kind.function_code, kind.name, address, items))


def _read_registers(
    connection: Connection, kind, address: int, count: int, value_type: str, order: str
) -> None:
    from mbtool.codec.values import decode_values, registers_needed
    from mbtool.render import Result

    reply = execute(connection, kind(address, registers_needed(value_type, count)))
    items = [
        (address + offset, value)
        for offset, value in decode_values(reply.registers, value_type, order.upper())
    ]
    show(
        connection,
        Result(
            connection.unit, kind.function_code, kind.name, address, items, value_type, list(reply.registers)
        ),
    )


@device_command("read-coils")
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
def read_coils(connection, address, count):
    """Read coils (FC 01). COUNT (default 1, at most 2000) bits from ADDRESS."""
    from mbtool.codec.data_access import ReadCoils

    _read_bits(connection, ReadCoils, address, count)


@device_command("read-discrete-inputs")
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
def read_discrete_inputs(connection, address, count):
    """Read discrete inputs (FC 02). COUNT (default 1, at most 2000) bits from ADDRESS."""
    from mbtool.codec.data_access import ReadDiscreteInputs

    _read_bits(connection, ReadDiscreteInputs, address, count)


@device_command("read-holding-registers", types=VALUE_TYPES)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
def read_holding_registers(connection, address, count, value_type, order):
    """Read holding registers (FC 03). COUNT (default 1) from ADDRESS, at most 125.

    With --type, COUNT counts values of that type (float32: 2 registers each);
    for --type string it counts registers (2 characters each).
    """
    from mbtool.codec.data_access import ReadHoldingRegisters

    _read_registers(connection, ReadHoldingRegisters, address, count, value_type, order)


@device_command("read-input-registers", types=VALUE_TYPES)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
def read_input_registers(connection, address, count, value_type, order):
    """Read input registers (FC 04). COUNT (default 1) from ADDRESS, at most 125.

    With --type, COUNT counts values of that type (float32: 2 registers each);
    for --type string it counts registers (2 characters each).
    """
    from mbtool.codec.data_access import ReadInputRegisters

    _read_registers(connection, ReadInputRegisters, address, count, value_type, order)
