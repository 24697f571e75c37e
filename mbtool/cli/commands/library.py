"""The device library (issue 43): ``mbtool maps list`` and ``mbtool maps show`` (the maps
mbtool ships, mbtool/library/), and ``mbtool identify`` (which of them a device is)."""

from __future__ import annotations

import sys
import time
from functools import partial
from pathlib import Path

import click

from mbtool.cli.options import device_command
from mbtool.cli.param_types import FilePath, Seconds, parse_units, units_text
from mbtool.cli.parsing import QuickHelp
from mbtool.cli.results import Listing
from mbtool.cli.session import open_client, trace_for
from mbtool.cli.sinks import render
from mbtool.cli.sinks.json import to_json
from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.codec.errors import FrameError, ModbusException, exception_name
from mbtool.codec.pdu import printable, text_of
from mbtool.codec.record import replace
from mbtool.codec.tables import HOLDING_REGISTERS, reference
from mbtool.codec.values import decode_values
from mbtool.errors import NoResponse, OutputFailed, UsageError
from mbtool.library import MAPS, library_names, load_named_map, resolve_map, signatures
from mbtool.words import counted

HELP = {"help_option_names": ["-h", "--help"]}


class MapsGroup(QuickHelp, click.Group):
    pass


class MapsCommand(QuickHelp, click.Command):
    pass


@click.group("maps", cls=MapsGroup, context_settings=HELP)
def maps() -> None:
    """The register maps mbtool ships: -m NAME reads a device by one of them.

    A map of your own in $XDG_CONFIG_HOME/mbtool/maps (or a poll inventory's folder, or the
    exporter's --maps DIR) named like one of these comes first. docs/maps-library.md says how
    to add a device."""


COLUMNS = ("name", "manufacturer", "model", "kind", "transport", "source")


@maps.command("list", cls=MapsCommand, context_settings=HELP)
@click.argument("text", required=False)
@click.option("--json", "as_json", is_flag=True, help="One JSON object a map, in a list.")
def list_maps(text, as_json) -> None:
    """The library's maps: name, manufacturer, model, kind, transport and source manual.

    TEXT keeps those whose name, manufacturer, model or kind contain it (any case)."""
    rows = []
    for name in library_names():
        header = load_named_map(str(MAPS / f"{name}.toml")).header
        row = {
            "name": name,
            "manufacturer": header.manufacturer if header else "",
            "model": header.model if header else "",
            "kind": header.kind if header else "",
            "transport": header.transport if header else "",
            "source": header.source if header else "",
        }
        searched = " ".join((row["name"], row["manufacturer"], row["model"], row["kind"])).lower()
        if text is None or text.lower() in searched:
            rows.append(row)
    if as_json:
        click.echo(to_json(rows))
        return
    if not rows:
        raise click.UsageError(f"no map of the library matches {text!r} (mbtool maps list shows them all)")
    _columns([[row[key] for key in COLUMNS] for row in rows], [key.upper() for key in COLUMNS])


@maps.command("show", cls=MapsCommand, context_settings=HELP)
@click.argument("name")
@click.option("--toml", "as_toml", is_flag=True, help="The map's file as it is.")
def show_map(name, as_toml) -> None:
    """A map's device and points: NAME is a library map's name (or a map file), found as -m finds it."""
    path = resolve_map(name)
    register_map = load_named_map(name)
    if as_toml:
        click.echo(path.read_text(encoding="utf-8"), nl=False)
        return
    header = register_map.header
    if header is not None:
        click.echo(f"{header.manufacturer} {header.model} ({header.kind}, {header.transport}): {path}")
        serial = ", ".join(f"{key} {value}" for key, value in header.serial().items())
        if header.default_unit is not None or serial:
            click.echo(f"unit {header.default_unit or '?'}" + (f", {serial}" if serial else ""))
        click.echo(f"source: {header.source}")
        for probe in header.signature:
            click.echo(f"signature: {probe.describe()}")
        click.echo("")
    rows = [
        [
            point.name,
            point.ref,
            point.type if point.bit is None else f"bit {point.bit}",
            point.order if point.size > 1 and point.type != "string" else "",
            "" if point.scale is None else str(point.scale),
            point.unit,
            "rw" if point.writable else "r",
            point.description,
        ]
        for point in register_map.points.values()
    ]
    _columns(rows, ["NAME", "REF", "TYPE", "ORDER", "SCALE", "UNIT", "ACCESS", "DESCRIPTION"])


