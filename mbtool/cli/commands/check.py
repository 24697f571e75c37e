"""``mbtool check``: a monitoring plugin for Nagios, Icinga and their kin, by the
Monitoring Plugins development guidelines.

One line on stdout, ``MODBUS STATE - text | perfdata``, and the exit code of the
state: 0 OK, 1 WARNING, 2 CRITICAL, 3 UNKNOWN.  Thresholds are the guidelines'
ranges (``10``, ``10:``, ``~:10``, ``10:20``, ``@10:20``): an alert when the value
lies outside the range (inside, with ``@``).  The grammar is nagiosplugin's.

Every outcome is a state and that one line (``PluginCommand``), as the plugin API asks.
Anything that keeps the check from judging is UNKNOWN with the reason: bad arguments, a
profile or config file that cannot be used, an output format check does not write, a
signal (SIGTERM, SIGHUP, SIGINT), a bug.  A device that does not answer, refuses or
garbles, a point it refuses and a value that reads NaN are UNKNOWN unless
``--state-on-error`` says otherwise; perfdata has U for a value that is not a finite
number.  The worst state wins, UNKNOWN above CRITICAL (nagiosplugin's order).  Only a
stdout that cannot be written (full, closed, its reader gone) leaves no line: the reason
goes to stderr, and the state is UNKNOWN.
"""

from __future__ import annotations

import math
import os
import signal
import sys
from functools import partial

import click

from mbtool.cli.options import VALUE_TYPES, device_command, map_option, reference_target, type_options_given
from mbtool.cli.param_types import Choice
from mbtool.cli.parsing import DeviceCommand
from mbtool.cli.program import discard_stdout
from mbtool.cli.session import execute, open_client
from mbtool.codec.tables import READS, reference
from mbtool.codec.values import decode_values, registers_needed, value_addresses
from mbtool.errors import KNOWN_ERRORS, ExitCode, PartialRead, UsageError, exit_code_for, link_failure

STATES = ("OK", "WARNING", "CRITICAL", "UNKNOWN")  # by exit code
UNKNOWN = 3
ERROR_STATES = {"unknown": 3, "warning": 1, "critical": 2}  # --state-on-error
# Units of measure perfdata may carry (guidelines, "Performance data"); others are
# shown in the text only, as a graphing tool would misread them.
PERFDATA_UNITS = {"s", "ms", "us", "%", "B", "KB", "MB", "TB", "c"}
STOPPING = (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)  # what a scheduler or a terminal sends


def plugin_exit(state: int, text: str, perfdata: str = "") -> None:
    """The plugin's one line, and its exit code.  ``|`` separates the perfdata and is
    dropped anywhere else (nagiosplugin's rule); a control character would break the line."""
    for stop in STOPPING:  # the verdict is in: a signal now must not cut the line short
        signal.signal(stop, signal.SIG_IGN)
    line = f"MODBUS {STATES[state]} - {_one_line(text)}" + (f" | {_one_line(perfdata)}" if perfdata else "")
    try:
        sys.stdout.write(line + "\n")
        sys.stdout.flush()
    except OSError as error:  # a full disk, a closed stdout or its reader gone: no line can go
        discard_stdout()
        reason = error.strerror or error
        print(f"mbtool: cannot write the plugin's line to standard output: {reason}", file=sys.stderr)
        state = UNKNOWN
    raise click.exceptions.Exit(state)


def _one_line(text: str) -> str:
    """No | (it starts the perfdata) and no control character (it would end the line)."""
    return "".join(char if char.isprintable() else " " for char in text.replace("|", ""))


def _stopped(signum, frame):
    raise KeyboardInterrupt(signal.Signals(signum).name)


