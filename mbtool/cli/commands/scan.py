"""``mbtool scan``: which unit ids answer on a bus, and at which serial settings (issue 5).

One probe per unit id.  Any reply, and any Modbus exception, proves a device is
there (spec §3: an exception response is a valid answer); silence means nobody
is.  Bytes that make no valid frame ("garbled": bad CRC/LRC, broken framing, a
reply that does not fit the probe) mean something is there but the settings
(baud, parity, framing) are probably wrong, so they are kept apart from the
units found.  Exceptions 0A and 0B are a gateway saying the unit behind it is
unreachable (spec §3), so they prove the opposite.

A sweep (--bauds, --parities) opens the link once per serial setting and probes
every unit at each.  The per-unit timeout is short by default: a silent unit
costs the whole timeout, and 247 of them at 1 s would take four minutes.  A
reply that comes after its timeout arrives while the next unit is probed; it is
recognised by its unit id and reported as "late" (raise -t).
"""

from __future__ import annotations

import sys
import time
from contextlib import ExitStack

import click

from mbtool.cli.options import ADDRESS, COUNT, Choice, device_command, parse_units, units_text
from mbtool.codec.errors import FrameError, MismatchError, ModbusException, ProtocolError, RequestError
from mbtool.codec.record import record, replace
from mbtool.errors import ConnectionFailed, ExitCode, NoResponse, Summary
from mbtool.link.connection import close_quietly
from mbtool.link.transport import SerialSettings

SCAN_TIMEOUT = 0.2  # seconds per unit: a reply at 1200 baud plus a slow device's turnaround
DEFAULT_UNITS = "1-247"  # spec §2: 1..247 are the individual addresses, 248..255 reserved
COMMON_BAUDS = (9600, 19200, 38400, 115200, 57600, 4800, 2400, 1200)  # the likeliest first
GATEWAY_EXCEPTIONS = (0x0A, 0x0B)  # spec §3: path unavailable, target failed to respond

READS = ("read-holding-registers", "read-input-registers", "read-coils", "read-discrete-inputs")
PROBES = READS + ("report-id", "device-id", "return-query-data")


# --- options ------------------------------------------------------------------------------


class UnitList(click.ParamType):
    """Unit ids as ``serve -u`` takes them: 1-247, 1,5,10-20 (0, broadcast, is refused)."""

    name = "units"

    def convert(self, value, param, ctx):
        if isinstance(value, frozenset):
            return value
        if isinstance(value, int):
            # A profile's unit names one device; it does not narrow a scan (see _scan_units).
            return value
        try:
            return parse_units(value)
        except RequestError as error:
            self.fail(str(error), param, ctx)


class BaudList(click.ParamType):
    """9600,19200 or "common": each checked as -b checks one."""

    name = "bauds"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        if value.strip().lower() == "common":
            return COMMON_BAUDS
        baud = _shared_param(ctx, "baud").type
        return tuple(_unique(baud.convert(item, param, ctx) for item in _items(value, param, ctx)))


class ParityList(click.ParamType):
    """N,E,O: each checked as --parity checks one."""

    name = "parities"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        parity = _shared_param(ctx, "parity").type
        return tuple(_unique(parity.convert(item, param, ctx) for item in _items(value, param, ctx)))


def _items(text: str, param, ctx) -> list[str]:
    items = [item.strip() for item in text.split(",")]
    if not all(items):
        raise click.BadParameter(f"empty item in {text}", ctx, param)
    return items


def _unique(values) -> list:
    return list(dict.fromkeys(values))


def _shared_param(ctx: click.Context, name: str) -> click.Parameter:
    return next(param for param in ctx.command.params if param.name == name)


def _scan_options(command: click.Command) -> click.Command:
    """Adapt two shared options to a scan.

    -u takes a set of units, as ``serve -u`` does (MBTOOL_UNIT names one device and
    does not narrow a scan), and -t defaults to SCAN_TIMEOUT: a silent unit costs a
    whole timeout.  Every other connection option is the shared one, unchanged.
    """
    for index, param in enumerate(command.params):
        if param.name == "unit":
            command.params[index] = click.Option(
                ["-u", "--unit", "--units", "unit"],
                type=UnitList(),
                metavar="UNITS",
                default=DEFAULT_UNITS,
                show_default=True,
                help="Unit ids to probe: 1-247, 1,5,10-20. Unit 0 (broadcast) is never answered.",
            )
        elif param.name == "timeout":
            param.default = SCAN_TIMEOUT
            param.help = "Seconds to wait for each unit's reply (raise it for slow devices or gateways)."
    return command


