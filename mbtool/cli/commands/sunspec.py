"""``mbtool sunspec``: find a SunSpec device's models and name every point, with no map
written by hand; ``--map`` writes the register map of what it found (issue 34)."""

from __future__ import annotations

import math
import sys
from functools import partial

import click
import tomli_w

from mbtool.cli.options import device_command
from mbtool.cli.param_types import FilePath, Number
from mbtool.cli.profiles import defaults
from mbtool.cli.results import Listing, value_text
from mbtool.cli.session import open_client
from mbtool.cli.sinks import default_format, render
from mbtool.cli.sinks.table import titled_tables
from mbtool.cli.whole_file import WholeFile
from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.codec.errors import ModbusException
from mbtool.errors import ExitCode, NoResponse, UsageError, Verdict
from mbtool.registermap.load import build_map
from mbtool.sunspec.discover import NotSunSpec, discover
from mbtool.sunspec.layout import map_rows
from mbtool.sunspec.models import BASES
from mbtool.sunspec.values import read_values
from mbtool.words import counted

SMA_UNIT = 126  # SMA inverters answer SunSpec on unit 126 (their own register map on 3)
MAP_MAX_GAP = 8  # a SunSpec chain has no holes: bridging 8 registers is cheaper than a request


@device_command("sunspec")
@click.option(
    "--base",
    type=Number(0, 65534, "base"),
    help="Look for the marker (SunS) only at this holding register (default: 40000, then 0, then 50000).",
)
@click.option(
    "--model",
    "model_ids",
    type=Number(1, 65534, "model"),
    multiple=True,
    metavar="ID",
    help="Show this model only, by id (repeatable): --model 103. The chain is walked all the same.",
)
@click.option(
    "--map",
    "map_path",
    metavar="FILE",
    type=FilePath(dir_okay=False),
    help="Write a register map (TOML) of the points found, for read -m, write -m, check -m and poll. "
    "FILE is replaced whole (written beside it, then renamed), or left as it was.",
)
def sunspec(connection, settings, base, model_ids, map_path):
    """Find a SunSpec device's models and name every point: solar inverters, meters, batteries.

    Looks for the marker "SunS" at holding register 40000, 0 and 50000 (--base: only
    there), walks the chain of models to the end model (0xFFFF) and prints each model
    (id, name, where it starts, its length) and its points: the value with its scale
    factor applied, the unit, an enum's symbol and a bitfield's set bits; a repeating
    group (model 160's MPPT modules) one repeat a line. A value SunSpec calls
    unimplemented (0xFFFF, 0x8000, 0x80000000, NaN, as the point's type says) is shown as
    not implemented. -o json gives the whole tree.

    The definitions are the SunSpec Alliance's (shipped with mbtool). Without -u, a device
    that has no SunSpec marker on unit 1 is asked on unit 126 (SMA's SunSpec unit). A
    chain without its end model, one ended by 0x0000, a model whose length is not its
    definition's (the length on the wire is used), a repeating group that does not fit and
    a model SunSpec does not define (shown raw) are each a warning on stderr; the walk
    goes on. A model whose registers the device refuses is named, the others shown: exit 8.
    The walk stops after 100 models, or before a model that would take it past 10,000
    registers read: the models found are shown, exit 8. Ctrl-C or SIGTERM shows the models
    found so far (and writes no map): exit 130.
    """
    if map_path is not None and not map_path.lower().endswith(".toml"):
        raise UsageError(f"--map writes a TOML map: {map_path} is not a .toml file name")
    fmt = settings.output_format or default_format()
    bases = (base,) if base is not None else None
    chain, unit = _walk(connection, settings, bases, set(model_ids))
    wanted = [m for m in chain.models if not model_ids or m.layout.model_id in model_ids]
    if model_ids and not wanted:
        found = ", ".join(str(m.layout.model_id) for m in chain.models) or "none"
        raise UsageError(f"no model {', '.join(map(str, model_ids))} in the chain (its models: {found})")
    # A model the device refused is laid out by its length alone: its layout says nothing.
    for warning in [*chain.warnings, *(w for m in wanted if m.error is None for w in m.layout.warnings)]:
        print(f"mbtool: warning: {warning}", file=sys.stderr)
    unwritten = None
    if map_path is not None:
        # An interrupted walk's map would be a part of the device's, put in place of a whole one.
        if chain.interrupted:
            unwritten = f"no map written to {map_path}"
        else:
            unwritten = _write_map(map_path, connection, unit, chain, wanted)
    tree = _tree(chain, unit, wanted)
    listing = Listing(
        data=lambda: tree,
        table=lambda: (CSV_HEADER, _rows(tree)),
        lines=lambda: _lines(tree),
        draw=lambda: titled_tables(_blocks(tree)),
    )
    render(listing, fmt, csv_header=settings.csv_header)
    refused = [m for m in wanted if m.error is not None]
    if refused or unwritten or chain.stopped:
        named = [f"{m.layout.title} at {m.layout.address}: {m.error}" for m in refused]
        if refused:
            named.append(f"{len(wanted) - len(refused)} of {counted(len(wanted), 'model')} read")
        if chain.stopped:
            named.append(f"{chain.stopped}; the models found are shown")
        text = "; ".join(named + ([unwritten] if unwritten else []))
        if chain.interrupted:
            return Verdict(f"interrupted; {text}", ExitCode.INTERRUPTED)
        return Verdict(text, ExitCode.PARTIAL)
    return None