class PluginCommand(DeviceCommand):
    """check's command: whatever happens, from parsing its arguments on, ends in
    ``plugin_exit`` (one line, a state 0-3), never in cli.main's exit codes."""

    def make_context(self, info_name, args, parent=None, **extra):
        for stop in STOPPING:
            signal.signal(stop, _stopped)
        try:
            return super().make_context(info_name, args, parent, **extra)
        except click.exceptions.Exit:
            raise  # --help
        except click.ClickException as failure:  # bad arguments
            plugin_exit(UNKNOWN, failure.format_message())
        except KeyboardInterrupt as stop:
            plugin_exit(UNKNOWN, _interrupted(stop))

    def invoke(self, ctx):
        try:
            return super().invoke(ctx)
        except click.exceptions.Exit:
            raise  # the plugin's line is out
        except click.ClickException as failure:
            plugin_exit(UNKNOWN, failure.format_message())
        except KeyboardInterrupt as stop:
            plugin_exit(UNKNOWN, _interrupted(stop))
        except (*KNOWN_ERRORS, OSError) as error:
            error = link_failure(error)
            code = exit_code_for(error)
            if code == ExitCode.OK:
                raise  # --dry-run has shown the frame
            if code == ExitCode.USAGE:  # bad arguments, a bad map, profile or range: nothing was sent
                plugin_exit(UNKNOWN, str(error))
            plugin_exit(ERROR_STATES[ctx.params["state_on_error"]], str(error))
        except Exception as failure:  # a bug: still a state; MBTOOL_DEBUG=1 shows the traceback
            if os.environ.get("MBTOOL_DEBUG", "0") not in ("", "0"):
                raise
            plugin_exit(UNKNOWN, f"internal error: {type(failure).__name__}: {failure}")


def _interrupted(stop: KeyboardInterrupt) -> str:
    return f"interrupted by {stop.args[0] if stop.args else 'SIGINT'}"  # Ctrl-C raises it bare


RANGE_FORMS = "ranges are 10, 10:, ~:10, 10:20 or @10:20"


def _range(text: str | None, what: str, typed: bool = False):
    """A threshold range, [@][START:][END] as nagiosplugin reads it; a bad one is a
    UsageError in the check's own words.  ``typed``: from the command line, where an
    unquoted ~:10 arrives as the home directory (the shell expands the ~)."""
    import nagiosplugin  # noqa: PLC0415 - nagiosplugin, 12 ms: not for mbtool --help

    if text is None or text == "":
        return None
    at = "@" if text.startswith("@") else ""
    body = text.removeprefix("@")
    home = os.path.expanduser("~")
    if typed and home != "~" and body.startswith(home + ":"):
        meant = f"{at}~:{body[len(home) + 1 :]}"
        raise UsageError(
            f"{what} {text} is not a range: the shell made {meant} into your home directory; "
            f"quote it: {what} '{meant}'"
        )
    why = _range_fault(body)
    if why:
        raise UsageError(f"{what} {text} is not a range: {why}; {RANGE_FORMS}")
    return nagiosplugin.Range(text)


def _range_fault(body: str) -> str:
    """Why a range (after its @) is none in nagiosplugin's grammar, or "" when it is one."""
    if body.count(":") > 1:
        return "it has more than one ':'"
    start_text, _, end_text = body.rpartition(":")
    if end_text == "~":
        return "~ is not a number (~ is for the start: ~:10)"
    start = float("-inf") if start_text == "~" else _range_number(start_text, 0)
    end = _range_number(end_text, float("inf"))
    if start is None or end is None:
        return f"{start_text if start is None else end_text} is not a number"
    if start > end:
        return f"its start {start_text} is above its end {end_text}"
    return ""


def _range_number(atom: str, default: float) -> float | None:
    """A range's end as nagiosplugin reads it (int, or float with a '.'); None if it is none."""
    if atom == "":
        return default
    try:
        return float(atom) if "." in atom else int(atom)
    except ValueError:
        return None


