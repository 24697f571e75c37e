"""Frames by hand: raw (send any PDU or exact bytes), decode (offline), crc and lrc (spec §2)."""

from __future__ import annotations

import re
import sys

import click

from mbtool.cli.frames import frame_report
from mbtool.cli.options import NO_HEADER_OPTION, device_command, output_chosen
from mbtool.cli.param_types import Choice
from mbtool.cli.parsing import QuickHelp
from mbtool.cli.results import Report, Row
from mbtool.cli.session import open_client
from mbtool.cli.sinks import RESULTS, SINKS, default_format, formats, render
from mbtool.codec.checksum import crc16
from mbtool.codec.checksum import lrc as lrc8
from mbtool.codec.describe import describe, describe_pdu, looks_whole, parse_hex, split_frame
from mbtool.codec.errors import ChecksumError, FrameError, ModbusException, RequestError
from mbtool.codec.framing import FRAMERS, Frame, Framer
from mbtool.codec.raw import RawRequest
from mbtool.codec.record import replace
from mbtool.errors import KNOWN_ERRORS, UsageError
from mbtool.link.connection import framer_name
from mbtool.words import counted

FORMAT_OPTION = click.option(
    "-o",
    "--format",
    "output_format",
    type=Choice(formats(RESULTS)),
    callback=output_chosen,
    help="Output format: table on a terminal, plain in a pipe.",
)


class OfflineCommand(QuickHelp, click.Command):
    """A command that talks to no device."""


def _render(report, output_format: str | None, no_header: bool) -> None:
    render(report, output_format or default_format(), csv_header=not no_header)


def _problem(described) -> str:
    if described.checksum_ok is False:
        return described.checksum
    return described.error


# --- decode ----------------------------------------------------------------------------------