# --- the walk, on one unit or, when none is given, on SMA's too --------------------------------


def _walk(connection, settings, bases, model_ids: set[int]):
    """The chain and the unit it was found on."""
    bases = bases or BASES
    with open_client(
        connection, settings, ReadHoldingRegisters.name, then="then the chain of models after the marker"
    ) as client:
        if settings.dry_run:
            client.execute(connection.unit, ReadHoldingRegisters(bases[0], 2))
        try:
            return discover(partial(client.execute, connection.unit), bases, model_ids), connection.unit
        except (NoResponse, ModbusException, NotSunSpec) as error:
            if _unit_given() or connection.unit == SMA_UNIT:
                raise
            first = error
        try:
            chain = discover(partial(client.execute, SMA_UNIT), bases, model_ids)
        except (NoResponse, ModbusException, NotSunSpec):
            raise first from None
    print(
        f"mbtool: warning: unit {connection.unit}: {_why(first)}; unit {SMA_UNIT} (SMA's SunSpec unit) "
        f"has it: -u {SMA_UNIT} goes there at once",
        file=sys.stderr,
    )
    return chain, SMA_UNIT


def _why(error: BaseException) -> str:
    return "no response" if isinstance(error, NoResponse) else str(error)


def _unit_given() -> bool:
    """-u, MBTOOL_UNIT or the profile named the unit: only that one is asked."""
    ctx = click.get_current_context()
    if ctx.get_parameter_source("unit") is not click.core.ParameterSource.DEFAULT:
        return True
    profile = ctx.meta.get("mbtool.profile")
    if not profile:
        return False

    return "unit" in defaults(profile)


# --- what was found, as a tree: models, their points and groups --------------------------------


def _tree(chain, unit: int, models) -> dict:
    out = {"unit": unit, "base": chain.base, "models": []}
    for model in models:
        layout = model.layout
        entry = {
            "id": layout.model_id,
            "name": layout.name,
            "label": layout.label,
            "address": layout.address,
            "length": layout.length,
        }
        if model.error is not None:
            entry["error"] = str(model.error)
        else:
            values = read_values(layout, model.registers)
            if layout.root is not None:
                entry |= _group(layout.root, values)
            if layout.raw is not None:
                address, count = layout.raw
                start = address - layout.start
                entry["raw"] = {"address": address, "registers": list(model.registers[start : start + count])}
        if layout.warnings and model.error is None:
            entry["warnings"] = list(layout.warnings)
        out["models"].append(entry)
    out["warnings"] = list(chain.warnings)
    if chain.stopped:
        out["stopped"] = chain.stopped
    return out


def _group(group, values) -> dict:
    points = {}
    for slot in group.slots:
        read = values[slot.name]
        point = {"name": slot.name, "value": read.value}
        if slot.point.get("units"):
            point["unit"] = slot.point["units"].strip()
        point |= {"type": slot.point["type"], "address": slot.address, "registers": list(read.raw)}
        point["implemented"] = read.implemented
        if read.factor is not None:
            point["sf"] = read.factor
        if read.bits:
            point["bits"] = list(read.bits)
        points[slot.point["name"]] = point
    groups: dict = {}
    for sub in group.groups:
        shown = _group(sub, values) | ({"index": sub.index} if sub.index is not None else {})
        if sub.index is None:
            groups[sub.name] = shown
        else:
            groups.setdefault(sub.name, []).append(shown)
    return {"points": points, **({"groups": groups} if groups else {})}


