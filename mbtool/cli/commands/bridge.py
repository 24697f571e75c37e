"""``mbtool bridge``: a gateway between Modbus TCP and a serial line, showing its traffic.

Its two halves exist already (design notes: a gateway is ``link`` + ``device`` joined in
``cli``): ``mbtool.device.server`` takes the requests, from TCP clients or as a slave on a
serial line, and ``mbtool.link.forward`` sends each on as a master and turns what comes back
(or does not) into the reply.  Here they are joined, and every transaction is shown.
"""

from __future__ import annotations

import queue
import sys
import threading

import click

from mbtool.cli.completion import complete_port
from mbtool.cli.frames import one_line, shown_frame
from mbtool.cli.listen import check_udp_rate, datagrams_dropped, tls_server_settings
from mbtool.cli.options import (
    LINK_OPTIONS,
    TLS_OPTIONS,
    WRITE_ROLES_OPTION,
    output_chosen,
    serial_line_options,
    tcp_client_options,
    with_options,
)
from mbtool.cli.param_types import Choice, Seconds, parse_units, units_text
from mbtool.cli.parsing import QuickHelp
from mbtool.cli.session import warn_insecure
from mbtool.cli.sinks import LOG, formats, sink
from mbtool.cli.stamps import local_time
from mbtool.codec.describe import describe
from mbtool.codec.errors import function_code_text
from mbtool.codec.framing import make_framer
from mbtool.device.server import Server, parse_target
from mbtool.errors import UsageError
from mbtool.link import IN_PROCESS
from mbtool.link.connection import check, connection_of, open_client
from mbtool.link.connection import rs485_delays as rs485_delays_of
from mbtool.link.forward import BROADCAST, INVALID, NO_PATH, NO_RESPONSE, OUTCOMES, REFUSED, REPLY, Forwarder
from mbtool.link.settings import RS485_DRIVES, SETTINGS, check_data_bits, not_for_tls
from mbtool.link.transport import MBAP_SCHEMES, SerialSettings, default_framer, is_network
from mbtool.words import counted

DEFAULT_LISTEN = "tcp://127.0.0.1:5020"
EVERY_UNIT = "1-247"  # the addresses a serial line's slaves may have (spec §2)
PRINTER_STOP = 5.0  # seconds a stop waits for the transactions still to be printed
# Lines (transactions and the server's events) waiting for a display that falls behind: past
# it they are dropped and counted, so the bus never waits for stdout nor memory grows.
DISPLAY_BACKLOG = 1000


class BridgeCommand(QuickHelp, click.Command):
    pass


