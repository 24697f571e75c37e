"""The command line: the only layer that imports everything (design notes).

Shared options are decorators defined once; every error reaches ``main``,
which prints one line on stderr and exits with the code of ``errors.ExitCode``.
"""

from __future__ import annotations

import functools
import os
import signal
import sys
from collections.abc import Callable
from dataclasses import dataclass

import click

from mbtool import __version__
from mbtool.errors import ExitCode, MbtoolError, RequestError, exit_code_for

# --- parameter types --------------------------------------------------------------


def parse_int(text: str, what: str = "number") -> int:
    """Decimal or 0x hex (also 0o / 0b); leading zeros are decimal, as a user means them."""
    text = text.strip()
    try:
        if text.lstrip("+-").isdigit():
            return int(text, 10)
        return int(text, 0)
    except ValueError:
        raise RequestError(f"{what} {text!r} is not a number (decimal or 0x hex)") from None


class Number(click.ParamType):
    """An integer in decimal or hex within [low, high]."""

    name = "number"

    def __init__(self, low: int, high: int, what: str) -> None:
        self.low, self.high, self.what = low, high, what

    def convert(self, value, param, ctx):
        if isinstance(value, int):
            number = value
        else:
            try:
                number = parse_int(value, self.what)
            except RequestError as error:
                self.fail(str(error), param, ctx)
        if not self.low <= number <= self.high:
            self.fail(f"{self.what} {number} is out of range {self.low}..{self.high}", param, ctx)
        return number


ADDRESS = Number(0, 0xFFFF, "address")
COUNT = Number(0, 0xFFFF, "count")  # the spec limit is the codec's to check, per function code


def _is_number(token: str) -> bool:
    try:
        float(token) if not token.lower().lstrip("+-").startswith("0x") else int(token, 16)
    except ValueError:
        return False
    return True


class DeviceCommand(click.Command):
    """Takes negative numbers as arguments (write-register 100 -5) yet still refuses unknown options."""

    def parse_args(self, ctx, args):
        known = {name for param in self.get_params(ctx) for name in param.opts + param.secondary_opts}
        for token in args:
            if token == "--":
                break
            if token.startswith("-") and len(token) > 1 and not _is_number(token):
                name = token.split("=", 1)[0]
                if name not in known and not (name[:2] in known and not name.startswith("--")):
                    raise click.NoSuchOption(name, ctx=ctx)
        return super().parse_args(ctx, args)


class PositiveFloat(click.ParamType):
    name = "seconds"

    def convert(self, value, param, ctx):
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value!r} is not a number of seconds", param, ctx)
        if not number > 0 or number != number or number == float("inf"):
            self.fail(f"must be more than 0 seconds, not {value}", param, ctx)
        return number


# --- shared options ------------------------------------------------------------------


@dataclass
class Connection:
    port: str | None
    unit: int
    framer: str | None
    baud: int
    parity: str
    bytesize: int
    stopbits: int
    timeout: float
    retries: int
    echo: bool
    hex: bool
    output_format: str | None


CONNECTION_OPTIONS = [
    click.option("-p", "--port", envvar="MBTOOL_PORT", metavar="TARGET",
                 help="tcp://HOST[:PORT], a serial device, socket://HOST:PORT, rfc2217://HOST:PORT, "
                 "loop:// or sim:// (the built-in device). [env: MBTOOL_PORT]"),
    click.option("-u", "--unit", envvar="MBTOOL_UNIT", type=Number(0, 255, "unit"), default=1,
                 show_default=True, help="Unit (slave) id; 0 broadcasts a write. [env: MBTOOL_UNIT]"),
    click.option("--framer", type=click.Choice(["rtu", "ascii", "tcp"]),
                 help="Framing: tcp for tcp:// targets, rtu otherwise."),
    click.option("-b", "--baud", type=Number(1, 4_000_000, "baud rate"), default=19200, show_default=True,
                 help="Serial baud rate."),
    click.option("--parity", type=click.Choice(["N", "E", "O"], case_sensitive=False), default="E",
                 show_default=True, help="Serial parity."),
    click.option("--bytesize", type=click.Choice(["7", "8"]), default="8", show_default=True,
                 help="Serial data bits (ASCII mode classically uses 7)."),
    click.option("--stopbits", type=click.Choice(["1", "2"]), default="1", show_default=True,
                 help="Serial stop bits."),
    click.option("-t", "--timeout", type=PositiveFloat(), default=1.0, show_default=True,
                 help="Seconds to wait for each reply."),
    click.option("--retries", type=Number(0, 100, "retries"), default=0, show_default=True,
                 help="Times to resend after a timeout or a bad reply."),
    click.option("--echo", is_flag=True, help="Strip the local echo of a half-duplex adapter."),
    click.option("--hex", "hex_trace", is_flag=True,
                 help="Print every frame sent and received (stderr), checksum checked."),
    click.option("-o", "--format", "output_format", type=click.Choice(["table", "plain", "json", "csv"]),
                 help="Output format: table on a terminal, plain in a pipe."),
]

