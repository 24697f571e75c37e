"""Write commands: single and multiple coils and registers (FC 05, 06, 15, 16); ``write``,
which takes a device manual's references or a register map's point names; and
``write-bit``, one bit of a register (FC 22)."""

from __future__ import annotations

import sys
from functools import partial
from typing import TYPE_CHECKING

import click

from mbtool.cli.options import (
    NONFINITE_OPTION,
    ONE_REGISTER_TYPES,
    VALUE_TYPES,
    device_command,
    map_option,
    type_options_given,
)
from mbtool.cli.param_types import ADDRESS, Number
from mbtool.cli.results import PointRow, Points, Result, engineering_unit, value_text
from mbtool.cli.session import execute, open_client, show
from mbtool.codec.data_access import (
    ReadHoldingRegisters,
    WriteMultipleCoils,
    WriteMultipleRegisters,
    WriteSingleCoil,
    WriteSingleRegister,
)
from mbtool.codec.errors import ModbusException
from mbtool.codec.framing import is_broadcast
from mbtool.codec.values import decode_values, parse_registers, value_addresses
from mbtool.errors import UsageError, Verdict
from mbtool.link.connection import framer_name

if TYPE_CHECKING:
    from mbtool.registermap.point import Point  # imported when -m is used (decimal, 1 ms)

# --- writes: FC 05, 06, 15, 16 ------------------------------------------------------------

BIT_WORDS = {"1": True, "on": True, "true": True, "0": False, "off": False, "false": False}


def parse_bit(text: str) -> bool:
    try:
        return BIT_WORDS[text.lower()]
    except KeyError:
        raise UsageError(f"{text} is not a bit: use on|off|1|0") from None


def echoed_values(texts, registers: list[int], value_type: str, order: str) -> list:
    """What a write echoes of its values (issue 39 item 19).  A plain register is the number
    as typed: -5 stays -5, though the register holds 65531 (the same bits; the JSON's
    ``registers`` say so).  A value of another --type is what the registers now hold, read back
    through that type: a float32 shows the nearest float it could hold."""
    if value_type == "uint16":
        return [int(text, 0) for text in texts]  # parse_registers has checked each
    return decode_values(registers, value_type, order)


@device_command("write-coil")
@click.argument("address", type=ADDRESS)
@click.argument("state", metavar="on|off|1|0")
def write_coil(connection, settings, address, state):
    """Write one coil (FC 05). Switch the coil at ADDRESS on or off (also 1|0|true|false)."""
    request = WriteSingleCoil(address, parse_bit(state))
    execute(connection, settings, request)
    show(
        connection,
        settings,
        Result(connection.unit, request.function_code, request.name, address, [request.on]),
    )


@device_command("write-register", types=ONE_REGISTER_TYPES)
@click.argument("address", type=ADDRESS)
@click.argument("value")
def write_register(connection, settings, address, value, value_type, order):
    """Write one register (FC 06). VALUE (-32768..65535 or 0x hex) at ADDRESS."""
    (register,) = parse_registers((value,), value_type, order)
    request = WriteSingleRegister(address, register)
    execute(connection, settings, request)
    (written,) = echoed_values((value,), [register], value_type, order)
    show(
        connection,
        settings,
        Result(
            connection.unit,
            request.function_code,
            request.name,
            address,
            [written],
            value_type,
            [register],
        ),
    )


@device_command("write-coils")
@click.argument("address", type=ADDRESS)
@click.argument("bits", nargs=-1, required=True, metavar="BIT...")
def write_coils(connection, settings, address, bits):
    """Write coils (FC 15). BITs (on|off|1|0|true|false) from ADDRESS, at most 1968."""
    values = tuple(parse_bit(bit) for bit in bits)
    request = WriteMultipleCoils(address, values)
    execute(connection, settings, request)
    show(
        connection,
        settings,
        Result(connection.unit, request.function_code, request.name, address, list(values)),
    )