def _scan_units(ctx: click.Context) -> list[int]:
    # From the command line or the default, never from a profile's single unit.
    return sorted(ctx.params["unit"])


# --- what was found -----------------------------------------------------------------------


@record
class Setting(SerialSettings):
    """One serial setting of a sweep; ``error`` when the port refused it."""

    error: str = ""


@record
class Answer:
    """How one unit answered one probe: reply, exception or garbled."""

    unit: int
    answer: str  # "reply" | "exception" | "garbled"
    text: str  # for people
    fields: dict  # for scripts (JSON)
    ms: float | None = None  # probe to answer; None for a late answer
    setting: Setting | None = None  # when sweeping
    late: bool = False  # answered after its timeout, during a later probe


class Tally:
    def __init__(self) -> None:
        self.found: list[Answer] = []
        self.garbled: list[Answer] = []
        self.settings: list[Setting] = []
        self.probes = 0
        self.silent: set[tuple[int, int]] = set()  # (setting index, unit) that never answered
        self.gateway = 0  # units a gateway said it cannot reach (exception 0A/0B)
        self.interrupted = False


# --- probing ------------------------------------------------------------------------------


def probe_request(function: str, address: int, count: int):
    """The request each unit is asked; built before anything is opened (bad input: exit 2)."""
    if function in READS:
        from mbtool.codec import data_access

        kind = {
            "read-holding-registers": data_access.ReadHoldingRegisters,
            "read-input-registers": data_access.ReadInputRegisters,
            "read-coils": data_access.ReadCoils,
            "read-discrete-inputs": data_access.ReadDiscreteInputs,
        }[function]
        return kind(address, count)
    if function == "report-id":
        from mbtool.codec.serial_line import ReportSlaveId

        return ReportSlaveId()
    if function == "device-id":
        from mbtool.codec.device_id import ReadDeviceIdCode, ReadDeviceIdentification

        return ReadDeviceIdentification(ReadDeviceIdCode.BASIC, 0)
    from mbtool.codec.serial_line import DEFAULT_QUERY_DATA, Diagnostics, DiagnosticSubFunction

    return Diagnostics(DiagnosticSubFunction.RETURN_QUERY_DATA, DEFAULT_QUERY_DATA)


def _reply_answer(unit: int, reply, ms: float | None) -> Answer:
    """What a reply says about the device, for people (text) and for scripts (fields)."""
    from mbtool.codec.data_access import BitsResponse, RegistersResponse
    from mbtool.codec.describe import printable, text_of
    from mbtool.codec.device_id import DeviceIdentificationResponse
    from mbtool.codec.serial_line import DiagnosticsResponse, ReportSlaveIdResponse

    fields: dict = {}
    text = "reply"
    if isinstance(reply, RegistersResponse):
        fields = {"values": list(reply.registers)}
        text = "registers " + " ".join(str(v) for v in reply.registers)
    elif isinstance(reply, BitsResponse):
        fields = {"values": list(reply.bits)}
        text = "bits " + " ".join("1" if bit else "0" for bit in reply.bits)
    elif isinstance(reply, ReportSlaveIdResponse):
        fields = {
            "slave_id": reply.slave_id,
            "run_indicator": reply.run_indicator,
            "extra_hex": reply.extra.hex(" ").upper(),
            "extra_text": printable(reply.extra),
        }
        text = f"slave id {reply.slave_id}, run {'ON' if reply.run_indicator else 'OFF'}"
        if reply.extra:
            text += f", {printable(reply.extra)}"
    elif isinstance(reply, DeviceIdentificationResponse):
        fields = {"objects": {name: text_of(value) for name, value in reply.named_objects()}}
        text = " / ".join(fields["objects"].values()) or "no objects"
    elif isinstance(reply, DiagnosticsResponse):
        fields = {"echo": reply.data.hex(" ").upper()}
        text = "echo " + fields["echo"]
    return Answer(unit, "reply", text, fields, ms)


