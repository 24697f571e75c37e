"""``mbtool serve``: a Modbus device simulator on TCP or a serial line, for testing masters.

Its -p and -u differ from the other commands' (a place to listen on, a set of
unit ids to answer for), so it defines its own options here; the number and
choice types are the shared ones.
"""

from __future__ import annotations

import functools
import sys
import time

import click

from mbtool.cli.completion import complete_port
from mbtool.cli.listen import DATAGRAM_SCHEMES, check_udp_rate, datagrams_dropped, tls_server_settings
from mbtool.cli.options import serial_line_options, serve_tls_options, tcp_client_options
from mbtool.cli.param_types import Choice, FilePath, Number, PositiveFloat, parse_int, parse_units, units_text
from mbtool.cli.parsing import QuickHelp
from mbtool.cli.sinks.table import serve_live
from mbtool.device.datafile import load_data
from mbtool.device.device import Device, Faults
from mbtool.device.model import demo_model
from mbtool.device.server import Server, parse_target
from mbtool.device.serving import IoFaults
from mbtool.errors import UsageError
from mbtool.link.settings import check_data_bits
from mbtool.link.transport import SerialSettings, default_framer
from mbtool.words import counted

DEFAULT_TARGET = "tcp://127.0.0.1:5020"


class ServeCommand(QuickHelp, click.Command):
    pass


def parse_exception(text: str) -> tuple[int, int]:
    function, colon, code = text.partition(":")
    if not colon:
        raise UsageError(f"--exception {text}: expected FC:CODE, e.g. 3:2 or 0x10:0x06")
    fc = parse_int(function, "function code")
    ex = parse_int(code, "exception code")
    if not 1 <= fc <= 0x7F:
        raise UsageError(f"function code {function} is out of range 1..127")
    if not 1 <= ex <= 0xFF:
        raise UsageError(f"exception code {ex} is out of range 1..255")
    return fc, ex


class Fraction(click.ParamType):
    name = "fraction"

    def convert(self, value, param, ctx):
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value} is not a number between 0 and 1", param, ctx)
        if not 0 <= number <= 1:
            self.fail(f"{value} is not between 0 and 1", param, ctx)
        return number