def _columns(rows: list[list[str]], titles: list[str]) -> None:
    """Rows in aligned columns, the last one left as long as it is."""
    table = [titles, *rows]
    widths = [max(len(row[i]) for row in table) for i in range(len(titles) - 1)]
    for row in table:
        cells = [cell.ljust(width) for cell, width in zip(row, widths, strict=False)]
        click.echo("  ".join([*cells, row[-1]]).rstrip())


# --- identify ----------------------------------------------------------------------------

IDENTIFY_THEN = "identify's further reads (FC 17, SunSpec, the maps' signatures) follow the replies"


@device_command("identify")
@click.option(
    "--budget",
    type=Seconds(),
    default=10.0,
    show_default=True,
    help="Seconds identify may take a unit: the signatures not read by then are left out, and said to be.",
)
@click.option(
    "--all-units",
    is_flag=True,
    help="Walk the bus: find the units that answer (as scan does, over --units) and identify each.",
)
@click.option(
    "--units",
    "unit_set",
    metavar="UNITS",
    default="1-247",
    show_default=True,
    help="With --all-units: the unit ids to look for, 1-247, 1,5,10-20.",
)
@click.option(
    "--inventory",
    "inventory_path",
    metavar="PLANT.toml",
    type=FilePath(dir_okay=False),
    help="With --all-units: write a poll inventory of the bus, each device with its map.",
)
def identify(connection, settings, budget, all_units, unit_set, inventory_path):
    """Which device this is, and its map: mbtool read -m NAME reads it.

    Asks the device what it says of itself (FC 43/14 device identification, basic and
    regular objects; FC 17 report server id; the SunSpec marker), then reads the signature
    of each library map (and each of your own maps with one): a few registers with an
    expected shape. Prints the maps that fit, best first, with the evidence; "unknown
    device", with what it saw, when none does. Reads only: nothing is ever written.
    """
    ctx = click.get_current_context()
    given = [
        option
        for name, option in (("unit_set", "--units"), ("inventory_path", "--inventory"))
        if ctx.get_parameter_source(name) is not click.core.ParameterSource.DEFAULT
    ]
    if given and not all_units:
        raise UsageError(f"{given[0]} goes with --all-units")
    headers = signatures()
    if not all_units:
        found = _identify_unit(connection, settings, headers, budget)
        _show_identity(connection.unit, settings, *found)
        return
    try:
        wanted = sorted(parse_units(unit_set))
    except UsageError as error:
        raise UsageError(f"--units: {error}") from None
    if settings.dry_run:  # the walk's reads depend on the replies: its first is all there is to show
        _dry_run_walk(connection, settings, wanted)
        return
    units = _answering_units(connection, settings, wanted)
    if not units:
        raise NoResponse(f"no unit of {units_text(frozenset(wanted))} answered on {connection.port}")
    results = []
    for unit in units:
        try:
            found = _identify_unit(replace(connection, unit=unit), settings, headers, budget)
        except NoResponse:  # it answered the scan: say so, and go on with the others
            found = ([], None, {"fc43": "no response"})
        results.append((unit, *found))
        _show_identity(unit, settings, *found)
    if inventory_path:
        _write_inventory(inventory_path, connection, results)


def _identify_unit(connection, settings, headers: dict, budget: float):
    """(the candidates ranked, the SunSpec device or None, what each step saw) of one unit."""
    from mbtool.codec.device_id import ReadDeviceIdentification  # noqa: PLC0415 - identify only
    from mbtool.library.identify import probe, rank  # noqa: PLC0415 - identify only

    deadline = time.monotonic() + budget
    with open_client(connection, settings, ReadDeviceIdentification.name, then=IDENTIFY_THEN) as client:
        execute = partial(client.execute, connection.unit)
        seen: dict[str, str] = {}
        objects = _device_identification(execute, seen)
        _server_id(execute, seen)
        sunspec = _sunspec(execute, seen)
        answers = probe(execute, headers, deadline)
    if all(text == "no response" for text in seen.values()) and all(a.missing for a in answers.values()):
        raise NoResponse(f"no response from unit {connection.unit} to any of identify's reads")
    left_out = sum(1 for a in answers.values() if a.missing.startswith("not read"))
    if left_out:
        seen["budget"] = f"{left_out} signature reads left out: the {budget:g} s budget was spent"
    return rank(headers, answers, objects), sunspec, seen