# --- the outputs ------------------------------------------------------------------------------


NOT_IMPLEMENTED = "not implemented"


def _value_text(point: dict) -> str:
    """A point's value as a person reads it: not implemented, or the value, its unit and a
    bitfield's set bits; a value whose scale factor is not implemented says so."""
    if not point["implemented"]:
        return NOT_IMPLEMENTED
    if point["value"] is None:
        return "no value (its scale factor is not implemented)"
    text = f"{value_text(point['value'])} {point.get('unit', '')}".rstrip()
    if "bits" in point:
        text += f" ({', '.join(point['bits'])})" if point["bits"] else " (none set)"
    return text


def _shown(points: dict) -> dict:
    """The points a person reads: scale factors are applied, not shown."""
    return {name: point for name, point in points.items() if point["type"] != "sunssf"}


def _models(tree: dict) -> str:
    return counted(len(tree["models"]), "model")


def _model_title(model: dict) -> str:
    name = f" {model['name']}" if model["name"] else " (SunSpec defines no such model)"
    label = f" ({model['label']})" if model.get("label") and model["label"] != model["name"] else ""
    return f"model {model['id']}{name}{label} at {model['address']}, {counted(model['length'], 'register')}"


def _repeats(groups: dict, prefix: str = ""):
    """Each group as (its title, its points, its own groups), in order: a repeat of a
    repeating group is one."""
    for name, shown in groups.items():
        for each in shown if isinstance(shown, list) else [shown]:
            title = f"{prefix}{name}" + (f" {each['index']}" if "index" in each else "")
            yield title, each["points"], each.get("groups", {})


def _lines(tree: dict) -> list[str]:
    """One model after another: its title, a point a line (NAME VALUE), a repeat of a
    group on one line of NAME VALUE pairs."""
    lines = [f"SunSpec at {tree['base']}, unit {tree['unit']}: {_models(tree)}"]
    for model in tree["models"]:
        lines.append(_model_title(model))
        if "error" in model:
            lines.append(f"  refused: {model['error']}")
            continue
        lines += [f"  {name} {_value_text(point)}" for name, point in _shown(model.get("points", {})).items()]
        lines += _plain_groups(model.get("groups", {}), "  ")
        if "raw" in model:
            registers = " ".join(f"{r:04X}" for r in model["raw"]["registers"])
            lines.append(f"  raw at {model['raw']['address']}: {registers}")
    return lines


def _plain_groups(groups: dict, indent: str) -> list[str]:
    lines = []
    for title, points, inner in _repeats(groups):
        pairs = ", ".join(f"{name} {_value_text(point)}" for name, point in _shown(points).items())
        lines.append(f"{indent}{title}: {pairs}")
        lines += _plain_groups(inner, indent + "  ")
    return lines


CSV_HEADER = ["model", "name", "value", "unit", "address", "registers", "implemented"]


def _rows(tree: dict) -> list[list]:
    """A row a point (scale factors too), by its name in the map."""
    return [
        [
            model["id"],
            point["name"],
            "" if point["value"] is None else value_text(point["value"]),
            point.get("unit", ""),
            point["address"],
            " ".join(map(str, point["registers"])),
            int(point["implemented"]),
        ]
        for model in tree["models"]
        for point in _every_point(model)
    ]


def _every_point(group: dict):
    yield from group.get("points", {}).values()
    for _, points, inner in _repeats(group.get("groups", {})):
        yield from _every_point({"points": points, "groups": inner})


def _blocks(tree: dict) -> list[tuple]:
    """What -o table draws (cli.sinks.table.titled_tables): a table a model; a repeating
    group's repeats as the rows of a table of their own, a column a point."""
    blocks: list[tuple] = [("title", f"SunSpec at {tree['base']} · unit {tree['unit']} · {_models(tree)}")]
    for model in tree["models"]:
        if "error" in model:
            blocks.append(("error", _model_title(model), model["error"]))
            continue
        blocks.append(("title", _model_title(model)))
        rows = [
            [name, _value_text(point), str(point["address"])]
            for name, point in _shown(model.get("points", {})).items()
        ]
        if "raw" in model:
            registers = " ".join(f"{r:04X}" for r in model["raw"]["registers"])
            rows.append(["(raw)", registers, str(model["raw"]["address"])])
        blocks.append(("table", [("Point", "left"), ("Value", "right"), ("Address", "right")], rows))
        blocks += _group_blocks(model.get("groups", {}))
    return blocks


