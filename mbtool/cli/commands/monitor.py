"""monitor: a passive bus monitor on a serial line; it never transmits (spec §2).

The splitting, pairing and flagging are sans-IO in mbtool.monitor.bus; this module owns
the port, the clock and the output.  The port is opened read-only in spirit: nothing
is ever written to it, and RTS is dropped at once, since an RS-485 adapter that
switches direction by RTS would otherwise drive the bus and silence it.

The summary leaves as one ``mbtool:`` line through cli.main, like polling's: exit 0
when stopped by --duration, --frames, the end of --from-file, or Ctrl-C/SIGTERM after
frames were seen; 130 only when interrupted before any frame (as polling does before
any poll).  Checksum errors and exceptions on the bus are observations, counted in the
summary, not failures of the monitor.
"""

from __future__ import annotations

import sys
import time
from typing import NamedTuple

import click

from mbtool.cli.frames import frame_report, one_line
from mbtool.cli.options import PROFILE_OPTION, output_chosen, serial_line_options
from mbtool.cli.param_types import Choice, FilePath, Number, PositiveFloat
from mbtool.cli.parsing import QuickHelp
from mbtool.cli.profiles import defaults
from mbtool.cli.sinks import LOG, default_format, formats, sink
from mbtool.cli.sinks.table import escape
from mbtool.cli.stamps import local_time
from mbtool.codec.errors import function_code_text
from mbtool.codec.timing import char_time, character_bits, silent_interval
from mbtool.errors import ConnectionFailed, ExitCode, NoResponse, UsageError, Verdict
from mbtool.link.transport import SerialSettings, SerialTransport
from mbtool.monitor.bus import BusFrame, BusMonitor, Tally, Unanswered
from mbtool.monitor.pcap import BusCapture, is_pcap, packets
from mbtool.monitor.stats import BusStats

TICK = 0.05  # longest wait for bytes before the clock (silence, timeouts, --duration) is looked at
# On a UART t3.5 ends a frame (spec §2), but ptys and USB adapters deliver one frame in
# bursts with pauses of several ms (an FTDI chip's latency timer is 16 ms by default), so a
# shorter pause must not cut a frame.  A frame of known length never waits for the pause.
MIN_RTU_SILENCE = 0.02
ASCII_SILENCE = 1.0  # spec §2: up to 1 s may pass between the characters of an ASCII frame


class MonitorCommand(QuickHelp, click.Command):
    """Listens; sends nothing."""


def default_silence(framer: str, baud: int) -> float:
    return ASCII_SILENCE if framer == "ascii" else max(silent_interval(baud), MIN_RTU_SILENCE)