class Listener:
    """Passes the trace on (--hex) and keeps the frames that answered no probe: late replies.

    A reply that misses its timeout arrives during a later probe, either as a frame
    the client discards (another unit, an old transaction id) or as stale bytes
    dropped before the next request; both reach the trace, and are read here with a
    framer of their own.
    """

    def __init__(self, inner, framer_name: str) -> None:
        self.inner = inner
        self.framer_name = framer_name
        self.strays: list = []  # codec Frames

    def sent(self, adu: bytes) -> None:
        self.inner.sent(adu)

    def received(self, adu: bytes, note: str = "") -> None:
        self.inner.received(adu, note)
        if note:
            self.strays += frames_in(self.framer_name, adu)

    def rejected(self, data: bytes, error: FrameError) -> None:
        self.inner.rejected(data, error)
        self.strays += frames_in(self.framer_name, data)

    def take(self) -> list:
        strays, self.strays = self.strays, []
        return strays


def frames_in(framer_name: str, data: bytes) -> list:
    """The whole, valid frames in ``data``, read as replies."""
    from mbtool.codec.framing import Frame, make_framer

    framer = make_framer(framer_name)
    framer.feed(data)
    frames = []
    for _ in range(len(data) + 1):  # every event consumes bytes: this bounds the loop
        event = framer.next_event() or framer.silence()
        if event is None:
            break
        if isinstance(event, Frame):
            frames.append(event)
    return frames


def ask(client, unit: int, request, framer_name: str) -> Answer | str:
    """Probe one unit: an Answer, or why there is none ("silent" or "gateway").

    Link failures (ConnectionFailed, a closed connection, OSError) are the caller's.
    """
    from mbtool.link.transport import ConnectionClosed

    began = time.monotonic()
    try:
        reply = client.execute(unit, request)
    except ModbusException as exception:
        return _exception_answer(unit, exception.exception_code, _ms(began)) or "gateway"
    except ConnectionClosed:
        raise
    except NoResponse:
        return "silent"
    except MismatchError as error:
        # A valid frame from another unit is a late reply to an earlier probe (the
        # Listener credits it), not an answer from this one.
        frames = frames_in(framer_name, error.data)
        if frames and all(frame.unit != unit for frame in frames):
            return "silent"
        return Answer(unit, "garbled", str(error), {"error": str(error)})
    except FrameError as error:
        return Answer(unit, "garbled", str(error), {"error": str(error)})
    return _reply_answer(unit, reply, _ms(began))


def _ms(began: float) -> float:
    return round((time.monotonic() - began) * 1000, 1)


def _late(frame, request, probed: set[int], found: set[int]) -> Answer | None:
    """A stray frame as the late answer of a unit probed earlier on this link, if it is one."""
    from mbtool.codec.pdu import ExceptionResponse

    if frame.unit not in probed or frame.unit in found:
        return None
    try:
        reply = request.decode_response(frame.pdu)
    except ProtocolError:
        return None  # not an answer to this probe (another function, or garbled)
    if isinstance(reply, ExceptionResponse):
        answer = _exception_answer(frame.unit, reply.exception_code, None)
    else:
        answer = _reply_answer(frame.unit, reply, None)
    if answer is None:
        return None
    return replace(answer, text=f"{answer.text} (late: answered after the timeout, raise -t)", late=True)


def _exception_answer(unit: int, code: int, ms: float | None) -> Answer | None:
    """An exception proves a device is there, except a gateway's 0A/0B: nobody behind it answered."""
    from mbtool.codec.errors import exception_name

    if code in GATEWAY_EXCEPTIONS:
        return None
    name = exception_name(code)
    return Answer(unit, "exception", f"{code:02X} {name}", {"exception": code, "exception_name": name}, ms)


# --- the sweep ----------------------------------------------------------------------------