def _group_blocks(groups: dict, prefix: str = "") -> list[tuple]:
    blocks: list[tuple] = []
    by_name: dict[str, list] = {}
    for title, points, inner in _repeats(groups, prefix):
        by_name.setdefault(title.rsplit(" ", 1)[0] if title[-1].isdigit() else title, []).append(
            (title, points, inner)
        )
    for name, repeats in by_name.items():
        columns = list(_shown(repeats[0][1]))
        rows = [
            [title, *(_value_text(points[c]) for c in columns if c in points)] for title, points, _ in repeats
        ]
        blocks.append(("table", [(name, "left"), *((column, "right") for column in columns)], rows))
        for title, _, inner in repeats:
            blocks += _group_blocks(inner, f"{title} ")
    return blocks


# --- --map: the register map of what was found -----------------------------------------------------


def _write_map(path: str, connection, unit: int, chain, models) -> str | None:
    """A map of every point of the models read, scaled by their scale factors (scale_ref),
    SunSpec's unimplemented values as invalid; checked by the map loader before it is written.
    Why no map was written, when no point was read that a map could name."""
    rows: dict = {}
    left_out: list[str] = []
    for model in models:
        if model.error is not None or model.layout.root is None:
            left_out.append(
                f"{model.layout.title} at {model.layout.address} ({'refused' if model.error else 'raw'})"
            )
            continue
        found, missing = map_rows(model.layout)
        rows |= found
        left_out += missing
    if not rows:
        return f"no map written to {path}: no point of a model SunSpec defines was read"
    build_map(path, {"max_gap": MAP_MAX_GAP}, rows)  # the loader's own checks, before a byte is written
    common = next((m for m in models if m.layout.model_id == 1 and m.error is None), None)
    device = ""
    if common is not None:
        values = read_values(common.layout, common.registers)
        named = [
            values[f"{common.layout.key}.{n}"].value
            for n in ("Mn", "Md", "SN")
            if f"{common.layout.key}.{n}" in values
        ]
        device = " ".join(str(v) for v in named if v)
    listed = ", ".join(
        f"{m.layout.model_id} {m.layout.name or '(raw)'} at {m.layout.address}" for m in models
    )
    header = [
        f"# The register map of unit {unit} at {connection.port}, written by mbtool sunspec --map.",
        *([f"# Device: {device}."] if device else []),
        f"# SunSpec models (the chain at {chain.base}): {listed}.",
        "# A point's scale factor is read with it (scale_ref); SunSpec's 'not implemented' values are invalid.",
        *([f"# Left out: {', '.join(left_out)}."] if left_out else []),
    ]
    text = "\n".join(header) + "\n\n" + _toml({"max_gap": MAP_MAX_GAP}, rows)
    with WholeFile(path) as out:  # a write that fails leaves the previous map as it was
        out.commit(text)
    print(
        f"mbtool: wrote {path}: {counted(len(rows), 'point')} of {counted(len(models), 'model')}",
        file=sys.stderr,
    )
    return None


def _toml(device: dict, rows: dict) -> str:
    """The map as TOML, a point a table of one-line keys (tomli_w writes each list and enum
    over lines of their own)."""
    lines = ["[device]", *(f"{key} = {_toml_value(value)}" for key, value in device.items())]
    for name, row in rows.items():
        lines += ["", f"[points.{_toml_key(name)}]"]
        lines += [f"{key} = {_toml_value(value)}" for key, value in row.items()]
    return "\n".join(lines) + "\n"


def _toml_key(key: str) -> str:
    return tomli_w.dumps({key: 0}).rsplit(" = ", 1)[0]


def _toml_value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_toml_key(k)} = {_toml_value(v)}" for k, v in value.items()) + " }"
    return tomli_w.dumps({"v": value}).split(" = ", 1)[1].rstrip("\n")