@click.command(
    "monitor",
    cls=MonitorCommand,
    context_settings={"help_option_names": ["-h", "--help"]},
    short_help="Watch a bus and decode every frame; never sends.",
)
@click.option(
    "-p",
    "--port",
    envvar="MBTOOL_PORT",
    metavar="TARGET",
    show_envvar=True,
    help="The serial line to listen on: a serial device, socket://HOST:PORT or rfc2217://HOST:PORT.",
)
@click.option(
    "--framer",
    type=Choice(["rtu", "ascii"]),
    default="rtu",
    show_default=True,
    help="Framing on the line.",
)
@serial_line_options
@click.option(
    "--silence",
    type=PositiveFloat(),
    help="Seconds without a byte that end a frame whose length is not known "
    "(default: t3.5 at --baud, at least 0.02 for USB adapters; 1 for ascii).",
)
@click.option(
    "--response-timeout",
    type=PositiveFloat(),
    default=1.0,
    show_default=True,
    help="Seconds after which a request counts as unanswered.",
)
@click.option("--duration", type=PositiveFloat(), help="Stop after this many seconds.")
@click.option("--frames", "frame_limit", type=Number(1, 2**31, "frames"), help="Stop after N frames.")
@click.option(
    "--capture",
    metavar="FILE",
    type=FilePath(dir_okay=False),
    help="Also write every frame to a pcap file that Wireshark decodes as Modbus RTU.",
)
@click.option(
    "--from-file",
    metavar="FILE",
    type=FilePath(exists=True, dir_okay=False),
    help="Analyse a recording instead of listening: a pcap file (as --capture writes), with its "
    "time stamps, or raw bytes from a line, with no timing (frames split by their implicit length; "
    "no time, gap or latency shown).",
)
@click.option(
    "-o",
    "--format",
    "output_format",
    type=Choice(formats(LOG)),
    callback=output_chosen,
    help="Output: coloured lines on a terminal (table), plain lines in a pipe, json one object a line.",
)
@click.option(
    "--stats",
    is_flag=True,
    help="Show statistics instead of each frame: per unit its requests, replies, exceptions by "
    "code, unanswered requests, corrupt frames, response time min/avg/p95/max and frames that "
    "broke the t3.5 silence, and the bus's utilisation; on exit (a table, or -o json).",
)
@click.option(
    "--stats-interval",
    type=PositiveFloat(),
    metavar="SECONDS",
    help="With --stats: also every SECONDS while listening, each time all since the start.",
)
@PROFILE_OPTION
def monitor(
    port,
    framer,
    baud,
    parity,
    bytesize,
    stopbits,
    silence,
    response_timeout,
    duration,
    frame_limit,
    capture,
    from_file,
    output_format,
    stats,
    stats_interval,
):
    """Watch a serial bus and decode every frame; never transmits.

    Frames are split by their implicit length and by silence, checked (CRC or LRC),
    decoded, and each response is paired with its request, with the latency. Flags:
    bad-checksum, exception, invalid, unsolicited (a response to no request seen),
    late, broadcast, garbage; a request with no response gets an "unanswered" line.
    Each line has the time (ms) and the gap before the frame. Ctrl-C, SIGTERM,
    --duration or --frames stop it, with a summary line on stderr.

    --stats counts instead, per unit, to tell which device is sick: a table on exit (and
    every --stats-interval), or one JSON object each time with -o json.
    """
    ctx = click.get_current_context()
    profile = ctx.meta.get("mbtool.profile")
    if profile:
        line = defaults(profile)  # port, framer and the serial settings of a device's profile
        port = port if from_file else line.get("port", port)  # a recording needs no port
        framer = line.get("framer", framer)
        baud, parity = line.get("baud", baud), line.get("parity", parity)
        bytesize, stopbits = line.get("bytesize", bytesize), line.get("stopbits", stopbits)
    port_given = port and ctx.get_parameter_source("port") is not click.core.ParameterSource.ENVIRONMENT
    if from_file and port_given:
        raise UsageError("give -p TARGET to listen or --from-file FILE to analyse a recording, not both")
    recording, timed = None, True
    if stats_interval is not None and not stats:
        raise UsageError("--stats-interval goes with --stats")
    if from_file:
        recording, timed = _recording(from_file)
        _check_replay_options(ctx, from_file, timed)
    else:
        _check_port(port)
    sniffer = BusMonitor(framer, silence or default_silence(framer, baud), response_timeout, timed)
    output = Output(output_format or default_format(), timed=timed)
    tally = Tally()
    counts = _bus_stats(framer, baud, parity, bytesize, stopbits, timed, from_file) if stats else None
    next_stats = time.monotonic() + stats_interval if stats_interval else None
    recorder = None
    if capture:
        try:
            recorder = BusCapture.create(capture)
        except OSError as error:
            raise UsageError(f"cannot write capture file {capture}: {error.strerror or error}") from None

    def show(seen) -> bool:
        """Show what the sniffer found; False once --frames is reached."""
        nonlocal next_stats
        for item in seen:
            if frame_limit and tally.frames >= frame_limit:
                return False
            tally.count(item)
            if counts is None:
                output.write(item)
            else:
                counts.count(item)
            if recorder is not None and isinstance(item, BusFrame):
                recorder.frame(item)
        if next_stats is not None and time.monotonic() >= next_stats:
            next_stats += stats_interval
            output.stats(counts, time.time())
        return not (frame_limit and tally.frames >= frame_limit)

    interrupted = False
    lost = None
    try:
        if from_file:
            assert recording is not None  # read from from_file above
            _replay(from_file, recording, sniffer, show)
        else:
            lost = _listen(port, framer, baud, parity, bytesize, stopbits, duration, sniffer, show)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        if counts is not None:
            # Listening: the time watched runs to now; a recording's, to its last frame.
            output.stats(counts, None if from_file else time.time())
        output.close()
        if recorder is not None:
            recorder.close()
    summary = str(tally)
    if not timed:
        summary += f"; {from_file} is raw bytes with no time stamps: no time, gap or latency"
    if lost is not None:
        raise ConnectionFailed(f"{lost}; {summary}")
    if interrupted:
        return Verdict("interrupted; " + summary, ExitCode.INTERRUPTED if tally.frames == 0 else ExitCode.OK)
    return Verdict(summary, ExitCode.OK)