class Scan:
    def __init__(
        self,
        connection,
        request,
        units: list[int],
        settings: list[Setting],
        sweeping: bool,
        first: bool,
        output,
    ) -> None:
        self.connection = connection
        self.request = request
        self.units = units
        self.settings = settings
        self.sweeping = sweeping
        self.first = first
        self.output = output
        self.tally = Tally()

    def run(self, progress: Progress) -> Tally:
        self.progress = progress
        tally = self.tally
        try:
            for setting in self.settings:
                tally.settings.append(setting)
                if self._link(setting):
                    break
        except KeyboardInterrupt:
            tally.interrupted = True
        return tally

    def _open(self, setting: Setting):
        from mbtool.cli.session import open_client
        from mbtool.link.connection import framer_name

        # unit: a real one, for open_client's broadcast check (the option holds the whole set).
        connection = replace(self.connection, baud=setting.baud, parity=setting.parity, unit=self.units[0])
        link = ExitStack()
        client = link.enter_context(open_client(connection, self.request.name))
        client.trace = Listener(client.trace, framer_name(connection))
        return link, client

    def _link(self, setting: Setting) -> bool:
        """Probe every unit at one setting; True when the scan should stop (--first)."""
        from mbtool.link.connection import framer_name
        from mbtool.link.transport import ConnectionClosed

        tally = self.tally
        name = framer_name(self.connection)
        link = ExitStack()
        try:
            try:
                link, client = self._open(setting)
            except ConnectionFailed as error:
                if not self.sweeping:
                    raise
                self._refused(setting, str(error), len(self.units))
                return False
            probed: set[int] = set()
            found: set[int] = set()
            here = len(tally.settings) - 1
            for index, unit in enumerate(self.units):
                self.progress.at(setting if self.sweeping else None, unit)
                try:
                    outcome = ask(client, unit, self.request, name)
                except (ConnectionFailed, ConnectionClosed, OSError) as error:
                    # The link broke (a gateway hanging up on an unknown unit, a cable
                    # pulled): count this unit silent and go on over a new link.
                    close_quietly(link)
                    try:
                        link, client = self._open(setting)
                    except ConnectionFailed as again:
                        self._refused(setting, str(again), len(self.units) - index)
                        return False
                    outcome = "silent"
                    self.output.note(f"unit {unit}: {error}; link reopened")
                tally.probes += 1
                self.progress.advance()
                # Only units asked before this one can answer late; a stray frame from this
                # unit is something else (the adapter's echo of the probe, an old transaction).
                answers = [_late(frame, self.request, probed, found) for frame in client.trace.take()]
                probed.add(unit)
                if outcome == "silent":
                    tally.silent.add((here, unit))
                elif outcome == "gateway":
                    tally.gateway += 1
                else:
                    answers.append(outcome)
                for answer in answers:
                    if answer is not None:
                        self._record(replace(answer, setting=setting if self.sweeping else None), here, found)
                if self.first and tally.found:
                    return True
            return False
        finally:
            close_quietly(link)

    def _record(self, answer: Answer, here: int, found: set[int]) -> None:
        """Keep an answer: garbled ones apart, each unit found once per setting."""
        tally = self.tally
        if answer.answer == "garbled":
            tally.garbled.append(answer)
            self.output.garbled(answer)
            return
        if answer.unit in found:
            return
        tally.silent.discard((here, answer.unit))  # a late answer: silent no more
        found.add(answer.unit)
        tally.found.append(answer)
        self.output.found(answer)
        self.progress.found(len(tally.found))

    def _refused(self, setting: Setting, error: str, skipped: int) -> None:
        self.tally.settings[-1] = replace(setting, error=error)
        self.output.note(f"{setting}: {error}" if self.sweeping else error)
        self.progress.advance(skipped)


# --- output -------------------------------------------------------------------------------