@click.command(
    "bridge",
    cls=BridgeCommand,
    context_settings={"help_option_names": ["-h", "--help"]},
    short_help="A Modbus TCP <-> RTU/ASCII gateway that shows its traffic.",
)
@click.option(
    "--listen",
    metavar="WHERE",
    default=DEFAULT_LISTEN,
    shell_complete=complete_port,
    show_default=True,
    help="Where requests come from: tcp://HOST:PORT (Modbus TCP clients; PORT 0 picks a free "
    "one), tls://HOST:PORT (Modbus/TCP Security: --cert, --key, --ca), udp://HOST:PORT or "
    "rtu+udp://HOST:PORT (datagrams), or a serial device or pyserial URL (mbtool is then a "
    "slave on that line). Only loopback by default: tcp://0.0.0.0:502 opens the bus to the "
    "network, a choice you type.",
)
@click.option(
    "-p",
    "--port",
    "target",
    metavar="TARGET",
    required=True,
    shell_complete=complete_port,
    help="Where requests go: a serial device or pyserial URL (the bus), tcp://HOST[:PORT] "
    "(a Modbus TCP device), tls://HOST[:PORT], udp://HOST[:PORT], rtu+udp://HOST:PORT, or "
    "sim:// (the built-in device).",
)
@click.option(
    "--framer",
    type=Choice(["rtu", "ascii"]),
    help="The serial side's framing (default rtu); tcp://, tls:// and udp:// always speak Modbus TCP (MBAP).",
)
@click.option(
    "--units",
    metavar="UNITS",
    default=EVERY_UNIT,
    show_default=True,
    help="Units forwarded: 1,17 or 1-10 or both. From TCP a request for another unit gets "
    "exception 0A; on a serial line it is left to the other slaves. Unit 0 is a broadcast "
    "where a serial line is either side: forwarded only if listed (0-247), only writes, "
    "never answered.",
)
@click.option(
    "--raw-functions",
    is_flag=True,
    help="Forward function codes mbtool does not know (01-7F, and FC 43 (0x2B) MEI types other than "
    "0E) as they come; without it they are answered exception 01. Known ones are always "
    "checked: a request that does not fit its layout is answered 01 or 03, never forwarded.",
)
@click.option(
    "--silent-hold",
    type=Seconds(),
    default=5.0,
    show_default=True,
    help="After a unit sends nothing within the timeout, answer its requests exception 0B at "
    "once, without the bus, for SECONDS: a client asking again and again for a unit that is "
    "not there does not cost the others its timeout. 0: try the bus every time.",
)
@serial_line_options
@with_options(LINK_OPTIONS)
@with_options(TLS_OPTIONS)
@WRITE_ROLES_OPTION
@tcp_client_options
@click.option(
    "--hex",
    "hex_trace",
    is_flag=True,
    help="Show each transaction's frames in hex, both sides, checksums checked.",
)
@click.option(
    "-o",
    "--format",
    "output_format",
    type=Choice(formats(LOG)),
    callback=output_chosen,
    help="How transactions are shown: table on a terminal, plain in a pipe, json one object a "
    "transaction. A display 1000 lines behind drops lines (and says how many) rather than hold up the bus.",
)
@click.option(
    "-q", "--quiet", is_flag=True, help="Show no transactions; only the start line and the summary."
)
def bridge(
    listen,
    target,
    framer,
    units,
    raw_functions,
    silent_hold,
    baud,
    parity,
    bytesize,
    stopbits,
    timeout,
    retries,
    echo,
    pause,
    connect_delay,
    lenient,
    rs485,
    rs485_delays,
    cert,
    key,
    ca,
    insecure,
    server_name,
    write_roles,
    max_clients,
    idle_timeout,
    first_request_timeout,
    udp_rate,
    hex_trace,
    output_format,
    quiet,
):
    """A gateway: Modbus TCP clients to a serial bus (RTU or ASCII), or a serial line's master
    to a Modbus TCP device, one transaction at a time, each shown as it passes.

    Requests are forwarded as they come, with the serial line's silences; replies go back
    with the client's transaction id. The gateway answers for the device only where the
    spec says a gateway does: exception 0B when the device does not answer (or its reply is
    garbled), 0A when the unit is not forwarded or the link cannot be used (it is opened
    again for the next request). A request no device could take (one that does not fit
    its function code's layout, a read broadcast) never reaches the bus: the bridge answers
    it 01 or 03 as the device would. TCP clients take turns, the one that has used the
    least bus time lately first, and the requests of a client that has gone are dropped:
    none can hold up the others.
    The start line and a summary on exit go to stderr, with a line for each unit: its
    transactions on the link by outcome (answered, exception, timeout, corrupt, not ours,
    link lost) and their round-trip time. Ctrl-C or SIGTERM stops it with exit status 0.

    \b
    Try it:
      mbtool bridge -p /dev/ttyUSB0 -b 9600 --parity N
      mbtool read-holding-registers 0 10 -p tcp://127.0.0.1:5020
    The reverse, mbtool as a slave on a serial line in front of a TCP device:
      mbtool bridge --listen /dev/ttyUSB1 -p tcp://192.0.2.10
    """
    if quiet and (output_format or hex_trace):
        shown = " and ".join(name for name, given in (("-o", output_format), ("--hex", hex_trace)) if given)
        raise UsageError(f"-q shows no transaction: {shown} would have nothing to show")
    where = parse_target(listen)
    forwarded = parse_units(units, broadcast=True)
    serial_framer = framer or "rtu"
    listening_framer = "tcp" if where.scheme in MBAP_SCHEMES else serial_framer
    link_framer = "tcp" if default_framer(target) == "tcp" else serial_framer
    if framer and "tcp" == listening_framer == link_framer:
        raise UsageError("--framer sets the serial side's framing, and both sides are tcp://")
    if where.scheme == "serial" and where.path == target:
        raise UsageError(f"--listen and -p are both {target}: a bridge joins two links")
    check_data_bits(bytesize, (listening_framer, link_framer))
    # --rs485 drives the RTS line of the serial side, whichever side that is.
    direction = rs485_delays_of(rs485, rs485_delays)
    link_serial = (
        link_framer != "tcp"
        and not target.startswith(tuple(f"{s}://" for s in IN_PROCESS))
        and not is_network(target)
    )
    if direction and where.scheme != "serial" and not link_serial:
        raise UsageError(f"{RS485_DRIVES}, and neither side is one")
    # --cert, --key and --ca are the bridge's one identity: the server's on a tls:// --listen,
    # the client's towards a tls:// -p, both where both are.
    link_tls = target.lower().startswith("tls://")
    if where.scheme != "tls" and not link_tls:
        given = [SETTINGS[name].option for name, value in (("cert", cert), ("key", key), ("ca", ca)) if value]
        if given:
            raise not_for_tls(given[0], "tls://", ", and neither side is tls://")
    listening: tuple[str | None, str | None, str | None] = (
        (cert, key, ca) if where.scheme == "tls" else (None, None, None)
    )
    context, roles = tls_server_settings(where, listening_framer, *listening, write_roles)
    check_udp_rate(where, udp_rate)
    connection = connection_of(
        port=target,
        unit=1,
        framer=link_framer,
        baud=baud,
        parity=parity,
        bytesize=bytesize,
        stopbits=stopbits,
        timeout=timeout,
        retries=retries,
        echo=echo,
        pause=pause,
        connect_delay=connect_delay,
        lenient=lenient,
        rs485_delays=direction if link_serial else None,
        cert=cert if link_tls else None,
        key=key if link_tls else None,
        ca=ca if link_tls else None,
        insecure=insecure,
        server_name=server_name,
    )
    check(connection)
    warn_insecure(connection)
    fmt = output_format or ("table" if sys.stdout.isatty() else "plain")
    show = Show(fmt, hex_trace, quiet)
    forwarder = Forwarder(
        lambda: open_client(connection), link_framer, forwarded, show.passage, raw_functions, silent_hold
    )
    forwarder.open()  # a link that cannot be opened now is a mistake to hear of at once (exit 6)
    server = Server(
        None,
        where,
        listening_framer,
        answerer=forwarder,
        queued=True,
        settings=SerialSettings(baud, parity, bytesize, stopbits, direction),
        log=show.event,
        max_clients=max_clients,
        idle_timeout=idle_timeout,
        first_request_timeout=first_request_timeout,
        tls_context=context,
        write_roles=roles,
        udp_rate=udp_rate,
    )
    show.on_failure = server.stop
    try:
        server.open()
        # The stop by signal is in place before the line that says the bridge is ready (as serve).
        with server.stopped_by_signals():
            click.echo(
                f"bridging {server.stats.listening} ({listening_framer}) to {target} ({link_framer}), "
                f"units {units_text(forwarded)}",
                err=True,
            )
            server.run()
    finally:
        forwarder.close()
        show.close()
    if show.failure is not None:
        raise show.failure  # cli.main: a reader gone (exit 141), or the output failed (exit 7)
    connections = server.stats.connections if where.scheme in ("tcp", "tls") else None
    summary = "; ".join(
        [show.summary(connections, listening_framer == "tcp"), *datagrams_dropped(server.stats)]
    )
    click.echo(f"stopped: {summary}", err=True)
    for unit, stats in sorted(forwarder.stats.items()):  # what became of each unit's transactions
        click.echo(f"unit {unit}: {stats}", err=True)


