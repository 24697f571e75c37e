"""``mbtool check``: a monitoring plugin for Nagios, Icinga and their kin, by the
Monitoring Plugins development guidelines.

One line on stdout, ``MODBUS STATE - text | perfdata``, and the exit code of the
state: 0 OK, 1 WARNING, 2 CRITICAL, 3 UNKNOWN.  Thresholds are the guidelines'
ranges (``10``, ``10:``, ``~:10``, ``10:20``, ``@10:20``): an alert when the value
lies outside the range (inside, with ``@``).  The grammar is nagiosplugin's.
Anything that keeps the check from judging the value is UNKNOWN with the reason:
bad arguments always, a device that does not answer, refuses or garbles unless
``--state-on-error`` says otherwise.
"""

from __future__ import annotations

from functools import partial

import click

from mbtool.cli.options import (
    VALUE_TYPES,
    Choice,
    device_command,
    map_option,
    reference_target,
    type_options_given,
)
from mbtool.codec.errors import RequestError

STATES = ("OK", "WARNING", "CRITICAL", "UNKNOWN")  # by exit code
# Units of measure perfdata may carry (guidelines, "Performance data"); others are
# shown in the text only, as a graphing tool would misread them.
PERFDATA_UNITS = {"s", "ms", "us", "%", "B", "KB", "MB", "TB", "c"}


def plugin_output(state: int, text: str, perfdata: str = "") -> None:
    """The plugin's one line, and its exit code."""
    click.echo(f"MODBUS {STATES[state]} - {text}" + (f" | {perfdata}" if perfdata else ""))
    raise click.exceptions.Exit(state)


RANGE_FORMS = "ranges are 10, 10:, ~:10, 10:20 or @10:20"


def _range(text: str | None, what: str, typed: bool = False):
    """A threshold range, [@][START:][END] as nagiosplugin reads it; a bad one is a
    RequestError in the check's own words.  ``typed``: from the command line, where an
    unquoted ~:10 arrives as the home directory (the shell expands the ~)."""
    import os

    import nagiosplugin

    if text is None or text == "":
        return None
    at = "@" if text.startswith("@") else ""
    body = text.removeprefix("@")
    home = os.path.expanduser("~")
    if typed and home != "~" and body.startswith(home + ":"):
        meant = f"{at}~:{body[len(home) + 1 :]}"
        raise RequestError(
            f"{what} {text} is not a range: the shell made {meant} into your home directory; "
            f"quote it: {what} '{meant}'"
        )
    why = _range_fault(body)
    if why:
        raise RequestError(f"{what} {text} is not a range: {why}; {RANGE_FORMS}")
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
    for number, atom in ((start, start_text), (end, end_text)):
        if number is None:
            return f"{atom} is not a number"
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
    # A perfdata label may hold anything but = and ' (guidelines).
    return name.replace("=", "_").replace("'", "_")


class Checked:
    """One value judged: its name, number, text for people, unit and thresholds."""

    def __init__(self, name: str, number: float, text: str, unit: str, warn, crit) -> None:
        self.name, self.number, self.text, self.unit = name, number, text, unit
        self.warn, self.crit = warn, crit

    @property
    def state(self) -> int:
        if self.crit is not None and not self.crit.match(self.number):
            return 2
        if self.warn is not None and not self.warn.match(self.number):
            return 1
        return 0

    def summary(self) -> str:
        shown = f"{self.name}={self.text}" + (f" {self.unit}" if self.unit else "")
        state = self.state
        if state:
            limit = self.crit if state == 2 else self.warn
            shown += f" ({STATES[state]}: {_violation(limit)})"
        return shown

    def perfdata(self) -> str:
        import nagiosplugin

        unit = self.unit if self.unit in PERFDATA_UNITS else ""
        warn, crit = self.warn or "", self.crit or ""
        return str(nagiosplugin.Performance(_label(self.name), self.number, unit, warn, crit))


def _number(value, what: str) -> float:
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int | float):
        return value
    raise RequestError(f"{what} reads {value}, not a number to check")