def _violation(limit) -> str:
    """Why a value alerts, with both ends spelled out (10 means 0:10)."""

    def end(value: float, infinite: str) -> str:
        if value in (float("inf"), float("-inf")):
            return infinite
        return str(int(value)) if value == int(value) else str(value)

    bounds = f"{end(limit.start, '~')}:{end(limit.end, '')}"
    return f"inside {bounds}" if limit.invert else f"outside {bounds}"


def _label(name: str) -> str:
    # A perfdata label may hold anything but = and ' (guidelines); | ends the text, so it goes.
    return name.replace("=", "_").replace("'", "_").replace("|", "")


class Checked:
    """One value judged: its name, number, text for people, unit and thresholds.  A number
    of None is a point the device refused (``text`` says why); it and NaN cannot be judged:
    their state is ``unjudged`` (--state-on-error's)."""

    def __init__(self, name: str, number, text: str, unit: str, warn, crit, unjudged: int = UNKNOWN) -> None:
        self.name, self.number, self.text, self.unit = name, number, text, unit
        self.warn, self.crit, self.unjudged = warn, crit, unjudged

    @property
    def judged(self) -> bool:
        # A device reads NaN for "no valid measurement" (a sensor fault): every comparison
        # with NaN is false, so a range would let it pass as OK.  ±Infinity is judged.
        return self.number is not None and not math.isnan(self.number)

    @property
    def state(self) -> int:
        if not self.judged:
            return self.unjudged
        if self.crit is not None and not self.crit.match(self.number):
            return 2
        if self.warn is not None and not self.warn.match(self.number):
            return 1
        return 0

    def summary(self) -> str:
        state = self.state
        if self.number is None:
            return f"{self.name} not read ({STATES[state]}: {self.text})"
        shown = f"{self.name}={self.text}" + (f" {self.unit}" if self.unit else "")
        if not self.judged:
            shown += f" ({STATES[state]}: not a number, nothing to judge)"
        elif state:
            limit = self.crit if state == 2 else self.warn
            shown += f" ({STATES[state]}: {_violation(limit)})"
        return shown

    def perfdata(self) -> str:
        import nagiosplugin  # noqa: PLC0415 - nagiosplugin, 12 ms: not for mbtool --help

        unit = self.unit if self.unit in PERFDATA_UNITS and self.number is not None else ""
        warn, crit = self.warn or "", self.crit or ""
        return str(nagiosplugin.Performance(_label(self.name), _perf_value(self.number), unit, warn, crit))


def _perf_value(number: float) -> str:
    """A perfdata value in the guidelines' characters, [-0-9.]: no exponent, and a whole
    float without its .0 (a scaled point's 10.0 is 10); U, their "could not be determined",
    for NaN and the infinities."""
    if number is None or isinstance(number, float) and not math.isfinite(number):
        return "U"
    if not isinstance(number, float):
        return str(number)
    from decimal import Decimal  # noqa: PLC0415 - 1 ms: a float's perfdata only

    return format(Decimal(repr(number)).normalize(), "f")


def _number(value, what: str) -> float:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int | float):
        return value
    raise UsageError(f"{what} reads {value}, not a number to check")


def _reference_values(
    connection, settings, targets, given, value_type, order, warn, crit, unjudged
) -> list[Checked]:
    table, address, count = reference_target(targets, "check", given)
    if table.bits:
        reply = execute(connection, settings, READS[table.name](address, count))
        values = list(reply.bits[:count])
        addresses = list(range(address, address + count))
    else:
        reply = execute(connection, settings, READS[table.name](address, registers_needed(value_type, count)))
        values = decode_values(reply.registers, value_type, order)
        addresses = value_addresses(value_type, address, len(reply.registers))
    out = []
    for item_address, value in zip(addresses, values, strict=True):
        name = reference(table, item_address)
        number = _number(value, name)
        text = str(int(number) if isinstance(value, bool) else value)
        out.append(Checked(name, number, text, "", warn, crit, unjudged))
    return out