class Show:
    """Each transaction as it passes, and the tally for the summary.

    The bus worker only hands a transaction over: a printer thread decodes and prints it, so
    a reply never waits for its own display, nor the bus for a slow terminal or pipe.  A
    display that falls DISPLAY_BACKLOG lines behind (a pipe nobody reads) loses the lines past
    it, and says how many where it catches up.
    """

    def __init__(self, fmt: str, hex_trace: bool, quiet: bool) -> None:
        self.hex = hex_trace
        self.quiet = quiet
        self.on_failure = lambda: None  # called (by the printer) when the output cannot be written
        self.counts = dict.fromkeys(OUTCOMES, 0)
        self.timed = 0  # transactions with a bus time, their sum and the longest
        self.bus_total = 0.0
        self.bus_longest = 0.0
        # The format's sink writes each line (its Log); this Show gives each format's view of one.
        self.log = None if quiet else sink(fmt).Log(sys.stdout, self, highlight=False, soft_wrap=True)
        self.failure: OSError | None = None
        self.not_shown = 0  # lines dropped because the display fell behind
        self._dropped = 0  # of those, the ones the display has not been told of yet
        self._queueing = threading.Lock()  # the bus worker and the server's loop both queue
        self._lines: queue.SimpleQueue = queue.SimpleQueue()
        self._printer = threading.Thread(target=self._print, name="mbtool-show", daemon=True)
        self._printer.start()

    def passage(self, passage) -> None:
        """A transaction has ended (called by whoever answered it)."""
        self.counts[passage.outcome] += 1
        if passage.bus_time is not None:
            self.timed += 1
            self.bus_total += passage.bus_time
            self.bus_longest = max(self.bus_longest, passage.bus_time)
        if not self.quiet:
            self._show(passage)

    def event(self, direction: str, peer: str, data: bytes, note: str) -> None:
        """The server's own events: clients connecting, closed, refused."""
        if self.quiet:
            return
        assert self.log is not None  # made unless quiet
        if not self.log.events or direction not in ("open", "close", "refuse"):
            return
        self._show(f"{local_time()} {peer} {note}")

    def _show(self, item) -> None:
        """Queue a line for the printer, never waiting: past DISPLAY_BACKLOG it is dropped."""
        with self._queueing:
            if self._lines.qsize() >= DISPLAY_BACKLOG:
                self._dropped += 1
                self.not_shown += 1
                return
            self._tell_dropped()
            self._lines.put(item)

    def _tell_dropped(self) -> None:
        """The count of the lines dropped since the last, in their place among the others."""
        if self._dropped:
            self._lines.put(self._dropped)
            self._dropped = 0

    def close(self) -> None:
        """Print what is still queued (a few seconds at most), then stop the printer."""
        with self._queueing:
            self._tell_dropped()
        self._lines.put(None)
        self._printer.join(PRINTER_STOP)

    def _next(self):
        """The next line to print; once every line queued is out, the count of those dropped
        since: the display says it where it catches up, not with the next transaction, which
        may be minutes away, nor only at the end."""
        if self._dropped and self._lines.empty():
            with self._queueing:
                self._tell_dropped()
        return self._lines.get()

    def _print(self) -> None:
        while (item := self._next()) is not None:
            if self.failure is not None:
                continue  # the reader has gone: the bridge is stopping
            try:
                self._write(item)
            except OSError as error:  # a closed pipe, a full disk: the bridge stops, main says why
                self.failure = error
                self.on_failure()

    def _write(self, item) -> None:
        assert self.log is not None  # made unless quiet, and nothing is queued when quiet
        self.log.write(item)
        sys.stdout.flush()

    # Each format's view of a line to show: lines dropped (a count), a server event (a str), a
    # transaction (a passage).
    WHY_DROPPED = "the display fell behind"

    def data(self, item) -> dict | None:
        if isinstance(item, int):
            return {"time": local_time(), "not_shown": item, "why": self.WHY_DROPPED}
        if isinstance(item, str):
            return None  # a server event: JSON's lines are transactions
        return passage_record(item)

    def styled(self, item) -> list[tuple[str, str]]:
        if isinstance(item, int):
            return [("bold red", f"{local_time()} {item} not shown: {self.WHY_DROPPED}")]
        if isinstance(item, str):
            return [("dim", item)]
        return hex_lines(item) if self.hex else decoded_lines(item)

    def lines(self, item) -> list[str]:
        return [line for _, line in self.styled(item)]

    def draw(self, item, console) -> None:
        for style, line in self.styled(item):
            console.print(line, style=style, markup=False, emoji=False)

    def summary(self, connections: int | None, tcp: bool) -> str:
        """The tally; ``connections``: a TCP or TLS server's (None: no connections to count),
        ``tcp``: its clients speak MBAP, and are told 0A (a serial line's slaves are not)."""
        counts = self.counts
        parts = [
            counted(counts[REPLY], "reply", "replies"),
            f"{counted(counts[REFUSED], 'exception')} from devices",
            f"{counts[NO_RESPONSE]} unanswered (0B)",
            f"{counts[NO_PATH]} {'refused (0A)' if tcp else 'not forwarded or refused (0A)'}",
            counted(counts[BROADCAST], "broadcast"),
            f"{counts[INVALID]} invalid (01, 03)",
        ]
        text = f"{counted(sum(counts.values()), 'transaction')}: " + ", ".join(parts)
        if connections is not None:
            text += f"; {counted(connections, 'connection')}"
        if self.timed:
            text += (
                f"; bus time mean {self.bus_total / self.timed * 1000:.1f} ms, "
                f"max {self.bus_longest * 1000:.1f} ms"
            )
        if self.not_shown:
            text += f"; {self.not_shown} not shown (the display fell behind)"
        return text


