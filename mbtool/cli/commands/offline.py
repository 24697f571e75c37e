"""Frames by hand: raw (send any PDU or exact bytes), decode (offline), crc and lrc (spec §2)."""

from __future__ import annotations

import sys

import click

from mbtool.cli.frames import frame_report
from mbtool.cli.options import NO_HEADER_OPTION, Choice, QuickHelp, device_command, output_chosen
from mbtool.codec.errors import RequestError

FORMAT_OPTION = click.option(
    "-o",
    "--format",
    "output_format",
    type=Choice(["table", "plain", "json", "csv"]),
    callback=lambda ctx, param, value: output_chosen(value),
    help="Output format: table on a terminal, plain in a pipe.",
)


class OfflineCommand(QuickHelp, click.Command):
    """A command that talks to no device."""


def _render(report, output_format: str | None) -> None:
    from mbtool.cli.render import default_format, render

    render(report, output_format or default_format())


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
def decode(frame, framer, direction, output_format):
    """Decode frames offline.

    Field by field, checking the CRC, LRC or MBAP header. HEX is one frame (RTU bytes, an
    ASCII ':...' frame, or a Modbus TCP frame); with no HEX or '-', one frame per line is
    read from stdin and decoded as it comes (tail -f log | mbtool decode), also the TX and
    RX lines --hex prints. A reply after its request is checked against it. A line that is
    no frame is reported with its number and decoding goes on. Exit 5 when a checksum, a
    field or a line is wrong.
    """
    from mbtool.codec.describe import describe
    from mbtool.codec.errors import FrameError

    if frame and frame != ("-",):
        described = describe(" ".join(frame), framer, direction)
        _render(frame_report(described), output_format)
        problem = _problem(described)
        if problem:
            raise FrameError(problem)
        return
    from mbtool.cli.render import default_format

    if sys.stdin.isatty():
        print("mbtool: reading frames from stdin, one per line; Ctrl-D ends", file=sys.stderr)
    _decode_stream(sys.stdin, framer, direction, output_format or default_format())


def _decode_stream(lines, framer, direction, fmt: str) -> None:
    """One frame a line, each decoded and written as it comes, in constant memory."""
    from mbtool.cli.render import error_json
    from mbtool.codec.describe import describe
    from mbtool.codec.errors import FrameError
    from mbtool.codec.record import replace
    from mbtool.errors import KNOWN_ERRORS, ExitCode

    frames = unreadable = failed = 0  # frames decoded, lines that are none, lines with a problem
    first_failure = ""
    previous = None
    for number, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        text, kind = _trace_line(text)
        try:
            described = describe(text, framer, direction or kind, previous)
        except KNOWN_ERRORS as error:  # not a frame at all: say where, and go on
            problem, described = str(error), None
            unreadable += 1
        else:
            if frames and fmt in ("plain", "table"):
                sys.stdout.write("\n")
            report = frame_report(described, header=frames == 0)
            if fmt == "json":
                report = replace(report, data={"line": number, **report.data})
            _render(report, fmt)
            frames += 1
            problem = _problem(described)
        previous = described
        if problem:
            failed += 1
            first_failure = first_failure or f"line {number}: {problem}"
            if fmt == "json":
                if described is None:
                    sys.stdout.write(
                        error_json(problem, int(ExitCode.INVALID_RESPONSE), line=number, input=text) + "\n"
                    )
            else:
                sys.stdout.flush()  # stdout and stderr in the order of the lines
                print(f"mbtool: line {number}: {problem}", file=sys.stderr)
        sys.stdout.flush()
    if not frames and not failed:
        raise RequestError("no frame on stdin")
    if failed:
        raise FrameError(f"{failed} of {frames + unreadable} lines failed; the first: {first_failure}")


def _trace_line(text: str) -> tuple[str, str | None]:
    """A line --hex printed ('TX 01 03 ... C4 0B  CRC C4 0B ok'): the frame and its direction."""
    head, _, rest = text.partition(" ")
    if head in ("TX", "RX") and rest:
        frame = rest.strip().split("  ", 1)[0]  # the verdict follows two spaces
        return frame, "request" if head == "TX" else "response"
    return text, None


# --- crc / lrc -----------------------------------------------------------------------------------