@click.command("decode", cls=OfflineCommand, context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("frame", nargs=-1, metavar="[HEX...|-]")
@click.option("--framer", type=Choice(["rtu", "ascii", "tcp"]), help="Framing (default: detected).")
@click.option("--request", "direction", flag_value="request", help="Read the frame as a request.")
@click.option("--response", "direction", flag_value="response", help="Read the frame as a response.")
@FORMAT_OPTION
@NO_HEADER_OPTION
def decode(frame, framer, direction, output_format, no_header):
    """Decode frames offline.

    Field by field, checking the CRC, LRC or MBAP header. HEX is one frame (RTU bytes, an
    ASCII ':...' frame, or a Modbus TCP frame); with no HEX or '-', one frame per line is
    read from stdin and decoded as it comes (tail -f log | mbtool decode), also the TX and
    RX lines --hex prints, monitor's lines (plain or json) and socat -x dumps. A reply after
    its request is checked against it. A line that is no frame is named on stderr and
    passed over. Exit 5 when a frame's checksum or a field is wrong.
    """
    if frame and frame != ("-",):
        described = describe(" ".join(frame), framer, direction)
        _render(frame_report(described), output_format, no_header)
        problem = _problem(described)
        if problem:
            raise FrameError(problem)
        return

    if sys.stdin.isatty():
        print("mbtool: reading frames from stdin, one per line; Ctrl-D ends", file=sys.stderr)
    _decode_stream(sys.stdin, framer, direction, output_format or default_format(), no_header)


def _decode_stream(lines, framer, direction, fmt: str, no_header: bool) -> None:
    """Each frame in the lines decoded and written as it comes, in constant memory.  Only
    frames decide the exit status: a line that is no frame is named on stderr and passed over."""
    frames = failed = 0  # frames decoded, and of them those with a problem
    shown = SINKS[fmt]
    first_failure = ""
    previous = None
    for number, text, kind in frames_in(lines):
        try:
            described = describe(text, framer, direction or kind, previous)
        except KNOWN_ERRORS as error:  # not a frame at all (not hex, too short): say where, go on
            sys.stdout.flush()  # stdout and stderr in the order of the lines
            print(f"mbtool: line {number}: not a frame, passed over: {error}", file=sys.stderr)
            continue
        if frames and shown.blocks:  # a blank line between two frames' blocks
            sys.stdout.write("\n")
        report = frame_report(described, header=frames == 0)
        report = replace(report, data={"line": number, **report.data})  # JSON's own keys
        _render(report, fmt, no_header)
        frames += 1
        previous = described
        problem = _problem(described)
        if problem:
            failed += 1
            first_failure = first_failure or f"line {number}: {problem}"
            if not shown.errors:  # the JSON record carries its error
                sys.stdout.flush()
                print(f"mbtool: line {number}: {problem}", file=sys.stderr)
        sys.stdout.flush()
    if not frames:
        raise UsageError("no frame on stdin")
    if failed:
        raise FrameError(f"{failed} of {counted(frames, 'frame')} failed; the first: {first_failure}")


# What decode reads besides a frame a line: the lines mbtool itself writes, and socat's dumps.
# --hex: 'TX 01 03 00 00 00 02 C4 0B  CRC C4 0B ok'
TRACE_LINE = re.compile(r"(TX|RX) (?P<frame>\S.*?)(  .*)?$")
# monitor -o plain (monitor.py's plain_line): 'TIME gap=... #N request unit=1 FC 03 (0x03) [01 03 ...] ...'
MONITOR_LINE = re.compile(
    r"\S+ gap=\S+ #\d+ (?P<direction>request|response|garbage) .*?\[(?P<frame>[^\]]*)\]"
)
MONITOR_UNANSWERED = re.compile(r"\S+ unanswered #\d+ ")
# socat -x (-v): '> 2026/01/02 10:00:00.000100  length=8 from=0 to=7', the bytes in hex on
# the lines after it (16 a line with -v, the text beside them), and '--' between blocks.
SOCAT_HEADER = re.compile(
    r"(?P<arrow>[<>]) \d{4}/\d\d/\d\d \d\d:\d\d:\d\d\S*\s+length=(?P<length>\d+) from=\d+ to=\d+$"
)


def frames_in(lines):
    """(line number, frame, "request" | "response" | None) of each frame in the lines: one
    frame a line, --hex's TX and RX lines, monitor's lines (-o plain and json), and socat -x
    dumps.  Blank lines, comments and what those tools write that is no frame (monitor's
    garbage and unanswered lines, socat's --) are passed over."""
    socat = _SocatBlocks()
    for number, line in enumerate(lines, start=1):
        text = line.strip()
        if socat.reading:
            try:  # a line of the block's bytes; with -v, the text beside them after two spaces
                socat.add(parse_hex(text.split("  ", 1)[0]))
                continue
            except RequestError:
                pass  # the block ends short of its length: what it has is decoded
        header = SOCAT_HEADER.match(text)
        if header:
            yield from socat.start(number, header["arrow"], int(header["length"]))
            continue
        if text != "--":
            yield from socat.end()
        if not text or text.startswith("#") or text == "--" or MONITOR_UNANSWERED.match(text):
            continue
        trace = TRACE_LINE.match(text)
        if trace:
            yield number, trace["frame"], "request" if trace[1] == "TX" else "response"
            continue
        monitored = MONITOR_LINE.match(text)
        if monitored:
            if monitored["direction"] != "garbage":
                yield number, monitored["frame"], monitored["direction"]
            continue
        frame = _monitor_json(text) if text.startswith("{") else None
        if frame is not None:
            if frame:
                yield number, *frame
            continue
        yield number, text, None
    yield from socat.end()


class _SocatBlocks:
    """socat -x's blocks: each is what one read of a link returned, so a frame on a serial
    line may come in several.  A block that ends no frame (codec.describe.looks_whole) is
    held and joined with the next block from the same side; the other side's block, or
    anything else, ends it as it is."""

    def __init__(self) -> None:
        self.block: list | None = None  # [line, side, bytes, length] being read
        self.held: list | None = None

    @property
    def reading(self) -> bool:
        return self.block is not None and len(self.block[2]) < self.block[3]

    def add(self, data: bytes) -> None:
        assert self.block is not None  # called while reading a block
        self.block[2] += data

    def start(self, number: int, side: str, length: int) -> list:
        done = self._settle()
        self.block = [number, side, bytearray(), length]
        return done

    def end(self) -> list:
        """Anything but a block follows: what is read or held is a frame as it is."""
        done = self._settle()
        if self.held is not None:
            done.append(self._frame(self.held))
            self.held = None
        return done

    def _settle(self) -> list:
        block, self.block = self.block, None
        done: list = []
        if block is None:
            return done
        if self.held is not None:
            if self.held[1] == block[1]:
                self.held[2] += block[2]
                block = self.held
            else:
                done.append(self._frame(self.held))
            self.held = None
        if looks_whole(bytes(block[2])):
            done.append(self._frame(block))
        else:
            self.held = block
        return done

    @staticmethod
    def _frame(block: list) -> tuple:
        number, _, data, _ = block
        if data[:1] == b":" and data.isascii():  # an ASCII frame: as its text
            return number, data.decode("ascii").strip(), None
        return number, bytes(data).hex(" ").upper(), None


def _monitor_json(text: str) -> tuple | None:
    """A line of monitor -o json: (frame, direction) for a frame, () for what is none
    (garbage, unanswered); None when the line is not monitor's JSON."""
    import json  # noqa: PLC0415 - 1 ms: decode of monitor's JSON lines only

    try:
        record = json.loads(text)
    except ValueError:
        return None
    if not isinstance(record, dict) or "event" not in record:
        return None
    if record["event"] != "frame" or not isinstance(record.get("frame"), str):
        return ()
    return record["frame"], record.get("direction")


# --- crc / lrc -----------------------------------------------------------------------------------


@click.command("crc", cls=OfflineCommand, context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("data", nargs=-1, required=True, metavar="HEX...")
@FORMAT_OPTION
@NO_HEADER_OPTION
def crc(data, output_format, no_header):
    """CRC-16/MODBUS of bytes.

    The CRC of HEX, and the RTU frame with it appended (low byte first).
    """
    body = parse_hex(" ".join(data))
    value = crc16(body)
    wire = value.to_bytes(2, "little")
    rows = [
        Row("crc", value, wire.hex(" ").upper()),
        Row("frame", (body + wire).hex(" ").upper()),
    ]
    data_out = {"crc": value, "crc_bytes": wire.hex(" ").upper(), "frame": (body + wire).hex(" ").upper()}
    _render(
        Report(None, None, "CRC-16/MODBUS", rows, data_out, note=f"0x{value:04X}, sent low byte first"),
        output_format,
        no_header,
    )


@click.command("lrc", cls=OfflineCommand, context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("data", nargs=-1, required=True, metavar="HEX...")
@FORMAT_OPTION
@NO_HEADER_OPTION
def lrc(data, output_format, no_header):
    """LRC of bytes.

    The LRC of HEX (unit through last data byte), and the ASCII frame with it.
    """
    body = parse_hex(" ".join(data))
    value = lrc8(body)
    text = ":" + (body + bytes([value])).hex().upper()
    rows = [Row("lrc", value, f"{value:02X}"), Row("frame", text + "\r\n", text)]
    data_out = {"lrc": value, "frame": text + "\r\n"}
    _render(
        Report(None, None, "LRC", rows, data_out, note="the frame ends with CR LF"), output_format, no_header
    )


# --- raw -------------------------------------------------------------------------------------------


@device_command("raw", unit=False)
@click.argument("data", nargs=-1, required=True, metavar="HEX...")
@click.option("--adu", is_flag=True, help="Send HEX exactly as given (checksum or MBAP header included).")
def raw(connection, settings, data, adu):
    """Send any PDU, or exact frame bytes.

    HEX is a unit and a PDU; mbtool adds the CRC, LRC or MBAP header and shows
    the reply decoded, with its checksum verdict. The first byte is the unit. Any function code may be sent;
    a reply of unknown length ends when the line goes quiet. With --adu the
    bytes go out exactly as typed, a wrong checksum too.
    """
    from mbtool.link.client import Trace  # noqa: PLC0415 - 5-7 M instructions: raw only, not crc

    name = framer_name(connection)
    text = " ".join(data)
    exact = None
    if adu:
        framing, sent, unit, pdu, _, _ = split_frame(text, name)
        exact = text.strip().encode() if text.strip().startswith(":") else sent
        if framing == "ascii" and not exact.endswith(b"\r\n"):
            exact = (exact if exact.startswith(b":") else b":" + sent.hex().upper().encode()) + b"\r\n"
    else:
        body = parse_hex(text)
        if len(body) < 2:
            raise UsageError("give the unit and at least a function code, e.g. raw 01 03 00 00 00 01")
        unit, pdu = body[0], body[1:]
    request = RawRequest(pdu)

    class Capture(Trace):
        """Keeps the reply frame (and any corrupted one) while passing everything to --hex."""

        def __init__(self, inner: Trace) -> None:
            self.inner = inner
            self.reply: bytes | None = None
            self.other: bytes | None = None  # the last frame that was not the reply, or a corrupted one

        def sent(self, frame: bytes) -> None:
            self.inner.sent(frame)

        def received(self, frame: bytes, note: str = "") -> None:
            self.inner.received(frame, note)
            if not note:
                self.reply = frame
            else:
                self.other = frame

        def rejected(self, frame: bytes, error) -> None:
            self.inner.rejected(frame, error)

            if isinstance(error, ChecksumError):
                self.other = frame

    failure = None
    with open_client(connection, settings, framer=_exact_framer(name, exact)) as client:
        capture = Capture(client.trace)
        client.trace = capture
        try:
            client.execute(unit, request)
        except (ModbusException, FrameError) as error:
            failure = error

    heard = capture.reply or capture.other
    if heard is None:
        if unit == client.framer.broadcast_unit:
            why = "broadcast: no reply expected"
            # As every write to unit 0 does: a script reading stdout alone must not take it as confirmed.
            print("mbtool: broadcast: no device confirms a write to unit 0", file=sys.stderr)
        elif failure is None:
            why = "none expected (force listen only)"
        else:
            why = f"none: {failure}"
        rows = [Row("sent", request.encode().hex(" ").upper()), Row("reply", why)]
        render(
            Report(unit, request.function_code, request.name, rows),
            settings.output_format or default_format(),
            csv_header=settings.csv_header,
        )
        if failure is not None:
            raise failure
        return
    shown = heard.decode("ascii", "replace") if name == "ascii" else heard.hex(" ")
    framing, got, got_unit, got_pdu, ok, verdict = split_frame(shown, name)
    asked = describe_pdu(name, b"", unit, request.encode(), None, "", "request")
    described = describe_pdu(framing, got, got_unit, got_pdu, ok, verdict, "response", asked)
    render(
        frame_report(described), settings.output_format or default_format(), csv_header=settings.csv_header
    )
    if failure is not None:
        raise failure
    if described.error:
        raise FrameError(f"invalid reply: {described.error}")


def _exact_framer(name: str, exact: bytes | None):
    """The framer for ``name``; with ``exact``, one that sends those bytes instead of building a frame."""
    base = FRAMERS[name]
    if exact is None:
        return base()
    # The framer's own class with _Exact's two methods first (a class made at run time, as
    # the framing is only known then).
    framer = type("Exact", (_Exact, base), {})()
    framer.exact = exact
    framer.tid = int.from_bytes(exact[0:2], "big") if name == "tcp" else None
    return framer


class _Exact(Framer):
    """Sends the user's bytes as they are, instead of building a frame."""

    exact: bytes
    tid: int | None  # the transaction id in those bytes (MBAP)

    def build(self, unit: int, pdu: bytes, transaction_id: int = 0) -> bytes:
        return self.exact

    def next_event(self):
        # The client matches replies to transaction ids it chose; these bytes carry the
        # user's, so a reply to the user's id is handed over unnumbered.
        event = super().next_event()
        if self.tid is not None and isinstance(event, Frame) and event.transaction_id == self.tid:
            event = event._replace(transaction_id=None)
        return event
