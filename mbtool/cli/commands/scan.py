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

import copy
import sys
import time

import click

from mbtool.cli.options import device_command
from mbtool.cli.param_types import ADDRESS, COUNT, Choice, parse_units, units_text
from mbtool.cli.results import Listing
from mbtool.cli.session import open_client, trace_for
from mbtool.cli.sinks import default_format, sink
from mbtool.cli.sinks.table import ScanProgress, scan_answers
from mbtool.codec.errors import function_code_text
from mbtool.codec.record import replace
from mbtool.errors import ExitCode, UsageError, Verdict
from mbtool.link.scan import PROBES, READS, Answer, Scan, Setting, Tally, probe_request
from mbtool.words import counted

SCAN_TIMEOUT = 0.2  # seconds per unit: a reply at 1200 baud plus a slow device's turnaround
DEFAULT_UNITS = "1-247"  # spec §2: 1..247 are the individual addresses, 248..255 reserved
COMMON_BAUDS = (9600, 19200, 38400, 115200, 57600, 4800, 2400, 1200)  # the likeliest first


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
        except UsageError as error:
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
            # A copy: the shared option is every other command's too (options.shared_option).
            timeout = copy.copy(param)
            timeout.default = SCAN_TIMEOUT
            timeout.help = "Seconds to wait for each unit's reply (raise it for slow devices or gateways)."
            command.params[index] = timeout
    return command


def _scan_units(ctx: click.Context) -> list[int]:
    # From the command line or the default, never from a profile's single unit.
    return sorted(ctx.params["unit"])


# --- output -------------------------------------------------------------------------------


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
    or all at the end (table, json): the rows of the format's sink."""

    def __init__(self, fmt: str, sweeping: bool, csv_header: bool = True) -> None:
        self.sweeping = sweeping
        where = ["baud", "parity"] if sweeping else []
        self.rows = sink(fmt).Rows(sys.stdout, ["unit", "answer", *where, "detail", "ms"], csv_header)

    def found(self, answer: Answer) -> None:
        where = [str(answer.setting.baud), answer.setting.parity] if answer.setting else []
        self.rows.row(
            [answer.unit, answer.answer, *where, answer.text, "" if answer.ms is None else answer.ms],
            " ".join([str(answer.unit), answer.answer, *where, answer.text]),
        )

    def garbled(self, answer: Answer) -> None:
        where = f" at {answer.setting}" if answer.setting else ""
        self.note(f"unit {answer.unit}{where}: garbled: {answer.text}")

    def note(self, text: str) -> None:
        print(f"mbtool: {text}", file=sys.stderr, flush=True)

    def finish(self, tally: Tally, head: dict, title: str) -> None:
        def data() -> dict:
            data = {
                **head,
                "units": [answer_dict(a) for a in tally.found],
                "garbled": [answer_dict(a) for a in tally.garbled],
                "probed": tally.probes,
                "silent": len(tally.silent),
                "gateway": tally.gateway,
                "interrupted": tally.interrupted,
                "transactions": tally.transactions.as_dict(),
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
            return data

        def draw() -> None:
            if tally.found or tally.garbled:
                scan_answers(sorted(tally.found, key=lambda a: a.unit) + tally.garbled, self.sweeping, title)

        self.rows.end(Listing(data=data, table=None, lines=list, draw=draw))


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
def scan(connection, settings, probe, address, count, bauds, parities, first):
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
                raise UsageError(f"--{option} goes with the read probes, not --function {probe}")
    request = probe_request(probe, address, count)
    sweeping = bauds is not None or parities is not None
    if sweeping:
        _check_sweepable(connection.port)
    lines = [
        Setting(
            baud=baud, parity=parity, bytesize=connection.serial.bytesize, stopbits=connection.serial.stopbits
        )
        for baud in (bauds or (connection.serial.baud,))
        for parity in (parities or (connection.serial.parity,))
    ]
    if settings.dry_run:
        _dry_run(connection, settings, request, units, lines, sweeping)
        return

    fmt = settings.output_format or default_format()
    output = Output(fmt, sweeping, settings.csv_header)
    started = time.monotonic()
    progress = ScanProgress(len(units) * len(lines), sys.stderr.isatty() and not settings.hex)
    try:
        tally = Scan(connection, request, units, lines, sweeping, first, output, trace_for(settings)).run(
            progress
        )
    finally:
        progress.stop()
    head = {"function": request.function_code, "name": request.name, "timeout": connection.timeout}
    title = f"[bold]Scan[/] {request.name} · {function_code_text(request.function_code)} · {connection.port}"
    output.finish(tally, head, title)
    return _summary(tally, time.monotonic() - started, connection.timeout, sweeping)


def _check_sweepable(port: str | None) -> None:
    scheme = port.split("://", 1)[0].lower() if port and "://" in port else ""
    if scheme in ("tcp", "sim", "socket"):
        why = {
            "tcp": "Modbus TCP has no serial settings",
            "sim": "the built-in device has no serial line",
            "socket": "a raw TCP bridge sets them on the bridge (rfc2217:// sets them remotely)",
        }[scheme]
        raise UsageError(f"--bauds/--parities sweep serial settings, and {why}")


def _dry_run(connection, settings, request, units: list[int], lines: list[Setting], sweeping: bool) -> None:
    then = f"then the same probe to units {units_text(frozenset(units))} ({counted(len(units), 'probe')}"
    then += f" at each of {counted(len(lines), 'serial setting')})" if sweeping else ")"
    with open_client(replace(connection, unit=units[0]), settings, request.name, then=then) as client:
        client.execute(units[0], request)


def _summary(tally: Tally, seconds: float, timeout: float, sweeping: bool) -> Verdict:
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
    text += f", {seconds:.1f} s; {tally.transactions}"
    if tally.interrupted:
        return Verdict("interrupted; " + text, ExitCode.INTERRUPTED)
    if found:
        return Verdict("scan: " + text, ExitCode.OK)
    if tally.garbled:
        # Something is on the line but nothing checked out: the settings are the suspects.
        return Verdict(
            f"no unit answered cleanly ({text}): try other --baud/--parity/--framer",
            ExitCode.INVALID_RESPONSE,
        )
    if tally.settings and all(setting.error for setting in tally.settings):
        return Verdict(f"no setting could be opened ({text})", ExitCode.CONNECTION)
    return Verdict(f"no unit answered within {timeout:g} s ({text})", ExitCode.TIMEOUT)