class _Quiet:
    """What scan's walk reports to, when identify walks the bus: nothing is shown."""

    def found(self, answer) -> None:
        pass

    def garbled(self, answer) -> None:
        pass

    def note(self, text: str) -> None:
        pass

    def at(self, setting, unit: int) -> None:
        pass

    def advance(self, steps: int = 1) -> None:
        pass


WALK_PROBE = ("read-holding-registers", 0, 1)  # scan's probe: any reply, an exception too, is a unit


def _dry_run_walk(connection, settings, units: list[int]) -> None:
    from mbtool.link.scan import probe_request  # noqa: PLC0415 - --all-units only

    request = probe_request(*WALK_PROBE)
    rest = f"then the same read to units {units_text(frozenset(units[1:]))}, " if units[1:] else ""
    then = rest + "and identify's reads of each unit that answers"
    with open_client(replace(connection, unit=units[0]), settings, request.name, then=then) as client:
        client.execute(units[0], request)


def _answering_units(connection, settings, units: list[int]) -> list[int]:
    """The units that answer a read of holding register 0 (an exception is an answer), as
    mbtool scan finds them, at the connection's settings."""
    from mbtool.link.scan import Scan, Setting, probe_request  # noqa: PLC0415 - --all-units only

    serial = connection.serial
    line = Setting(baud=serial.baud, parity=serial.parity, bytesize=serial.bytesize, stopbits=serial.stopbits)
    request = probe_request(*WALK_PROBE)
    quiet = _Quiet()
    tally = Scan(connection, request, units, [line], False, False, quiet, trace_for(settings)).run(quiet)
    return sorted({answer.unit for answer in tally.found})


def _best(candidates: list):
    """The map identify names: the first candidate, when the device named it in FC 43/14 or
    its whole signature fits; None otherwise."""
    first = candidates[0] if candidates else None
    return first if first is not None and (first.named or first.complete) else None


def _write_inventory(path: str, connection, results: list) -> None:
    """A poll inventory of the bus: one link, a device a unit with the map identify named;
    a unit it could not name is a comment saying what it saw."""
    import tomli_w  # noqa: PLC0415 - --inventory only

    link = {"target": connection.port}
    if connection.port and "://" not in connection.port:  # a serial line: its settings
        serial = connection.serial
        link |= {"baud": serial.baud, "parity": serial.parity, "stopbits": int(serial.stopbits)}
    devices, unknown = {}, []
    for unit, candidates, sunspec, _seen in results:
        best = _best(candidates)
        if best is None:
            what = "a SunSpec device: mbtool sunspec --map writes its map" if sunspec else "unknown device"
            unknown.append(f'# unit {unit}: {what}; give it map = "..." or read = ["40001 10"]')
            continue
        devices[f"{best.name}-{unit}"] = {"link": "bus", "unit": unit, "map": best.name}
    text = (
        f"# The devices mbtool identify --all-units found on {connection.port}, each with its map.\n"
        + tomli_w.dumps({"links": {"bus": link}, "devices": devices})
        + "".join(f"{line}\n" for line in unknown)
    )
    try:
        Path(path).write_text(text, encoding="utf-8")
    except OSError as error:
        raise OutputFailed(path, error) from None
    print(
        f"mbtool: wrote {path}: {counted(len(devices), 'device')}, {len(unknown)} not identified",
        file=sys.stderr,
    )


def _device_identification(execute, seen: dict[str, str]) -> dict[str, str]:
    """FC 43/14's basic and regular objects by name ({} when the device has none)."""
    from mbtool.codec.device_id import object_name  # noqa: PLC0415 - identify only
    from mbtool.link.dump import read_identification  # noqa: PLC0415 - identify only

    objects: dict[int, bytes] = {}
    for level, code in (("basic", 1), ("regular", 2)):
        try:
            found, _ = read_identification(execute, code)
        except ModbusException as error:
            seen.setdefault("fc43", _refused(error))
            break
        except NoResponse:
            seen.setdefault("fc43", "no response")
            break
        except FrameError as error:
            seen.setdefault("fc43", f"a bad reply: {error}")
            break
        objects.update(found)
        if level == "basic":
            seen["fc43"] = ""
    named = {object_name(i): text_of(value) for i, value in objects.items()}
    if named:
        seen["fc43"] = ", ".join(f'{key} "{value}"' for key, value in named.items())
    return named


