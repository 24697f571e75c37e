"""The device library (issue 43): ``mbtool maps list`` and ``mbtool maps show`` (the maps
mbtool ships, mbtool/library/), and ``mbtool identify`` (which of them a device is)."""

from __future__ import annotations

import click

from mbtool.cli.parsing import QuickHelp
from mbtool.library import MAPS, library_names, load_named_map, resolve_map

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
        from mbtool.cli.json_text import to_json  # noqa: PLC0415 - --json only

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