def _bus_stats(framer, baud, parity, bytesize, stopbits, timed: bool, from_file):
    """The counts --stats shows, with the line's t3.5 (none on ASCII: spec §2) and character time."""
    bits = character_bits(parity, int(bytesize), int(stopbits))
    t35 = silent_interval(baud, bits) if framer == "rtu" else None
    # Listening, the time watched starts now; a recording's at its first frame.
    return BusStats(t35, char_time(baud, bits), timed, None if from_file else time.time())


def _check_replay_options(ctx: click.Context, path: str, timed: bool) -> None:
    """Refuse the options a recording leaves nothing to do: a recording is read to its end,
    and raw bytes have no times to measure a silence or a timeout by."""

    def given(name: str) -> bool:
        return ctx.get_parameter_source(name) is click.core.ParameterSource.COMMANDLINE

    if given("duration"):
        raise UsageError(
            "--duration is for listening; a recording is read to its end (--frames stops sooner)"
        )
    if given("stats_interval"):
        raise UsageError("--stats-interval is for listening; a recording's statistics are shown at its end")
    for name in ("silence", "response_timeout"):
        if not timed and given(name):
            option = "--" + name.replace("_", "-")
            raise UsageError(f"{option} measures time, and {path} is raw bytes with no time stamps")


def _check_port(port: str | None) -> None:
    if not port:
        raise UsageError("no port given: use -p TARGET or set MBTOOL_PORT, or --from-file FILE")
    scheme = port.split("://", 1)[0].lower() if "://" in port else ""
    if scheme in ("tcp", "sim"):
        raise UsageError(
            f"monitor listens on a serial line, not {scheme}:// (a serial device, socket:// or rfc2217://)"
        )


def _recording(path: str) -> tuple[bytes, bool]:
    """A recording's bytes, and whether it has time stamps: a pcap file (--capture's) has,
    raw bytes from a line have none."""
    try:
        with open(path, "rb") as file:
            data = file.read()
    except OSError as error:
        raise UsageError(f"cannot read {path}: {error.strerror or error}") from None
    return data, is_pcap(data)


def _replay(path: str, data: bytes, sniffer, show) -> None:
    """A recording: a pcap file with its time stamps, else raw bytes with none."""
    if not sniffer.timed:  # frames split by their implicit length alone; the summary says so
        now = time.time()  # no time of its own: what --capture stamps its packets with
        if show(sniffer.feed(now, data)):
            show(sniffer.finish(now))
        return
    if sniffer.framing != "rtu":
        raise UsageError(
            f"{path} is a pcap file, which holds RTU frames (--capture writes ASCII ones as RTU)"
        )
    last = None
    try:
        for when, payload in packets(data):
            if not show(sniffer.feed(when, payload)):
                return
            last = when
    except ValueError as error:
        raise UsageError(f"{path}: {error}") from None
    if last is not None:
        show(sniffer.finish(last))