class Progress:
    """A rich progress bar on stderr when it is a terminal; nothing otherwise."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.bar = None
        if not enabled:
            return
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeRemainingColumn
        from rich.progress import Progress as Bar

        self.bar = Bar(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("found {task.fields[found]}"),
            TimeRemainingColumn(),
            console=Console(stderr=True),
            transient=True,
            # Lines written meanwhile (found units, notes) go above the bar, not through it.
            redirect_stdout=sys.stdout.isatty(),
            redirect_stderr=True,
        )
        self.task = self.bar.add_task("scan", total=total, found=0)
        self.bar.start()

    def at(self, setting: Setting | None, unit: int) -> None:
        if self.bar is not None:
            where = f"{setting} " if setting else ""
            self.bar.update(self.task, description=f"{where}unit {unit}")

    def advance(self, steps: int = 1) -> None:
        if self.bar is not None:
            self.bar.advance(self.task, steps)

    def found(self, count: int) -> None:
        if self.bar is not None:
            self.bar.update(self.task, found=count)

    def stop(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


def answer_dict(answer: Answer) -> dict:
    data: dict = {"unit": answer.unit, "answer": answer.answer}
    if answer.setting is not None:
        data.update(baud=answer.setting.baud, parity=answer.setting.parity)
    data.update(answer.fields)
    if answer.ms is not None:
        data["ms"] = answer.ms
    if answer.late:
        data["late"] = True
    return data


class Output:
    """Found units as they come (plain, csv: a long scan shows its progress in a pipe),
    or all at the end (table, json)."""

    def __init__(self, fmt: str, sweeping: bool) -> None:
        self.fmt = fmt
        self.sweeping = sweeping
        self.header_done = False

    def found(self, answer: Answer) -> None:
        where = [str(answer.setting.baud), answer.setting.parity] if answer.setting else []
        if self.fmt == "plain":
            print(" ".join([str(answer.unit), answer.answer, *where, answer.text]), flush=True)
        elif self.fmt == "csv":
            import csv

            if not self.header_done:
                self._csv_header()
            csv.writer(sys.stdout, lineterminator="\n").writerow(
                [answer.unit, answer.answer, *where, answer.text, "" if answer.ms is None else answer.ms]
            )
            sys.stdout.flush()

    def _csv_header(self) -> None:
        import csv

        from mbtool.cli.render import wants_csv_header

        where = ["baud", "parity"] if self.sweeping else []
        if wants_csv_header(sys.stdout):
            csv.writer(sys.stdout, lineterminator="\n").writerow(["unit", "answer", *where, "detail", "ms"])
        self.header_done = True

    def garbled(self, answer: Answer) -> None:
        where = f" at {answer.setting}" if answer.setting else ""
        self.note(f"unit {answer.unit}{where}: garbled: {answer.text}")

    def note(self, text: str) -> None:
        print(f"mbtool: {text}", file=sys.stderr, flush=True)

    def finish(self, tally: Tally, head: dict, title: str) -> None:
        if self.fmt == "json":
            from mbtool.cli.render import to_json

            data = {
                **head,
                "units": [answer_dict(a) for a in tally.found],
                "garbled": [answer_dict(a) for a in tally.garbled],
                "probed": tally.probes,
                "silent": len(tally.silent),
                "gateway": tally.gateway,
                "interrupted": tally.interrupted,
            }
            if self.sweeping:
                data["settings"] = [
                    {
                        "baud": s.baud,
                        "parity": s.parity,
                        "bytesize": s.bytesize,
                        "stopbits": s.stopbits,
                        **({"error": s.error} if s.error else {}),
                    }
                    for s in tally.settings
                ]
            print(to_json(data), flush=True)
        elif self.fmt == "csv" and not self.header_done:
            self._csv_header()  # nothing found: still a CSV a reader can load
        elif self.fmt == "table" and (tally.found or tally.garbled):
            self._table(tally, title)

    def _table(self, tally: Tally, title: str) -> None:
        from rich.console import Console
        from rich.markup import escape
        from rich.table import Table

        table = Table()
        table.add_column("Unit", justify="right")
        table.add_column("Answer")
        if self.sweeping:
            table.add_column("Baud", justify="right")
            table.add_column("Parity")
        table.add_column("Detail")
        table.add_column("ms", justify="right")
        for answer in sorted(tally.found, key=lambda a: a.unit) + tally.garbled:
            where = [str(answer.setting.baud), answer.setting.parity] if answer.setting else []
            style = "dim" if answer.answer == "garbled" else None
            table.add_row(
                str(answer.unit),
                answer.answer,
                *where,
                escape(answer.text),
                "" if answer.ms is None else f"{answer.ms:g}",
                style=style,
            )
        console = Console()
        console.print(title, highlight=False)
        console.print(table)


# --- the command --------------------------------------------------------------------------


@_scan_options
@device_command("scan", short_help="Find the units that answer, and the bus settings.")
@click.option(
    "--function",
    "probe",
    type=Choice(PROBES),
    default="read-holding-registers",
    show_default=True,
    help="What each unit is asked. Any reply or exception means a device is there.",
)
@click.option(
    "--address", type=ADDRESS, default=0, show_default=True, help="Address the read probes start at."
)
@click.option(
    "--count", type=COUNT, default=1, show_default=True, help="How many items the read probes ask for."
)
@click.option(
    "--bauds",
    type=BaudList(),
    metavar="BAUDS",
    help=f"Sweep these baud rates (9600,19200 or common: {','.join(map(str, COMMON_BAUDS))}) instead of -b.",
)
@click.option(
    "--parities",
    type=ParityList(),
    metavar="PARITIES",
    help="Sweep these parities (N,E,O) instead of --parity.",
)
@click.option("--first", is_flag=True, help="Stop at the first unit that answers.")
def scan(connection, probe, address, count, bauds, parities, first):
    """Find the unit ids that answer on a bus, and optionally the serial settings.

    Probes each unit of --units once, with a short timeout (-t, 0.2 s by default).
    A reply or a Modbus exception means a device is there; silence means none is;
    frames that do not check out (CRC, framing) are reported as garbled: something
    answered, perhaps at other settings. --bauds and --parities sweep serial
    settings, one link per combination, to find how an unknown device is set up.

    \b
    Output: a table on a terminal (with a progress bar on stderr), one line
    "UNIT ANSWER [BAUD PARITY] DETAIL" per unit found in a pipe, or -o json / csv.
    Exit 0 if any unit answered, 3 if none did (5 if only garbled answers came),
    130 when interrupted (what was found is still printed).
    """
    ctx = click.get_current_context()
    units = _scan_units(ctx)
    if probe not in READS:
        for option in ("address", "count"):
            if ctx.get_parameter_source(option) is not click.core.ParameterSource.DEFAULT:
                raise RequestError(f"--{option} goes with the read probes, not --function {probe}")
    request = probe_request(probe, address, count)
    sweeping = bauds is not None or parities is not None
    if sweeping:
        _check_sweepable(connection.port)
    settings = [
        Setting(baud=baud, parity=parity, bytesize=connection.bytesize, stopbits=connection.stopbits)
        for baud in (bauds or (connection.baud,))
        for parity in (parities or (connection.parity,))
    ]
    if connection.dry_run:
        _dry_run(connection, request, units, settings, sweeping)
        return
    from mbtool.cli.render import default_format

    fmt = connection.output_format or default_format()
    output = Output(fmt, sweeping)
    started = time.monotonic()
    progress = Progress(len(units) * len(settings), sys.stderr.isatty() and not connection.hex)
    try:
        tally = Scan(connection, request, units, settings, sweeping, first, output).run(progress)
    finally:
        progress.stop()
    head = {"function": request.function_code, "name": request.name, "timeout": connection.timeout}
    title = f"[bold]Scan[/] {request.name} (FC {request.function_code:02d}) · {connection.port}"
    output.finish(tally, head, title)
    raise _summary(tally, time.monotonic() - started, connection.timeout, sweeping)


def _check_sweepable(port: str | None) -> None:
    scheme = port.split("://", 1)[0].lower() if port and "://" in port else ""
    if scheme in ("tcp", "sim", "socket"):
        why = {
            "tcp": "Modbus TCP has no serial settings",
            "sim": "the built-in device has no serial line",
            "socket": "a raw TCP bridge sets them on the bridge (rfc2217:// sets them remotely)",
        }[scheme]
        raise RequestError(f"--bauds/--parities sweep serial settings, and {why}")


def _dry_run(connection, request, units: list[int], settings: list[Setting], sweeping: bool) -> None:
    from mbtool.cli.session import open_client

    then = f"then the same probe to units {units_text(frozenset(units))} ({len(units)} probes"
    then += f" at each of {len(settings)} serial settings)" if sweeping else ")"
    with open_client(replace(connection, unit=units[0]), request.name, then=then) as client:
        client.execute(units[0], request)


def _summary(tally: Tally, seconds: float, timeout: float, sweeping: bool) -> Summary:
    """One stderr line with the counts (like polling's), and the exit code the scan earned."""
    found = len(tally.found)
    text = (
        f"probes {tally.probes}, answered {found}, garbled {len(tally.garbled)}, silent {len(tally.silent)}"
    )
    if tally.gateway:
        text += f", unreachable behind the gateway {tally.gateway}"
    if sweeping:
        opened = sum(1 for setting in tally.settings if not setting.error)
        text += f", settings opened {opened} of {len(tally.settings)}"
    text += f", {seconds:.1f} s"
    if tally.interrupted:
        return Summary("interrupted; " + text, ExitCode.INTERRUPTED)
    if found:
        return Summary("scan: " + text, ExitCode.OK)
    if tally.garbled:
        # Something is on the line but nothing checked out: the settings are the suspects.
        return Summary(
            f"no unit answered cleanly ({text}): try other --baud/--parity/--framer",
            ExitCode.INVALID_RESPONSE,
        )
    if tally.settings and all(setting.error for setting in tally.settings):
        return Summary(f"no setting could be opened ({text})", ExitCode.CONNECTION)
    return Summary(f"no unit answered within {timeout:g} s ({text})", ExitCode.TIMEOUT)