@device_command("write-registers", types=VALUE_TYPES)
@click.argument("address", type=ADDRESS)
@click.argument("values", nargs=-1, required=True, metavar="VALUE...")
@NONFINITE_OPTION
def write_registers(connection, settings, address, values, allow_nonfinite, value_type, order):
    """Write registers (FC 16). VALUEs from ADDRESS, at most 123 registers.

    Each VALUE is -32768..65535 or 0x hex, or a value of --type (a float32
    fills 2 registers in --order).
    """
    registers = parse_registers(values, value_type, order, allow_nonfinite)
    request = WriteMultipleRegisters(address, tuple(registers))
    execute(connection, settings, request)
    typed = echoed_values(values, registers, value_type, order)
    addresses = value_addresses(value_type, address, len(registers))
    show(
        connection,
        settings,
        Result(
            connection.unit,
            request.function_code,
            request.name,
            address,
            typed,
            value_type,
            registers,
            addresses=addresses,
        ),
    )


# --- write: by reference, or a register map's points by name ------------------------------

MULTIPLE_OPTION = click.option(
    "--multiple",
    is_flag=True,
    help="FC 15/16 even for one coil or register (some devices accept no FC 05/06).",
)
RMW_NEEDS = "--rmw, which reads the register first,"  # what a broadcast cannot do
RMW_OPTION = click.option(
    "--rmw",
    is_flag=True,
    help="Set a bit by reading the register and writing it back (FC 03, then FC 06), for "
    "devices without FC 22. Not atomic: a change the device makes in between is lost.",
)


@device_command("write", types=VALUE_TYPES)
@click.argument("targets", nargs=-1, required=True, metavar="REF VALUE... | NAME=VALUE...")
@map_option("write points by name, in their units")
@MULTIPLE_OPTION
@RMW_OPTION
@NONFINITE_OPTION
def write(connection, settings, targets, map, multiple, rmw, allow_nonfinite, value_type, order):
    """Write by a device manual's reference, or a register map's points by name.

    REF is a Modicon reference: 00001 coil 1, 40001 holding register 1 (six digits up
    to 465536; 4x0108 is 40108); discrete inputs (1x) and input registers (3x) are
    read-only. One value is FC 05/06, more are FC 15/16 (--multiple: always 15/16).

    With -m MAP: NAME=VALUE in the point's units (the map's scale and offset are
    undone), an enum label (state=running) or on/off for a bit. Every value is checked
    against its point's type before anything is sent (a float32 that cannot hold the
    decimal given is a warning naming the value written). A bit of a register is written
    with FC 22 (--rmw: FC 03 then FC 06). The first write that fails stops the rest: each
    point is then listed as written, refused, failed or not-sent, and the exit code is the
    failure's own.
    """
    type_options_given(map)  # refused with a map
    if map:
        return _write_map(connection, settings, map, targets, multiple, rmw, allow_nonfinite)
    if len(targets) < 2:
        raise click.UsageError("give a reference and a value, such as 40001 17, or -m MAP NAME=VALUE")
    _write_reference(
        connection, settings, targets[0], targets[1:], multiple, value_type, order, allow_nonfinite
    )


def _write_reference(
    connection, settings, text: str, values, multiple: bool, value_type: str, order: str, nonfinite: bool
) -> None:
    from mbtool.codec.tables import (  # noqa: PLC0415 - REF, write-bit only
        parse_reference,
        reference,
        write_of,
    )

    if "=" in text:
        raise UsageError(f"{text}: NAME=VALUE writes a point of a register map: give -m MAP")
    table, address = parse_reference(text)
    if not table.writable:
        raise UsageError(
            f"{text} is {table.item} {address + 1}: {table.items} are read-only "
            "(coils 0xxxx and holding registers 4xxxx are the writable ones)"
        )
    if table.bits:
        written: list = [parse_bit(value) for value in values]
        request = write_of(table, address, written, multiple)
        addresses = list(range(address, address + len(written)))
        registers, kind = None, None
    else:
        registers = parse_registers(values, value_type, order, nonfinite)
        request = write_of(table, address, registers, multiple)
        written = echoed_values(values, registers, value_type, order)
        addresses = value_addresses(value_type, address, len(registers))
        kind = value_type
    execute(connection, settings, request)
    refs = [reference(table, at) for at in addresses]
    show(
        connection,
        settings,
        Result(
            connection.unit,
            request.function_code,
            request.name,
            address,
            written,
            kind,
            registers,
            refs=refs,
            addresses=addresses,
        ),
    )