def _reference_values(connection, targets, given, value_type, order, warn, crit) -> list[Checked]:
    from mbtool.cli.session import execute
    from mbtool.codec.tables import READS, reference
    from mbtool.codec.values import decode_values, registers_needed, value_addresses

    table, address, count = reference_target(targets, "check", given)
    if table.bits:
        reply = execute(connection, READS[table.name](address, count))
        values = list(reply.bits[:count])
        addresses = list(range(address, address + count))
    else:
        reply = execute(connection, READS[table.name](address, registers_needed(value_type, count)))
        values = decode_values(reply.registers, value_type, order)
        addresses = value_addresses(value_type, address, len(reply.registers))
    out = []
    for item_address, value in zip(addresses, values, strict=True):
        name = reference(table, item_address)
        number = _number(value, name)
        out.append(
            Checked(name, number, str(int(number) if isinstance(value, bool) else value), "", warn, crit)
        )
    return out


def _map_values(connection, path, names, warn, crit) -> list[Checked]:
    from mbtool.cli.session import open_client
    from mbtool.registermap.load import load_map
    from mbtool.registermap.plan import plan_reads, read_points

    register_map = load_map(path)
    points = register_map.select(names)
    # Every threshold is read before anything is sent: a bad one is bad arguments.
    limits = {
        point.name: (
            warn or _range(point.warn, f"{point.name}: warn"),
            crit or _range(point.crit, f"{point.name}: crit"),
        )
        for point in points
    }
    first = plan_reads(points, register_map.max_gap)[0].request()
    with open_client(connection, first.name) as client:
        readings = read_points(partial(client.execute, connection.unit), points, register_map.max_gap)
    out = []
    for reading in readings:
        point, value = reading.point, reading.value
        number = point.number_of(value)  # an enum by the raw number behind its label
        if number is None:
            raise RequestError(f"{point.name} reads {value}, not a number to check")
        text = ("on" if value else "off") if isinstance(value, bool) else str(value)
        out.append(Checked(point.name, number, text, point.unit, *limits[point.name]))
    return out


@device_command("check", types=VALUE_TYPES, output=False)
@click.argument("targets", nargs=-1, metavar="REF [COUNT] | NAME...")
@map_option("points by name, with their warn and crit keys")
@click.option("-w", "--warning", metavar="RANGE", help="Warning range (beats a map's warn).")
@click.option("-c", "--critical", metavar="RANGE", help="Critical range (beats a map's crit).")
@click.option(
    "--state-on-error",
    type=Choice(["unknown", "warning", "critical"]),
    default="unknown",
    show_default=True,
    help="The state when the device cannot be read (no response, exception, bad reply).",
)
def check(connection, targets, map, warning, critical, state_on_error, value_type, order):
    """A monitoring plugin (Nagios, Icinga): judge values against thresholds.

    Reads a reference (check 40011 -w 10 -c 20) or a map's points (check -m pump.toml
    flow level), and prints one line, MODBUS OK - flow=21.5 m3/h | flow=21.5;10;20,
    with exit 0 OK, 1 WARNING, 2 CRITICAL, 3 UNKNOWN. Ranges as the Monitoring Plugins
    guidelines write them: 10 (alert outside 0..10), 10: (below 10), ~:10 (above 10),
    10:20 (outside), @10:20 (inside). Bad arguments are UNKNOWN; so is a device that
    cannot be read, unless --state-on-error says otherwise.
    """
    from mbtool.errors import KNOWN_ERRORS, ConnectionFailed, ExitCode, exit_code_for

    try:
        given = type_options_given(map)
        warn, crit = _range(warning, "-w", typed=True), _range(critical, "-c", typed=True)
        if not map and not targets:
            raise RequestError("give a reference such as 40011, or -m MAP and point names")
        if map:
            values = _map_values(connection, map, targets, warn, crit)
        else:
            values = _reference_values(connection, targets, given, value_type, order, warn, crit)
    except (*KNOWN_ERRORS, OSError) as error:
        if isinstance(error, OSError):
            error = ConnectionFailed(str(error))
        code = exit_code_for(error)
        if code == ExitCode.OK:
            raise  # --dry-run has shown the frame
        if code == ExitCode.USAGE:  # bad arguments, a bad map or range: nothing was sent
            plugin_output(3, str(error))
        plugin_output({"unknown": 3, "warning": 1, "critical": 2}[state_on_error], str(error))
    state = max(value.state for value in values)
    plugin_output(
        state,
        ", ".join(value.summary() for value in values),
        " ".join(value.perfdata() for value in values),
    )