# Line styles on a terminal: the request, and its reply by what became of it.
ASKED = "cyan"
STYLES = {
    REPLY: "green",
    REFUSED: "yellow",
    BROADCAST: "green",
    NO_RESPONSE: "bold red",
    NO_PATH: "bold red",
    INVALID: "bold red",
}


def _describe(adu: bytes, framing: str, direction: str, previous=None):
    return describe(shown_frame(adu) if framing == "ascii" else adu.hex(), framing, direction, previous)


def decoded_lines(passage) -> list[tuple[str, str]]:
    """The request and what became of it, decoded as monitor prints frames: (style, line)."""
    request = _describe(passage.request, passage.upstream, "request")
    head = f"{local_time(passage.time)} {passage.peer}"
    fc = function_code_text(passage.function & 0x7F)
    lines = [(ASKED, f"{head} > unit {passage.unit} {fc} {one_line(request)}")]
    head = f"{local_time(passage.time + passage.total)} {passage.peer}"  # when it ended
    if passage.reply:
        reply = _describe(passage.reply, passage.upstream, "response", request)
        text = f"{head} < unit {passage.unit} {function_code_text(reply.function & 0x7F)} {one_line(reply)}"
    else:
        text = f"{head} - {_unanswered(passage)}"
    lines.append((STYLES[passage.outcome], text + _after(passage)))
    return lines