def _write_map(
    connection, settings, path: str, assignments, multiple: bool, rmw: bool, nonfinite: bool
) -> Verdict | None:
    """The points written, or the Verdict of a write that stopped part-way (what each point came
    to is in the report)."""
    from mbtool.cli.writes import Step, failure, report, send_all  # noqa: PLC0415 - write -m only
    from mbtool.library import load_named_map  # noqa: PLC0415 - the map loader, 4-8 ms: -m only
    from mbtool.registermap.plan import write_request  # noqa: PLC0415 - decimal, 2 ms: -m, write-bit only
    from mbtool.registermap.point import NoScaleFactor  # noqa: PLC0415 - with decimal, 1 ms: -m only

    register_map = load_named_map(path)
    wanted: list[tuple[Point, str]] = []  # every value checked before anything is sent
    for assignment in assignments:
        name, sep, text = assignment.partition("=")
        name = name.strip()
        if not sep or not name:
            raise UsageError(f"{assignment}: write a point as NAME=VALUE (such as setpoint=22.5)")
        (point,) = register_map.select([name])
        try:
            write_request(point, text, multiple, nonfinite)
        except NoScaleFactor:
            pass  # checked once the device has said its scale factor
        if any(known is point for known, _ in wanted):
            raise UsageError(f"{name} is given twice: write each point once")
        wanted.append((point, text))
    factors = [point.scale_ref for point, _ in wanted if point.scale_ref is not None]
    broadcast = is_broadcast(connection.unit, framer_name(connection))
    if factors and broadcast:
        raise UsageError(
            f"{factors[0].name} is read first, to scale what is written: unit 0 (broadcast) cannot be read"
        )
    bits_by_rmw = rmw and any(point.bit is not None for point, _ in wanted)
    rows: list[PointRow] = []

    def send(step: Step) -> None:
        point, value, request, factor = step.work
        if point.bit is not None:
            raw = _write_bit(connection, client, point.address, point.bit, value, rmw)
        else:
            client.execute(connection.unit, request)
            raw = (value,) if point.table.bits else tuple(point.registers_of(value))
        shown = value if point.is_bit or not raw else point.value_of(list(raw), factor)
        rows.append(
            PointRow(
                point.name,
                shown,
                point.unit,
                point.ref,
                raw,
                point.table.bits,
                point.description,
                no_label=point.no_label(shown),
            )
        )

    with open_client(connection, settings, RMW_NEEDS if bits_by_rmw else "") as client:
        # A scaled point (SunSpec's WMaxLimPct with its WMaxLimPct_SF) is written in the
        # scale the device reports now: its scale factors are read first.
        scale = _scale_factors(connection, settings, client, factors, register_map.max_gap)
        steps, warnings = [], []
        for point, text in wanted:
            factor = scale.get(point.scale_ref.name) if point.scale_ref is not None else None
            request = write_request(point, text, multiple, nonfinite, factor)
            value = point.raw_for(text, nonfinite, factor)
            held = point.held(text, value, factor)
            if held is not None:
                warnings.append(
                    f"{point.name}: a {point.type} cannot hold {text.strip()}; "
                    f"writing {value_text(held)} {point.unit}".rstrip()
                )
            shown = value if point.is_bit else point.value_of(point.registers_of(value), factor)
            item = {"table": point.table.name, "address": point.address, "ref": point.ref, "name": point.name}
            item |= {**engineering_unit(point.unit), "new": shown}
            steps.append(Step(f"{point.name} ({point.ref})", (item,), (point, value, request, factor)))
        for warning in warnings:
            print(f"mbtool: warning: {warning}", file=sys.stderr)
        if settings.dry_run:  # no write depends on a reply: show every frame
            for step in steps:
                point, _, request, _ = step.work
                if point.bit is not None and rmw:
                    request = _rmw_read(point.address)
                client.show(connection.unit, request)
            client.finish(connection.unit)
        outcome = send_all(steps, send, broadcast)
    if outcome.error is not None:
        summary = failure("write", outcome)
        items = [item for step in steps for item in step.items]
        end = {"error": str(summary), "exit_code": int(summary.exit_code)}
        report(settings, items, {"unit": connection.unit, "map": register_map.source}, end)
        return summary
    show(connection, settings, Points(connection.unit, register_map.source, rows))
    return None