@click.command("crc", cls=OfflineCommand, context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("data", nargs=-1, required=True, metavar="HEX...")
@FORMAT_OPTION
@NO_HEADER_OPTION
def crc(data, output_format):
    """CRC-16/MODBUS of bytes.

    The CRC of HEX, and the RTU frame with it appended (low byte first).
    """
    from mbtool.cli.render import Report, Row
    from mbtool.codec.checksum import crc16
    from mbtool.codec.describe import parse_hex

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
    )


@click.command("lrc", cls=OfflineCommand, context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("data", nargs=-1, required=True, metavar="HEX...")
@FORMAT_OPTION
@NO_HEADER_OPTION
def lrc(data, output_format):
    """LRC of bytes.

    The LRC of HEX (unit through last data byte), and the ASCII frame with it.
    """
    from mbtool.cli.render import Report, Row
    from mbtool.codec.checksum import lrc as lrc8
    from mbtool.codec.describe import parse_hex

    body = parse_hex(" ".join(data))
    value = lrc8(body)
    text = ":" + (body + bytes([value])).hex().upper()
    rows = [Row("lrc", value, f"{value:02X}"), Row("frame", text + "\r\n", text)]
    data_out = {"lrc": value, "frame": text + "\r\n"}
    _render(Report(None, None, "LRC", rows, data_out, note="the frame ends with CR LF"), output_format)


# --- raw -------------------------------------------------------------------------------------------


@device_command("raw")
@click.argument("data", nargs=-1, required=True, metavar="HEX...")
@click.option("--adu", is_flag=True, help="Send HEX exactly as given (checksum or MBAP header included).")
def raw(connection, data, adu):
    """Send any PDU, or exact frame bytes.

    HEX is a unit and a PDU; mbtool adds the CRC, LRC or MBAP header and shows
    the reply decoded, with its checksum verdict. The first byte is the unit (-u is not used). Any function code may be sent;
    a reply of unknown length ends when the line goes quiet. With --adu the
    bytes go out exactly as typed, a wrong checksum too.
    """
    from mbtool.cli.session import open_client
    from mbtool.codec.describe import describe_pdu, parse_hex, split_frame
    from mbtool.codec.errors import FrameError, ModbusException
    from mbtool.codec.raw import RawRequest
    from mbtool.link.client import Trace
    from mbtool.link.connection import framer_name

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
            raise RequestError("give the unit and at least a function code, e.g. raw 01 03 00 00 00 01")
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
            from mbtool.codec.errors import ChecksumError

            if isinstance(error, ChecksumError):
                self.other = frame

    failure = None
    with open_client(connection, framer=_exact_framer(name, exact)) as client:
        capture = Capture(client.trace)
        client.trace = capture
        try:
            client.execute(unit, request)
        except (ModbusException, FrameError) as error:
            failure = error
    from mbtool.cli.render import Report, Row, default_format, render

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
            connection.output_format or default_format(),
        )
        if failure is not None:
            raise failure
        return
    shown = heard.decode("ascii", "replace") if name == "ascii" else heard.hex(" ")
    framing, got, got_unit, got_pdu, ok, verdict = split_frame(shown, name)
    asked = describe_pdu(name, b"", unit, request.encode(), None, "", "request")
    described = describe_pdu(framing, got, got_unit, got_pdu, ok, verdict, "response", asked)
    render(frame_report(described), connection.output_format or default_format())
    if failure is not None:
        raise failure
    if described.error:
        raise FrameError(f"invalid reply: {described.error}")


def _exact_framer(name: str, exact: bytes | None):
    """The framer for ``name``; with ``exact``, one that sends those bytes instead of building a frame."""
    from mbtool.codec.framing import FRAMERS, Frame
    from mbtool.codec.record import replace

    base = FRAMERS[name]
    if exact is None:
        return base()
    tid = int.from_bytes(exact[0:2], "big") if name == "tcp" else None

    class Exact(base):
        def build(self, unit: int, pdu: bytes, transaction_id: int = 0) -> bytes:
            return exact

        def next_event(self):
            # The client matches replies to transaction ids it chose; these bytes carry the
            # user's, so a reply to the user's id is handed over unnumbered.
            event = super().next_event()
            if tid is not None and isinstance(event, Frame) and event.transaction_id == tid:
                event = replace(event, transaction_id=None)
            return event

    return Exact()
