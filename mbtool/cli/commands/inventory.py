"""``mbtool inventory check`` and ``mbtool inventory split`` (issue 44): a poll inventory
checked without opening anything, and split into one inventory per value of a device tag,
for a fleet of pollers (one a site)."""

from __future__ import annotations

import math
import os
import re
import sys
from pathlib import Path

import click

from mbtool.cli.parsing import QuickHelp
from mbtool.cli.sinks.json import to_json
from mbtool.errors import OutputFailed, UsageError
from mbtool.files import read_toml
from mbtool.link.settings import File
from mbtool.plant.budget import link_budget
from mbtool.plant.inventory import LINK_KEYS, load_inventory
from mbtool.registermap.plan import MapReader
from mbtool.words import counted

HELP = {"help_option_names": ["-h", "--help"]}
# A split's file is named by its tag's value: a name, never a path out of DIR.
FILE_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")


class InventoryGroup(QuickHelp, click.Group):
    pass


@click.group("inventory", cls=InventoryGroup, context_settings=HELP)
def inventory() -> None:
    """A poll inventory (PLANT.toml) checked, or split for a fleet of pollers."""


@inventory.command("check", context_settings=HELP)
@click.argument("path", metavar="PLANT.toml", type=click.Path(dir_okay=False))
def check(path):
    """Check an inventory whole, opening nothing (no port, no connection), and print its links,
    their devices and their poll groups, and each serial link's budget: the line time a second
    its polls need at its baud rate. Exit status 0 when it loads; 2, with the file, line, table
    and key of the first problem, when it does not."""
    plant = load_inventory(path)
    print(f"{path}: {counted(len(plant.links), 'link')}, {counted(len(plant.devices), 'device')}")
    for name, link in plant.links.items():
        devices = [device for device in plant.devices if device.link == name]
        print(f"link {name}: {link.connection.port}, {counted(len(devices), 'device')}")
        for device in devices:
            assert isinstance(device.reader, MapReader)  # an inventory's devices read their points
            reads = counted(len(device.reader.points), "point")
            source = f"map {plant.maps[device.name]}" if device.name in plant.maps else "references"
            print(f"  {device.name}: unit {device.unit}, {reads} ({source}), every {device.interval:g} s")
            for group in device.groups:
                assert isinstance(group.reader, MapReader)  # an inventory's groups read their points
                pace = (
                    "at start and after each reconnect"
                    if group.interval == math.inf
                    else f"every {group.interval:g} s"
                )
                what = f"{counted(len(group.reader.points), 'point')}, {counted(len(group.reader.blocks), 'read')}"
                print(f"    group {group.name}: {what}, {pace}")
        budget = link_budget(link, devices)
        print(f"  budget: {budget.line()}" if budget else "  budget: none, not a serial line of mbtool's own")


@inventory.command("split", context_settings=HELP)
@click.argument("path", metavar="PLANT.toml", type=click.Path(dir_okay=False))
@click.option("--by", "by", required=True, metavar="tag:NAME", help="Split by this device tag's values.")
@click.option(
    "-o",
    "--output",
    "folder",
    required=True,
    type=click.Path(file_okay=False),
    help="Write VALUE.toml for each value into this folder (made if missing).",
)
def split(path, by, folder):
    """Split an inventory into one a value of a device tag (--by tag:site): each file holds
    [poll], the devices of that value and their links, its maps and files named by absolute
    paths so each resolves wherever the file goes. Every device needs the tag, and a link's
    devices one value (a link is polled from one place). Exit status 2, nothing written, for
    a bad inventory or split; 7 when a file cannot be written."""
    kind, _, tag = by.partition(":")
    if kind != "tag" or not tag:
        raise UsageError(f"--by {by!r}: expected tag:NAME, such as tag:site")
    plant = load_inventory(path)  # checked whole first: a split of a bad inventory is none
    data = read_toml(Path(path), "inventory")
    parts: dict[str, list[str]] = {}
    link_of: dict[str, str] = {}  # link -> the value its devices have
    for device in plant.devices:
        value = (device.tags or {}).get(tag)
        if value is None:
            raise UsageError(f"{path}: [devices.{device.name}] has no tag {tag}: it would be in no part")
        if not FILE_NAME.fullmatch(value):
            raise UsageError(
                f"{path}: [devices.{device.name}] tags.{tag}: {value!r} cannot name a file "
                "(letters, digits, _, . and -, not first .)"
            )
        if link_of.setdefault(device.link, value) != value:
            raise UsageError(
                f"{path}: [links.{device.link}] has devices of {tag} {link_of[device.link]} and "
                f"{value}: a link is polled from one place (split it, or tag its devices alike)"
            )
        parts.setdefault(value, []).append(device.name)
    out = Path(folder)
    try:
        out.mkdir(parents=True, exist_ok=True)
        for value, names in parts.items():
            links = {device.link for device in plant.devices if device.name in names}
            text = _toml(_part(data, plant, names, links))
            (out / f"{value}.toml").write_text(text, encoding="utf-8")
            print(f"{out / f'{value}.toml'}: {counted(len(links), 'link')}, {counted(len(names), 'device')}")
    except OSError as error:
        raise OutputFailed(str(out), error) from None
    sys.stdout.flush()


def _part(data: dict, plant, names: list[str], links: set[str]) -> dict:
    """One part's tables as the file had them, with its maps and files named absolutely."""
    part: dict = {}
    if "poll" in data:
        part["poll"] = data["poll"]
    part["links"] = {}
    for name, table in data.get("links", {}).items():
        if name in links:
            part["links"][name] = {
                key: _absolute_file(key, value, Path(plant.path).parent) for key, value in table.items()
            }
    part["devices"] = {}
    for name, table in data["devices"].items():
        if name in names:
            table = dict(table)
            if name in plant.maps:
                # resolved, and absolute: the inventory's folder may be relative to here
                table["map"] = os.path.abspath(plant.maps[name])
            part["devices"][name] = table
    return part


def _absolute_file(key: str, value, folder: Path):
    """A link's file (cert, key, ca) named from the original inventory's folder."""
    setting = LINK_KEYS.get(key)
    if setting is not None and isinstance(setting.kind, File) and isinstance(value, str):
        return os.path.abspath(folder / Path(value).expanduser())
    return value


# --- TOML: what an inventory holds (text, numbers, booleans, lists, tables) -----------------


def _toml(data: dict) -> str:
    lines: list[str] = []
    for table, body in data.items():
        if table == "poll":
            lines += ["[poll]", *(f"{_key(k)} = {_value(v)}" for k, v in body.items()), ""]
            continue
        for name, entries in body.items():
            lines += [
                f"[{table}.{_key(name)}]",
                *(f"{_key(k)} = {_value(v)}" for k, v in entries.items()),
                "",
            ]
    return "\n".join(lines)


def _key(key: str) -> str:
    return key if BARE_KEY.fullmatch(key) else to_json(key)


def _value(value) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, str):
        return to_json(value)  # JSON's escapes are TOML basic string's
    if isinstance(value, int | float):
        return repr(value)  # Python's 1e+20, inf and nan are TOML's too
    if isinstance(value, list):
        return "[" + ", ".join(_value(item) for item in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }"
    raise UsageError(f"cannot write {value!r} as TOML")