def _scale_factors(connection, settings, client, factors: list, max_gap: int) -> dict:
    """The value each scale-factor point holds now (None: it has none), read before any
    write; with --dry-run their reads are shown and the run ends there, as the writes
    depend on the replies."""
    from mbtool.registermap.plan import MapReader  # noqa: PLC0415 - with decimal, 2 ms: -m and write-bit only

    if not factors:
        return {}
    reader = MapReader(factors, max_gap)
    if settings.dry_run:
        for block in reader.blocks:
            client.show(connection.unit, block.request)
        client.then = "then each point is written in the scale its scale factor reads"
        client.finish(connection.unit)
    return {
        reading.point.name: reading.value for reading in reader.read(partial(client.execute, connection.unit))
    }


class MaskWriteUnsupported(ModbusException):
    """Exception 01 to FC 22: the message names --rmw, the way around it."""

    def __init__(self, error: ModbusException) -> None:
        super().__init__(error.function_code, error.exception_code)
        self.args = (
            f"{error}: the device has no Mask Write Register; --rmw sets the bit by reading the "
            "register and writing it back (FC 03, then FC 06; not atomic)",
        )


def _rmw_read(address: int):
    return ReadHoldingRegisters(address, 1)


def _write_bit(connection, client, address: int, bit: int, on: bool, rmw: bool) -> tuple:
    """Set or clear one bit of a holding register: FC 22 (spec §3), or with ``rmw`` FC 03
    then FC 06.  The register as written when it is known (rmw), else ()."""
    from mbtool.codec.tables import HOLDING_REGISTERS, reference  # noqa: PLC0415 - REF and write-bit only
    from mbtool.registermap.plan import (  # noqa: PLC0415 - decimal, 2 ms: -m, write-bit only
        bit_request,
        with_bit,
    )

    if not rmw:
        try:
            client.execute(connection.unit, bit_request(address, bit, on))
        except ModbusException as error:
            if error.exception_code == 0x01:
                raise MaskWriteUnsupported(error) from None
            raise
        return ()
    current = client.execute(connection.unit, _rmw_read(address)).registers[0]
    value = with_bit(current, bit, on)
    print(
        f"mbtool: --rmw: {reference(HOLDING_REGISTERS, address)} read 0x{current:04X}, "
        f"writing 0x{value:04X}; not atomic: a change the device made in between is lost",
        file=sys.stderr,
    )
    client.execute(connection.unit, WriteSingleRegister(address, value))
    return (value,)


@device_command("write-bit")
@click.argument("ref", metavar="REF")
@click.argument("bit", type=Number(0, 15, "bit"))
@click.argument("state", metavar="on|off")
@RMW_OPTION
def write_bit(connection, settings, ref, bit, state, rmw):
    """Set or clear one BIT (0-15, 0 the least significant) of a holding register.

    REF is a Modicon reference of a holding register (40001, 400001, 4x0001). Mask
    Write Register (FC 22) changes that bit and leaves the others; a device without
    FC 22 answers exception 01, and --rmw reads the register and writes it back
    (FC 03, then FC 06) instead, which is not atomic.
    """
    from mbtool.codec.tables import HOLDING_REGISTERS, parse_reference  # noqa: PLC0415 - REF, write-bit only

    table, address = parse_reference(ref)
    if table is not HOLDING_REGISTERS:
        raise UsageError(
            f"{ref} is {table.item} {address + 1}: write-bit changes a bit of a holding register (4xxxx)"
        )
    on = parse_bit(state)
    with open_client(connection, settings, RMW_NEEDS if rmw else "") as client:
        if settings.dry_run:
            from mbtool.registermap.plan import bit_request  # noqa: PLC0415 - decimal, 2 ms: write-bit only

            client.show(connection.unit, _rmw_read(address) if rmw else bit_request(address, bit, on))
            client.finish(connection.unit)
        raw = _write_bit(connection, client, address, bit, on, rmw)
    function, name = (0x06, "Write Single Register") if rmw else (0x16, "Mask Write Register")
    extra = {"bit": bit} | ({"register": raw[0]} if raw else {})
    # Echoed as typed (issue 39 item 19): "40011 bit 2 on", not "40011 1", which reads as the
    # whole register's value.
    texts = [f"bit {bit} {'on' if on else 'off'}"]
    show(
        connection,
        settings,
        Result(connection.unit, function, name, address, [on], extra=extra, refs=[ref], texts=texts),
    )