def _listen(port, framer, baud, parity, bytesize, stopbits, duration, sniffer, show) -> str | None:
    """Read the line until --duration, --frames or an interrupt; the reason if the port was lost."""
    settings = SerialSettings(baud=baud, parity=parity, bytesize=int(bytesize), stopbits=int(stopbits))
    # Opened with RTS low: it never drives the bus. ConnectionFailed (exit 6) if it cannot open.
    transport = SerialTransport(port, settings, listen_only=True)
    try:
        # One write: a signal between the text and its newline would run them on to the summary.
        sys.stderr.write(
            f"mbtool: listening on {port} ({settings}, {framer}, silence "
            f"{1000 * sniffer.silence:g} ms); nothing is sent\n"
        )
        sys.stderr.flush()
        deadline = time.monotonic() + duration if duration else None
        wait = min(sniffer.silence, TICK)
        looked = time.time()  # when the last read returned: bytes found later came after it
        while True:
            if deadline is not None:
                left = deadline - time.monotonic()
                if left <= 0:
                    break
                wait = min(wait, left)
            try:
                data = transport.read(wait)
            except NoResponse as error:  # the port went away (USB adapter unplugged, bridge closed)
                show(sniffer.finish(time.time()))
                return f"lost the serial line: {error}"
            now = time.time()
            if not show(sniffer.feed(now, data, since=looked) if data else sniffer.idle(now)):
                return None
            looked = now
        show(sniffer.finish(time.time()))
        return None
    finally:
        transport.close()


# --- output --------------------------------------------------------------------------------


def _ms(seconds: float | None) -> float | None:
    return None if seconds is None else round(seconds * 1000, 1)


def wire_text(frame) -> str:
    """The bytes as a person reads them: ASCII frames as their text, everything else in hex."""
    if frame.framing == "ascii" and frame.direction != "garbage":
        return frame.wire.decode("ascii", "replace").strip()
    return frame.wire.hex(" ").upper()


def summary(frame) -> str:
    """The decoded frame in one line (cli.frames.one_line)."""
    return one_line(frame.described)


def _when(item, timed: bool) -> str | None:
    """The time of a frame or note; None for a recording with no time stamps."""
    return local_time(item.time) if timed else None


def as_dict(item, timed: bool = True) -> dict:
    """One JSON object per frame, garbage run or unanswered request."""
    if isinstance(item, Unanswered):
        request = item.request
        return {
            "time": _when(item, timed),
            "event": "unanswered",
            "request": request.number,
            "unit": request.unit,
            "function": request.function,
            "name": request.described.name if request.described else None,
            "reason": item.reason,
        }
    data = {
        "time": _when(item, timed),
        "event": "garbage" if item.direction == "garbage" else "frame",
        "number": item.number,
        "gap_ms": _ms(item.gap),
        "direction": item.direction,
        "unit": item.unit,
        "function": item.function,
        "name": item.described.name if item.described else None,
        "frame": item.wire.decode("ascii", "replace")
        if item.framing == "ascii" and item.direction != "garbage"
        else item.wire.hex(" ").upper(),
        "checksum": None if item.checksum_ok is None else {"ok": item.checksum_ok, "verdict": item.checksum},
        "summary": summary(item) if item.described else item.note,
        "latency_ms": _ms(item.latency),
        "request": item.request,
        "flags": list(item.flags),
    }
    if item.described is not None:
        decoded = frame_report(item.described).data
        data["fields"] = decoded["fields"]
        data["warnings"] = decoded["warnings"]
    return data