def hex_lines(passage) -> list[tuple[str, str]]:
    """Every frame of the transaction in hex, both sides, checksums checked: (style, line)."""
    head = local_time(passage.time)
    lines = [(ASKED, f"{head} {passage.peer} RX {_wire(passage.request, passage.upstream)}")]
    if passage.sent:
        lines.append((ASKED, f"{head} link TX {_wire(passage.sent, passage.downstream)}"))
    if passage.received:
        lines.append((ASKED, f"{head} link RX {_wire(passage.received, passage.downstream)}"))
    head = local_time(passage.time + passage.total)  # when it ended
    if passage.reply:
        text = f"{head} {passage.peer} TX {_wire(passage.reply, passage.upstream)}"
    else:
        text = f"{head} {passage.peer} -- {_unanswered(passage)}"
    lines.append((STYLES[passage.outcome], text + _after(passage)))
    return lines


def _unanswered(passage) -> str:
    return "broadcast" if passage.outcome == BROADCAST else "no reply"


def _after(passage) -> str:
    """What ends a transaction's last line: its times, and what the gateway saw."""
    bus = "" if passage.bus_time is None else f"bus {passage.bus_time * 1000:.1f} ms, "
    text = f" | {bus}total {passage.total * 1000:.1f} ms"
    return text + f" | {passage.why}" if passage.why and passage.outcome != REFUSED else text


def _wire(adu: bytes, framing: str) -> str:
    return f"{shown_frame(adu)}  {make_framer(framing).check(adu)}"


def passage_record(passage) -> dict:
    """One JSON object a transaction."""
    request = _describe(passage.request, passage.upstream, "request")
    reply = _describe(passage.reply, passage.upstream, "response", request) if passage.reply else None
    return {
        "time": local_time(passage.time),
        "client": passage.peer,
        "unit": passage.unit,
        "function": passage.function,
        "name": request.name,
        "outcome": passage.outcome,
        "why": passage.why or None,
        "bus_ms": None if passage.bus_time is None else round(passage.bus_time * 1000, 2),
        "total_ms": round(passage.total * 1000, 2),
        "request": {"frame": shown_frame(passage.request), "summary": one_line(request)},
        "forwarded": shown_frame(passage.sent) if passage.sent else None,
        "received": shown_frame(passage.received) if passage.received else None,
        "reply": None if reply is None else {"frame": shown_frame(passage.reply), "summary": one_line(reply)},
    }