TYPE_OPTIONS = [
    click.option("--type", "value_type",
                 type=click.Choice(["uint16", "int16", "uint32", "int32", "float32", "uint64", "int64",
                                    "float64", "hex", "string"]),
                 default="uint16", show_default=True, help="How to read the registers."),
    click.option("--order", type=click.Choice(["ABCD", "CDAB", "BADC", "DCBA"], case_sensitive=False),
                 default="ABCD", show_default=True,
                 help="Byte order of multi-register values: ABCD big-endian, CDAB word-swapped, "
                 "BADC byte-swapped, DCBA little-endian."),
]


def device_command(name: str, *, typed: bool = False, **settings) -> Callable:
    """A command that talks to a device: the shared options, then a Connection as first argument."""

    def decorate(function: Callable) -> Callable:
        @functools.wraps(function)
        def run(port, unit, framer, baud, parity, bytesize, stopbits, timeout, retries, echo, hex_trace,
                output_format, **kwargs):
            connection = Connection(port, unit, framer, baud, parity.upper(), int(bytesize), int(stopbits),
                                    timeout, retries, echo, hex_trace, output_format)
            return function(connection, **kwargs)

        for option in reversed(CONNECTION_OPTIONS + (TYPE_OPTIONS if typed else [])):
            run = option(run)
        # Negative register values (write-register 100 -5) must not be taken for options.
        context = {"ignore_unknown_options": True, **settings.pop("context_settings", {})}
        return cli.command(name, cls=DeviceCommand, context_settings=context, **settings)(run)

    return decorate