def plain_line(item, timed: bool = True) -> str:
    when = _when(item, timed) or "-"
    if isinstance(item, Unanswered):
        request = item.request
        assert request.function is not None  # a request's, read from its frame
        name = request.described.name if request.described else ""
        return (
            f"{when} unanswered #{request.number} unit={request.unit} "
            f"{function_code_text(request.function)} {name} | {item.reason}"
        )
    gap = "-" if item.gap is None else f"{item.gap * 1000:.1f}ms"
    head = f"{when} gap={gap} #{item.number} {item.direction}"
    if item.direction == "garbage":
        return f"{head} {len(item.wire)} bytes [{wire_text(item)}] | {item.note}"
    line = (
        f"{head} unit={item.unit} {function_code_text(item.function & 0x7F)} [{wire_text(item)}]"
        f" {item.checksum} | {summary(item)}"
    )
    if item.latency is not None:
        line += f" | latency={item.latency * 1000:.1f}ms request=#{item.request}"
    elif item.request is not None:  # no time stamps: the request it answers, no latency
        line += f" | request=#{item.request}"
    if item.flags:
        line += " | flags=" + ",".join(item.flags)
    return line


class _Stats(NamedTuple):
    """The statistics so far, as an item of the output: a table's lines, or a JSON object."""

    counts: BusStats
    now: float | None


class Output:
    """Each frame the moment it is seen, flushed, by the format's sink (its Log): a terminal
    gets coloured lines.  This Output gives each format's view of an item."""

    COLOURS = {"request": "cyan", "response": "green", "garbage": "red"}

    def __init__(self, fmt: str, out=None, timed: bool = True) -> None:
        self.out = out or sys.stdout
        self.timed = timed  # False: a recording with no time stamps
        self.log = sink(fmt).Log(self.out, self, highlight=False, soft_wrap=True)

    def write(self, item) -> None:
        self.log.write(item)
        self.out.flush()

    def data(self, item) -> dict:
        if isinstance(item, _Stats):
            # A recording's are as of its last frame; raw bytes have no time at all.
            counts, now = item
            when = now if now is not None else counts.last
            record = {"event": "stats", "time": local_time(when) if counts.timed and when else None}
            return {**record, **counts.as_dict(now)}
        return as_dict(item, self.timed)

    def lines(self, item) -> list[str]:
        if isinstance(item, _Stats):
            return item.counts.table(item.now)
        return [plain_line(item, self.timed)]

    def draw(self, item, console) -> None:
        if isinstance(item, _Stats):
            self.out.write("".join(line + "\n" for line in self.lines(item)))
        else:
            self._coloured(item, console)

    def _coloured(self, item, console) -> None:
        if isinstance(item, Unanswered):
            request = item.request
            assert request.function is not None  # a request's, read from its frame
            name = request.described.name if request.described else ""
            when = _when(item, self.timed) or "-"
            console.print(
                f"[dim]{when}[/] [bold red]unanswered[/] #{request.number} unit {request.unit} "
                f"{function_code_text(request.function)} {escape(name)}: {escape(item.reason)}"
            )
            return
        gap = "" if item.gap is None else f"+{item.gap * 1000:.1f}ms"
        colour = self.COLOURS.get(item.direction, "white")
        when = _when(item, self.timed) or "-"
        head = f"[dim]{when} {gap:>10}[/] #{item.number:<4} [{colour}]{item.direction:<8}[/]"
        if item.direction == "garbage":
            console.print(
                f"{head} [red]{len(item.wire)} bytes, {escape(item.note)}[/] [dim]{wire_text(item)}[/]"
            )
            return
        verdict = (
            f"[green]{escape(item.checksum)}[/]"
            if item.checksum_ok
            else f"[bold red]{escape(item.checksum)}[/]"
        )
        line = (
            f"{head} unit {item.unit:<3} {function_code_text(item.function & 0x7F)} {escape(summary(item))}"
        )
        if item.latency is not None:
            line += f" [yellow]{item.latency * 1000:.1f} ms[/]"
        flags = [flag for flag in item.flags if flag != "bad-checksum"]
        if flags:
            line += " [bold red]" + escape(" ".join(flags)) + "[/]"
        console.print(f"{line}\n    [dim]{escape(wire_text(item))}[/] {verdict}")

    def stats(self, counts, now: float | None) -> None:
        """The statistics so far (monitor.stats.BusStats): a table, or one JSON object."""
        self.write(_Stats(counts, now))

    def close(self) -> None:
        self.out.flush()