def _server_id(execute, seen: dict[str, str]) -> None:
    from mbtool.codec.serial_line import ReportSlaveId  # noqa: PLC0415 - identify only

    try:
        reply = execute(ReportSlaveId())
    except ModbusException as error:
        seen["fc17"] = _refused(error)
        return
    except NoResponse:
        seen["fc17"] = "no response"
        return
    except FrameError as error:
        seen["fc17"] = f"a bad reply: {error}"
        return
    extra = printable(reply.extra)
    seen["fc17"] = f"server id {reply.slave_id}" + (f', "{extra}"' if extra else "")


def _sunspec(execute, seen: dict[str, str]) -> dict | None:
    """The SunSpec marker and the Common model's manufacturer and model (Mn, Md), if any."""
    from mbtool.sunspec.discover import NotSunSpec, find_marker  # noqa: PLC0415 - identify only

    try:
        base = find_marker(execute)
    except NotSunSpec as error:
        seen["sunspec"] = str(error)
        return None
    except NoResponse:
        seen["sunspec"] = "no response"
        return None
    found = {"base": base, "ref": reference(HOLDING_REGISTERS, base)}
    try:  # the Common model follows the marker: ID, L, Mn (16 registers), Md (16)
        registers = execute(ReadHoldingRegisters(base + 4, 32)).registers
        found["manufacturer"] = str(decode_values(list(registers[:16]), "string")[0]).rstrip("\x00 ")
        found["model"] = str(decode_values(list(registers[16:32]), "string")[0]).rstrip("\x00 ")
    except (ModbusException, NoResponse, FrameError):
        pass
    seen["sunspec"] = f'"SunS" at {found["ref"]}'
    return found


def _refused(error: ModbusException) -> str:
    return f"exception {error.exception_code:02d} {exception_name(error.exception_code)}"


SEEN_NAMES = {"fc43": "FC 43/14", "fc17": "FC 17", "sunspec": "SunSpec", "budget": "budget"}


def _show_identity(unit: int, settings, candidates, sunspec: dict | None, seen: dict[str, str]) -> None:
    best = _best(candidates)

    def data() -> dict:
        return {
            "unit": unit,
            "identified": best is not None or sunspec is not None,
            "map": best.name if best else None,
            "sunspec": sunspec,
            "candidates": [
                {
                    "map": c.name,
                    "manufacturer": c.header.manufacturer,
                    "model": c.header.model,
                    "kind": c.header.kind,
                    "complete": c.complete,
                    "fits": f"{c.fits}/{c.probes}",
                    "score": c.score,
                    "evidence": list(c.evidence),
                }
                for c in candidates
            ],
            "seen": {SEEN_NAMES[key]: value or "no objects" for key, value in seen.items()},
        }

    def lines() -> list[str]:
        if best is not None:
            shown = [f"unit {unit}: {best.header.manufacturer} {best.header.model}, map {best.name}"]
        elif sunspec is not None:
            named = " ".join(filter(None, (sunspec.get("manufacturer"), sunspec.get("model"))))
            shown = [
                f"unit {unit}: SunSpec device {named}".rstrip()
                + ": mbtool sunspec reads it (--map writes its map)"
            ]
        else:
            shown = [f"unit {unit}: unknown device"]
        for candidate in candidates:
            if candidate is not best:
                how = (
                    "fits"
                    if candidate.complete
                    else f"partly ({candidate.fits} of {candidate.probes} probes)"
                )
                shown.append(
                    f"  also {how}: {candidate.header.manufacturer} {candidate.header.model}, map {candidate.name}"
                )
            shown += [f"    {line}" for line in candidate.evidence]
        shown += [f"  seen: {SEEN_NAMES[key]}: {value or 'no objects'}" for key, value in seen.items()]
        return shown

    # No table and no CSV of its own: its lines, as plain says them.
    render(Listing(data=data, table=None, lines=lines), settings.output_format or "plain")