@click.group(context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(__version__, "-V", "--version", prog_name="mbtool")
def cli() -> None:
    """A Modbus master for the command line: RTU, ASCII and TCP, every function code,
    and the frames on the wire shown as they are.

    Try it without hardware:  mbtool read-holding-registers 0 10 -p sim://

    Exit codes: 0 ok, 2 bad input (nothing sent), 3 no response, 4 Modbus exception,
    5 invalid response, 6 cannot open or connect, 130 interrupted.
    """


# --- running a request ------------------------------------------------------------


def execute(connection: Connection, request) -> object:
    """Open the link, run one transaction, close it; the reply (None for broadcast)."""
    from mbtool.client import Client
    from mbtool.codec.framing import make_framer
    from mbtool.render import HexTrace
    from mbtool.transport import SerialSettings, default_framer, open_transport

    if not connection.port:
        raise RequestError("no port given: use -p TARGET or set MBTOOL_PORT (try -p sim:// for the built-in device)")
    if connection.unit == 0 and not request.broadcastable:
        raise RequestError(f"unit 0 is broadcast, which only writes may use; {request.name} needs a unit 1..255")
    framer_name = connection.framer or default_framer(connection.port)
    settings = SerialSettings(connection.baud, connection.parity, connection.bytesize, connection.stopbits)
    transport = open_transport(connection.port, settings, connection.timeout, framer_name)
    try:
        client = Client(transport, make_framer(framer_name), timeout=connection.timeout,
                        retries=connection.retries, echo=connection.echo, baud=connection.baud)
        if connection.hex:
            client.trace = HexTrace()
        return client.execute(connection.unit, request)
    finally:
        transport.close()


def show(connection: Connection, result) -> None:
    from mbtool.render import default_format, render

    if connection.unit == 0:
        result.note = "broadcast: no device confirms a write to unit 0"
        click.echo(f"mbtool: {result.note}", err=True)
    render(result, connection.output_format or default_format())


# --- reads: FC 01-04 -------------------------------------------------------------------


def _read_bits(connection: Connection, kind, address: int, count: int) -> None:
    from mbtool.render import Result

    reply = execute(connection, kind(address, count))
    items = [(address + i, bit) for i, bit in enumerate(reply.bits)]
    show(connection, Result(connection.unit, kind.function_code, kind.name, address, items))


def _read_registers(connection: Connection, kind, address: int, count: int, value_type: str, order: str) -> None:
    from mbtool.codec.values import decode_values, registers_needed
    from mbtool.render import Result

    reply = execute(connection, kind(address, registers_needed(value_type, count)))
    items = [(address + offset, value) for offset, value in decode_values(reply.registers, value_type, order.upper())]
    show(connection, Result(connection.unit, kind.function_code, kind.name, address, items, value_type,
                            list(reply.registers)))


@device_command("read-coils")
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
def read_coils(connection, address, count):
    """Read COUNT coils from ADDRESS (FC 01); at most 2000."""
    from mbtool.codec.data_access import ReadCoils

    _read_bits(connection, ReadCoils, address, count)


@device_command("read-discrete-inputs")
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
def read_discrete_inputs(connection, address, count):
    """Read COUNT discrete inputs from ADDRESS (FC 02); at most 2000."""
    from mbtool.codec.data_access import ReadDiscreteInputs

    _read_bits(connection, ReadDiscreteInputs, address, count)


@device_command("read-holding-registers", typed=True)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
def read_holding_registers(connection, address, count, value_type, order):
    """Read COUNT holding registers from ADDRESS (FC 03); at most 125 registers.

    With --type, COUNT counts values of that type (float32: 2 registers each);
    for --type string it counts registers (2 characters each).
    """
    from mbtool.codec.data_access import ReadHoldingRegisters

    _read_registers(connection, ReadHoldingRegisters, address, count, value_type, order)


@device_command("read-input-registers", typed=True)
@click.argument("address", type=ADDRESS)
@click.argument("count", type=COUNT, default=1)
def read_input_registers(connection, address, count, value_type, order):
    """Read COUNT input registers from ADDRESS (FC 04); at most 125 registers.

    With --type, COUNT counts values of that type (float32: 2 registers each);
    for --type string it counts registers (2 characters each).
    """
    from mbtool.codec.data_access import ReadInputRegisters

    _read_registers(connection, ReadInputRegisters, address, count, value_type, order)


# --- writes: FC 05, 06, 15, 16 ------------------------------------------------------------

BIT_WORDS = {"1": True, "on": True, "true": True, "0": False, "off": False, "false": False}


def parse_bit(text: str) -> bool:
    try:
        return BIT_WORDS[text.lower()]
    except KeyError:
        raise RequestError(f"{text!r} is not a bit: use on|off|1|0") from None


def parse_registers(values: tuple[str, ...], value_type: str, order: str) -> list[int]:
    """The registers for the values the user typed, each checked against its type."""
    from mbtool.codec.values import encode_values, parse_register, parse_value

    if value_type == "uint16":
        return [parse_register(text) for text in values]  # -32768..65535, as the contract says
    return encode_values([parse_value(text, value_type) for text in values], value_type, order.upper())


@device_command("write-coil")
@click.argument("address", type=ADDRESS)
@click.argument("state", metavar="on|off|1|0")
def write_coil(connection, address, state):
    """Switch one coil at ADDRESS on or off (FC 05)."""
    from mbtool.codec.data_access import WriteSingleCoil
    from mbtool.render import Result

    request = WriteSingleCoil(address, parse_bit(state))
    execute(connection, request)
    show(connection, Result(connection.unit, request.function_code, request.name, address, [(address, request.on)]))


@device_command("write-register", typed=True)
@click.argument("address", type=ADDRESS)
@click.argument("value")
def write_register(connection, address, value, value_type, order):
    """Write one holding register at ADDRESS (FC 06).  VALUE is -32768..65535 or 0x hex."""
    from mbtool.codec.data_access import WriteSingleRegister
    from mbtool.codec.values import TYPES
    from mbtool.render import Result

    if TYPES[value_type].registers != 1:
        raise RequestError(f"--type {value_type} needs more than one register: use write-registers")
    (register,) = parse_registers((value,), value_type, order)
    request = WriteSingleRegister(address, register)
    execute(connection, request)
    show(connection, Result(connection.unit, request.function_code, request.name, address, [(address, register)],
                            "uint16"))


@device_command("write-coils")
@click.argument("address", type=ADDRESS)
@click.argument("bits", nargs=-1, required=True, metavar="BIT...")
def write_coils(connection, address, bits):
    """Write coils from ADDRESS (FC 15): each BIT is on|off|1|0; at most 1968."""
    from mbtool.codec.data_access import WriteMultipleCoils
    from mbtool.render import Result

    values = tuple(parse_bit(bit) for bit in bits)
    request = WriteMultipleCoils(address, values)
    execute(connection, request)
    items = [(address + i, bit) for i, bit in enumerate(values)]
    show(connection, Result(connection.unit, request.function_code, request.name, address, items))


@device_command("write-registers", typed=True)
@click.argument("address", type=ADDRESS)
@click.argument("values", nargs=-1, required=True, metavar="VALUE...")
def write_registers(connection, address, values, value_type, order):
    """Write holding registers from ADDRESS (FC 16); at most 123 registers.

    Each VALUE is -32768..65535 or 0x hex, or a value of --type (a float32
    fills 2 registers in --order).
    """
    from mbtool.codec.data_access import WriteMultipleRegisters
    from mbtool.codec.values import decode_values
    from mbtool.render import Result

    registers = parse_registers(values, value_type, order)
    request = WriteMultipleRegisters(address, tuple(registers))
    execute(connection, request)
    # Report the values as the device now holds them, read back through the same type.
    typed = decode_values(tuple(registers), value_type, order.upper())
    items = [(address + offset, value) for offset, value in typed]
    show(connection, Result(connection.unit, request.function_code, request.name, address, items, value_type,
                            registers))


# --- the one way out ---------------------------------------------------------------------


def _terminate(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> None:
    """Run the CLI; every outcome leaves through one exit code and at most one stderr line."""
    signal.signal(signal.SIGTERM, _terminate)
    try:
        cli.main(args=argv, prog_name="mbtool", standalone_mode=False)
        code = ExitCode.OK
    except click.exceptions.Exit as done:  # --help, --version
        code = done.exit_code
    except click.ClickException as error:  # usage errors: nothing was sent
        hint = ""
        if error.ctx is not None and isinstance(error, click.UsageError):
            hint = f" (see '{error.ctx.command_path} --help')"
        click.echo(f"mbtool: {error.format_message()}{hint}", err=True)
        code = ExitCode.USAGE
    except (KeyboardInterrupt, click.exceptions.Abort):
        click.echo("mbtool: interrupted", err=True)
        code = ExitCode.INTERRUPTED
    except BrokenPipeError:
        # The reader went away (| head): not an error of ours.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        code = ExitCode.OK
    except MbtoolError as error:
        click.echo(f"mbtool: {error}", err=True)
        code = error.exit_code
    except Exception as error:  # a bug: say so in one line; MBTOOL_DEBUG=1 shows the traceback
        if os.environ.get("MBTOOL_DEBUG"):
            raise
        click.echo(f"mbtool: internal error: {type(error).__name__}: {error} (set MBTOOL_DEBUG=1 for details)",
                   err=True)
        code = exit_code_for(error)
    sys.exit(int(code))