def _map_values(connection, settings, path, names, warn, crit, unjudged) -> list[Checked]:
    from mbtool.library import load_named_map  # noqa: PLC0415 - the map loader, 4-8 ms: -m only
    from mbtool.registermap.plan import MapReader  # noqa: PLC0415 - with decimal, 2 ms: -m only

    register_map = load_named_map(path)
    points = register_map.select(names)
    # Every threshold is read before anything is sent: a bad one is bad arguments.
    limits = {
        point.name: (
            warn or _range(point.warn, f"{point.name}: warn"),
            crit or _range(point.crit, f"{point.name}: crit"),
        )
        for point in points
    }
    reader = MapReader(points, register_map.max_gap)
    with open_client(connection, settings, reader.blocks[0].request.name) as client:
        try:
            readings = reader.read(partial(client.execute, connection.unit))
        except PartialRead as partial_read:  # the points read are judged; the others are unread
            readings = partial_read.readings
    out = []
    for reading in readings:
        point, value = reading.point, reading.value
        if reading.error is not None:
            out.append(
                Checked(point.name, None, reading.error.answer, point.unit, *limits[point.name], unjudged)
            )
            continue
        if value is None:  # a raw value the map's invalid key names: nothing to judge
            out.append(
                Checked(point.name, None, "no data (invalid)", point.unit, *limits[point.name], unjudged)
            )
            continue
        number = point.number_of(value)  # an enum by the raw number behind its label
        if number is None:
            raise UsageError(f"{point.name} reads {value}, not a number to check")
        text = ("on" if value else "off") if isinstance(value, bool) else str(value)
        out.append(Checked(point.name, number, text, point.unit, *limits[point.name], unjudged))
    return out


@device_command("check", types=VALUE_TYPES, output=False, cls=PluginCommand)
@click.argument("targets", nargs=-1, metavar="REF [COUNT] | NAME...")
@map_option("points by name, with their warn and crit keys")
@click.option("-w", "--warning", metavar="RANGE", help="Warning range (beats a map's warn).")
@click.option("-c", "--critical", metavar="RANGE", help="Critical range (beats a map's crit).")
@click.option(
    "--state-on-error",
    type=Choice(list(ERROR_STATES)),
    default="unknown",
    show_default=True,
    help="The state when the device cannot be read (no response, exception, bad reply), a point "
    "of a map is refused or a value reads NaN, which no range can judge.",
)
def check(connection, settings, targets, map, warning, critical, state_on_error, value_type, order):
    """A monitoring plugin (Nagios, Icinga): judge values against thresholds.

    Reads a reference (check 40011 -w 10 -c 20) or a map's points (check -m pump.toml
    flow level), and prints one line, MODBUS OK - flow=21.5 m3/h | flow=21.5;10;20,
    with exit 0 OK, 1 WARNING, 2 CRITICAL, 3 UNKNOWN, whatever happens. Ranges as the
    Monitoring Plugins guidelines write them: 10 (alert outside 0..10), 10: (below 10),
    ~:10 (above 10), 10:20 (outside), @10:20 (inside). Bad arguments, profiles and
    config files are UNKNOWN, and so is a signal; a device that cannot be read, a point
    it refuses and a value that reads NaN (perfdata U) are UNKNOWN unless
    --state-on-error says otherwise. The worst state wins, UNKNOWN above CRITICAL.
    """
    unjudged = ERROR_STATES[state_on_error]
    given = type_options_given(map)
    warn, crit = _range(warning, "-w", typed=True), _range(critical, "-c", typed=True)
    if not map and not targets:
        raise UsageError("give a reference such as 40011, or -m MAP and point names")
    if map:
        values = _map_values(connection, settings, map, targets, warn, crit, unjudged)
    else:
        values = _reference_values(
            connection, settings, targets, given, value_type, order, warn, crit, unjudged
        )
    plugin_exit(
        max(value.state for value in values),
        ", ".join(value.summary() for value in values),
        " ".join(value.perfdata() for value in values),
    )
