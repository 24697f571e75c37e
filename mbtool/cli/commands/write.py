"""Write commands: single and multiple coils and registers (FC 05, 06, 15, 16)."""

from __future__ import annotations

import click

from mbtool.cli.options import ADDRESS, ONE_REGISTER_TYPES, VALUE_TYPES, device_command
from mbtool.cli.session import execute, show
from mbtool.codec.errors import RequestError

# --- writes: FC 05, 06, 15, 16 ------------------------------------------------------------

BIT_WORDS = {"1": True, "on": True, "true": True, "0": False, "off": False, "false": False}


def parse_bit(text: str) -> bool:
    try:
        return BIT_WORDS[text.lower()]
    except KeyError:
        raise RequestError(f"{text} is not a bit: use on|off|1|0") from None


@device_command("write-coil")
@click.argument("address", type=ADDRESS)
@click.argument("state", metavar="on|off|1|0")
def write_coil(connection, address, state):
    """Write one coil (FC 05). Switch the coil at ADDRESS on or off (also 1|0|true|false)."""
    from mbtool.cli.render import Result
    from mbtool.codec.data_access import WriteSingleCoil

    request = WriteSingleCoil(address, parse_bit(state))
    execute(connection, request)
    show(
        connection,
        Result(connection.unit, request.function_code, request.name, address, [(address, request.on)]),
    )


@device_command("write-register", types=ONE_REGISTER_TYPES)
@click.argument("address", type=ADDRESS)
@click.argument("value")
def write_register(connection, address, value, value_type, order):
    """Write one register (FC 06). VALUE (-32768..65535 or 0x hex) at ADDRESS."""
    from mbtool.cli.render import Result
    from mbtool.codec.data_access import WriteSingleRegister
    from mbtool.codec.values import decode_values, parse_registers

    (register,) = parse_registers((value,), value_type, order)
    request = WriteSingleRegister(address, register)
    execute(connection, request)
    # As write-registers does: the value as the register now holds it, in the user's --type.
    ((_, written),) = decode_values((register,), value_type, order)
    show(
        connection,
        Result(
            connection.unit,
            request.function_code,
            request.name,
            address,
            [(address, written)],
            value_type,
            [register],
        ),
    )


@device_command("write-coils")
@click.argument("address", type=ADDRESS)
@click.argument("bits", nargs=-1, required=True, metavar="BIT...")
def write_coils(connection, address, bits):
    """Write coils (FC 15). BITs (on|off|1|0|true|false) from ADDRESS, at most 1968."""
    from mbtool.cli.render import Result
    from mbtool.codec.data_access import WriteMultipleCoils

    values = tuple(parse_bit(bit) for bit in bits)
    request = WriteMultipleCoils(address, values)
    execute(connection, request)
    items = [(address + i, bit) for i, bit in enumerate(values)]
    show(connection, Result(connection.unit, request.function_code, request.name, address, items))


@device_command("write-registers", types=VALUE_TYPES)
@click.argument("address", type=ADDRESS)
@click.argument("values", nargs=-1, required=True, metavar="VALUE...")
def write_registers(connection, address, values, value_type, order):
    """Write registers (FC 16). VALUEs from ADDRESS, at most 123 registers.

    Each VALUE is -32768..65535 or 0x hex, or a value of --type (a float32
    fills 2 registers in --order).
    """
    from mbtool.cli.render import Result
    from mbtool.codec.data_access import WriteMultipleRegisters
    from mbtool.codec.values import decode_values, parse_registers

    registers = parse_registers(values, value_type, order)
    request = WriteMultipleRegisters(address, tuple(registers))
    execute(connection, request)
    # Report the values as the device now holds them, read back through the same type.
    typed = decode_values(tuple(registers), value_type, order)
    items = [(address + offset, value) for offset, value in typed]
    show(
        connection,
        Result(connection.unit, request.function_code, request.name, address, items, value_type, registers),
    )