@click.command(
    "serve",
    cls=ServeCommand,
    context_settings={"help_option_names": ["-h", "--help"]},
    short_help="Simulate a device (slave) for testing masters.",
)
@click.option(
    "-p",
    "--port",
    "target",
    metavar="TARGET",
    default=DEFAULT_TARGET,
    shell_complete=complete_port,
    show_default=True,
    help="Where to listen: tcp://HOST:PORT (PORT 0 picks a free one), tls://HOST:PORT "
    "(Modbus/TCP Security: --cert, --key and --ca), udp://HOST:PORT (MBAP in datagrams), "
    "rtu+udp://HOST:PORT (RTU frames in datagrams), or a serial device or "
    "pyserial URL. Only loopback by default: binding another address (tcp://0.0.0.0:502) "
    "exposes the device to the network and is a choice you type.",
)
@click.option(
    "-u",
    "--unit",
    "units",
    metavar="UNITS",
    default="1",
    show_default=True,
    help="Unit ids to answer for: 1,17 or 1-10 or both. Frames for other ids are ignored, "
    "like a slave on a shared bus. With rtu or ascii framing unit 0 (broadcast) writes reach every "
    "unit and are never answered; on Modbus TCP units 0 and 255 address the device itself, "
    "answered as the lowest unit.",
)
@click.option(
    "--framer",
    type=Choice(["rtu", "ascii", "tcp"]),
    help="Framing: tcp (MBAP) for tcp://, tls:// and udp:// targets, rtu otherwise; rtu or ascii "
    "on tcp:// or udp:// serves like a serial device server.",
)
@serial_line_options
@click.option(
    "--data",
    "data_file",
    metavar="FILE",
    type=FilePath(dir_okay=False),
    help="Initial tables and device identity from a JSON or TOML file (see README); with "
    "sparse = true in it, addresses it does not list answer exception 02. "
    "Without it the device starts with the sim:// demo data.",
)
@click.option(
    "--read-only",
    is_flag=True,
    help="Answer every function that writes data (05, 06, 15, 16, 21, 22, 23) with exception 01, "
    "and every FC 08 sub-function that changes the device's state (01, 03, 04, 0A, 14; 15 with 0004).",
)
@click.option("--delay", type=PositiveFloat(), help="Fault: wait SECONDS before every reply.")
@click.option(
    "--drop", type=Fraction(), default=0.0, help="Fault: never send this fraction of replies (0..1)."
)
@click.option(
    "--corrupt",
    type=Fraction(),
    default=0.0,
    help="Fault: send this fraction of replies with a wrong CRC/LRC (rtu and ascii framing).",
)
@click.option(
    "--exception",
    "exceptions",
    metavar="FC:CODE",
    multiple=True,
    help="Fault: answer function FC with exception CODE, e.g. 3:2 (repeatable).",
)
@click.option(
    "--min-gap",
    type=PositiveFloat(),
    help="Fault (TCP): drop a request that comes less than SECONDS after the reply before it, "
    "as slow devices and gateways do (mbtool's --pause is the cure).",
)
@click.option(
    "--settle",
    type=PositiveFloat(),
    help="Fault (TCP): drop requests for SECONDS after a connection is accepted "
    "(mbtool's --connect-delay is the cure).",
)
@click.option(
    "--connection-requests",
    type=Number(1, 10**9, "requests"),
    help="Fault (TCP): answer only the first N requests of each connection, as a gateway that "
    "leaks connections does (mbtool's --reconnect-each is the cure).",
)
@click.option(
    "--pad", type=Number(1, 200, "bytes"), help="Fault (tcp framing): N zero bytes after every reply's PDU."
)
@click.option(
    "--byte-count-off",
    type=Number(1, 255, "bytes"),
    help="Fault (tcp framing): add N to the byte count of FC 01-04 replies; the data stays whole.",
)
@click.option(
    "--reply-unit",
    type=Number(0, 255, "unit"),
    help="Fault (tcp framing): every reply carries this unit id, as a confused gateway sends.",
)
@click.option(
    "--busy",
    type=PositiveFloat(),
    help="Fault: answer every request with exception 06 "
    "(server device busy) for the first SECONDS after start.",
)
@tcp_client_options
@serve_tls_options
@click.option("--seed", type=Number(0, 2**32 - 1, "seed"), help="Random seed for --drop and --corrupt.")
@click.option("-q", "--quiet", is_flag=True, help="Print only the line saying where it serves (for scripts).")
def serve(
    target,
    units,
    framer,
    baud,
    parity,
    bytesize,
    stopbits,
    data_file,
    read_only,
    delay,
    drop,
    corrupt,
    exceptions,
    min_gap,
    settle,
    connection_requests,
    pad,
    byte_count_off,
    reply_unit,
    busy,
    max_clients,
    idle_timeout,
    first_request_timeout,
    udp_rate,
    cert,
    key,
    ca,
    write_roles,
    seed,
    quiet,
):
    """Simulate a Modbus device (slave) for testing masters: every function code of the spec.

    On a terminal a live view shows requests, counters and the last frames; in a
    pipe every frame is logged on stdout; with -q only the first line ("serving
    ...") is printed. Ctrl-C or SIGTERM stops it cleanly with exit status 0.

    What a master (or --data) can make it hold is bounded: each unit has 65536 of each
    table, shared with the other units until written, and at most 16 files (FC 20/21) of
    10000 records, so a write to another file answers exception 02; a client's unsent
    replies, those --delay holds back included, are capped at 64 KB.

    \b
    Try it:
      mbtool serve                                   (in one terminal)
      mbtool read-holding-registers 0 10 -p tcp://127.0.0.1:5020
    """
    unit_set = parse_units(units)
    where = parse_target(target)
    framer = framer or default_framer(target)
    if where.scheme in ("serial", "rtu+udp") and framer == "tcp":
        raise UsageError(
            f"--framer tcp (MBAP) needs a tcp://, tls:// or udp:// target; {where} takes rtu or ascii"
        )
    check_data_bits(bytesize, (framer,))
    if (min_gap or settle or connection_requests) and where.scheme not in ("tcp", "tls"):
        raise UsageError(
            "--min-gap, --settle and --connection-requests are faults of TCP clients: serve on tcp://HOST:PORT"
        )
    context, roles = tls_server_settings(where, framer, cert, key, ca, write_roles, data_file)
    check_udp_rate(where, udp_rate)
    if (pad or byte_count_off or reply_unit is not None) and framer != "tcp":
        raise UsageError("--pad, --byte-count-off and --reply-unit bend Modbus TCP replies: use tcp framing")
    if seed is not None and not (drop or corrupt):
        raise UsageError("--seed picks which replies --drop and --corrupt spoil: give one of them")
    if corrupt and framer == "tcp":
        raise UsageError("--corrupt needs rtu or ascii framing: MBAP carries no CRC/LRC")
    injected = dict(parse_exception(text) for text in exceptions)
    if data_file:
        model, unit_models = load_data(data_file, unit_set)
    else:
        model, unit_models = demo_model(), {}
    device = Device(model, unit_set, unit_models)
    device.faults = Faults(injected or None, time.monotonic() + busy if busy else 0.0)
    device.read_only = read_only
    settings = SerialSettings(baud, parity, bytesize, stopbits)
    mode = "quiet" if quiet else ("live" if sys.stdout.isatty() else "log")
    log = functools.partial(_log_line, framer) if mode == "log" else None
    server = Server(
        device,
        where,
        framer,
        faults=IoFaults(
            delay or 0.0,
            drop,
            corrupt,
            min_gap or 0.0,
            settle or 0.0,
            connection_requests or 0,
            pad or 0,
            byte_count_off or 0,
            reply_unit,
        ),
        seed=seed,
        settings=settings,
        log=log,
        max_clients=max_clients,
        idle_timeout=idle_timeout,
        first_request_timeout=first_request_timeout,
        tls_context=context,
        write_roles=roles,
        udp_rate=udp_rate,
    )
    server.open()
    unit_text = units_text(unit_set)
    refusal = " read-only: writes get exception 01" if read_only else ""
    if roles is not None:
        refusal += f" writes by role {','.join(sorted(roles))} only" if roles else " no role may write"
    # The stop by signal is in place before the line that says the server is ready: a
    # supervisor may stop it as soon as it reads that line, and that is a clean stop (exit 0).
    with server.stopped_by_signals():
        click.echo(f"serving {server.stats.listening} units {unit_text} framer {framer}{refusal}")
        sys.stdout.flush()
        if mode == "live":
            serve_live(server, device, framer, unit_text, unit_set, _shown)
        else:
            server.run()
    if mode != "quiet":
        stats = server.stats
        turned_away = "".join(
            f", {count} {what}"
            for count, what in (
                (stats.refused, "refused (--max-clients)"),
                (stats.evicted, "gave their slot to a newcomer (--max-clients)"),
                (stats.expired, "timed out (--idle-timeout)"),
                (stats.unused, "sent no request (--first-request-timeout)"),
            )
            if count
        )
        peer = "peer" if where.scheme in DATAGRAM_SCHEMES else "connection"
        click.echo(
            f"stopped: {counted(stats.requests, 'request')}, {counted(stats.replies, 'reply', 'replies')}, "
            f"{counted(stats.connections, peer)}"
            + turned_away
            + "".join(f", {part}" for part in datagrams_dropped(stats))
        )


def _shown(data: bytes, framer: str) -> str:
    """A frame as the trace shows it: hex pairs, or the characters of an ASCII frame when
    they are all printable (a peer's escape sequences never reach the terminal)."""
    if framer == "ascii" and data.isascii():
        text = data.decode("ascii").replace("\r", "\\r").replace("\n", "\\n")
        if text.isprintable():
            return text
    return data.hex(" ").upper()


def _log_line(framer: str, direction: str, peer: str, data: bytes, note: str) -> None:
    stamp = time.strftime("%H:%M:%S")
    text = " ".join(part for part in (stamp, peer, direction, _shown(data, framer), note) if part)
    click.echo(text)
    sys.stdout.flush()
