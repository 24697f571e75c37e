"""The inventory of ``mbtool poll``: a plant's links and devices in one TOML file.

::

    [poll]                       # defaults for every device
    interval = 10                # seconds between polls of a device
    output = "json"              # any -o format; the command line beats it
    site = "north"               # labels on every record of every output (JSON keys, influx
    instance = "poller-a"        # tags, Prometheus labels); instance: the host name if not given

    [links.bus1]                 # every key a profile takes but unit and map; target for port
    target = "/dev/ttyUSB0"
    baud = 9600

    [links.plc]                  # Modbus/TCP Security: cert, key and ca beside the file
    target = "tls://plc7.plant.example"
    cert = "poller.pem"
    key = "poller.key"
    ca = "plant-ca.pem"

    [devices.meter1]
    link = "bus1"
    unit = 1
    map = "sdm630"               # a map's name (mbtool maps list), or a file relative to the
                                 # inventory's; points = [...] picks some
    tags = { site = "north" }
    measurement = "meters"       # -o influx's measurement for it (else --measurement, modbus)

    [devices.meter1.groups.fast] # poll groups (registermap/groups.py): these points every second,
    interval = 1                 # the rest at the device's interval; once = [...] read at start
    points = ["power"]           # and after each reconnect; a map may give them too

    [devices.plc]
    link = "bus1"
    unit = 3
    read = ["40001 10", "00001 16"]   # references with counts, as `read` takes them
    timeout = 2.5                     # its own timeout and retries: the link's otherwise

Everything is checked before anything is opened: an unknown key, a device that names a
link the file does not have, a map that does not load, a target that names nothing, a
value of the wrong type are one UsageError (exit 2) naming the file, the table and the key.
A link's keys are the link settings (``link.settings.SETTINGS``), read as a profile's are.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from mbtool.codec.errors import RequestError
from mbtool.codec.record import record, replace
from mbtool.codec.tables import parse_reference, reference
from mbtool.errors import UsageError
from mbtool.files import beside, read_toml
from mbtool.library import resolve_map
from mbtool.link import IN_PROCESS
from mbtool.link.connection import check, connection_of, read_credentials
from mbtool.link.settings import SETTINGS, File, Setting
from mbtool.link.transport import parse_target
from mbtool.mqtt.settings import check_table
from mbtool.plant.schedule import DeviceSpec, Group, LinkSpec
from mbtool.registermap.groups import DEFAULT, GroupPlan, read_groups
from mbtool.registermap.load import MapError, RegisterMap, load_map, name_problem, one_line
from mbtool.registermap.plan import MapReader
from mbtool.registermap.point import Point

POLL_KEYS = {
    "interval": "seconds between polls of a device, such as 10",
    "output": "one of poll's -o formats",
    "offline_after": "failed polls in a row that make a device offline, such as 3",
    "max_backoff": "the longest wait, in seconds, before an offline device is tried again (at least the interval)",
    "site": 'the site this poller serves, a label on every record, such as "north"',
    "instance": "this poller's name, a label on every record (default: the host name)",
}
# A fleet's labels: what tells one poller's records from another's where several feed one
# Prometheus or one broker.  They are every device's tags, so every output carries them.
FLEET_LABELS = ("site", "instance")
# A device may set its own interval, offline_after and max_backoff, its measurement, and its own timeout and
# retries where it is slower or less reliable than its link's other devices (the link's otherwise).
OWN_LINK_KEYS = ("timeout", "retries")
DEVICE_KEYS = (
    "link",
    "unit",
    "map",
    "points",
    "groups",
    "once",
    "read",
    "tags",
    "measurement",
    *POLL_KEYS.keys() - {"output", *FLEET_LABELS},
    *OWN_LINK_KEYS,
)
# A link takes every link setting but the unit (each device has its own); its port is its target.
LINK_KEYS: dict[str, Setting] = {"target": SETTINGS["port"]} | {
    key: setting for key, setting in SETTINGS.items() if key not in ("port", "unit")
}
DEFAULTS = {"interval": 10.0, "offline_after": 3, "max_backoff": 300.0}
# A tag is a Prometheus label and an influx tag: a name both can carry, and not one of the
# labels every record has.
TAG_NAME = re.compile(r"[a-zA-Z_][a-zA-Z0-9_]*")
RESERVED_TAGS = ("device", "name", "ref", "unit", "link")


@record
class Inventory:
    path: str
    output: str | None
    links: dict[str, LinkSpec]
    devices: list[DeviceSpec]
    maps: dict[str, str]  # device name -> the path of its register map (those with a map)
    labels: dict[str, str]  # [poll] site and instance: on every record of every output
    mqtt: dict | None = None  # its [mqtt] table, checked (mbtool/mqtt/settings.py): poll adds --mqtt's url


def load_inventory(path: str, outputs: tuple[str, ...] = ()) -> Inventory:
    """The inventory at ``path``, checked whole; UsageError (exit 2) naming what is wrong, and
    the line of the table or key it names (``FILE:LINE: [table] key: ...``).  ``outputs``: the
    formats its [poll] output may name (cli's registry of sinks, which this click-free room
    does not import); none given, any is taken."""
    try:
        return _load(path, outputs)
    except UsageError as error:
        raise UsageError(_with_line(str(error), path)) from None


# What a problem with a table or key names after the file: "[devices.d] speed: ...", or a
# table inside a device's: "[devices.d.groups.fast] interval: ..."
_NAMED = re.compile(r"\[([A-Za-z0-9_]+)(?:\.([^\]]+))?\](?: ([A-Za-z0-9_]+))?")
_HEADER = re.compile(r"\s*\[\s*([^\[\]]+?)\s*\]\s*(?:#.*)?$")
_PART = re.compile(r"\s*(\"[^\"]*\"|'[^']*'|[A-Za-z0-9_-]+)\s*(?:\.|$)")


def _with_line(message: str, path: str) -> str:
    """``message`` with the line of the file its table (and key) stand on; as it was when it
    names none, or names what the file does not hold (a table that is missing).  A table the
    file writes inside its parent's (``groups.fast = {...}``) is found at its first key's line."""
    prefix = f"{path}: "
    named = _NAMED.match(message[len(prefix) :]) if message.startswith(prefix) else None
    if named is None:
        return message
    table, name, key = named.groups()
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError):
        return message
    parts = [table, *(name.split(".") if name else ())]
    # the table itself, else the parent that holds it, found by the key the rest begins with
    for end in range(len(parts), 1 if name else 0, -1):
        found = _line_of(lines, ".".join(parts[:end]), key if end == len(parts) else parts[end])
        if found is not None:
            return f"{path}:{found}: {message[len(prefix) :]}"
    return message


def _line_of(lines: list[str], table: str, key: str | None) -> int | None:
    """The line of ``key`` in ``[table]``, or of its own table below it (``[table.key...]``); the
    table's header's when the key is not there; None when the table is not either."""
    found, inside = None, False
    for number, line in enumerate(lines, 1):
        header = _HEADER.match(line)
        if header:
            name = ".".join(part.strip("\"'") for part in _PART.findall(header[1]))
            if key and (name + ".").startswith(f"{table}.{key}."):  # the key's own table
                return number
            inside = name == table
            if inside and found is None:
                found = number
            continue
        if inside and key and re.match(rf"\s*{re.escape(key)}\s*[=.]", line):
            return number
    return found


def _load(path: str, outputs: tuple[str, ...]) -> Inventory:
    data = read_toml(Path(path), "inventory")
    for key in data:
        if key not in ("poll", "links", "devices", "mqtt"):
            raise UsageError(
                f"{path}: unknown table [{key}] (known: [poll], [links.NAME], [devices.NAME], [mqtt])"
            )
    poll = _table(data, "poll", path, "[poll]")
    defaults = {}  # what [poll] gives; DEFAULTS for the rest
    output = None
    labels = {"instance": os.uname().nodename}
    for key, value in poll.items():
        where = f"{path}: [poll] {key}"
        if key not in POLL_KEYS:
            raise UsageError(f"{where}: unknown key (known: {', '.join(POLL_KEYS)})")
        if key == "output":
            if outputs and value not in outputs:
                raise UsageError(f"{where}: {value!r} is not one of {', '.join(outputs)}")
            output = value
        elif key in FLEET_LABELS:
            labels[key] = _label(key, value, where)
        else:
            defaults[key] = _setting(key, value, where)
    links = {
        name: _link(name, table, path, Path(path).parent)
        for name, table in _table(data, "links", path, "[links.NAME]", nested=True).items()
    }
    _one_link_a_target(links, path)
    tables = _table(data, "devices", path, "[devices.NAME]", nested=True)
    loaded: dict[Path, RegisterMap] = {}  # each map file once, however many devices share it
    devices = [_device(name, table, path, links, defaults, loaded, labels) for name, table in tables.items()]
    if not devices:
        raise UsageError(f"{path}: no [devices.NAME]: nothing to poll")
    folder = Path(path).parent
    maps = {name: str(_map_path(table, folder)) for name, table in tables.items() if "map" in table}
    check_table(data.get("mqtt"), path, devices, labels)
    return Inventory(path, output, links, devices, maps, labels, data.get("mqtt"))


def _table(data: dict, key: str, path: str, shown: str, nested: bool = False) -> dict:
    table = data.get(key, {})
    if not isinstance(table, dict):
        raise UsageError(f"{path}: {key} must be a table, {shown}")
    for name, value in table.items() if nested else ():
        if not isinstance(value, dict):
            raise UsageError(f"{path}: [{key}.{name}] must be a table")
        _name(name, f"{path}: [{key}.{name}]")
    return table


def _name(name: str, where: str) -> None:
    """A link's or device's name: a label value and a tag, so on one line and not empty."""
    if not name or not one_line(name):
        raise UsageError(f"{where}: a name must not be empty nor hold a control character")


def _setting(key: str, value, where: str):
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise UsageError(f"{where}: expected {POLL_KEYS[key]}")
    if key == "offline_after":
        if not isinstance(value, int) or value < 1:
            raise UsageError(f"{where}: expected a whole number of polls, 1 or more")
        return value
    if not 0 < value <= 86400:
        raise UsageError(f"{where}: expected seconds above 0, at most a day (86400)")
    return float(value)


def _label(key: str, value, where: str) -> str:
    """A fleet label's value: text a tag's value may be."""
    if not isinstance(value, str) or _tag_value_problem(value):
        raise UsageError(f"{where}: expected {POLL_KEYS[key]} (one line, not empty, no trailing \\)")
    return value


def _link(name: str, table: dict, path: str, folder: Path) -> LinkSpec:
    settings = {}
    for key, value in table.items():
        where = f"{path}: [links.{name}] {key}"
        if key not in LINK_KEYS:
            raise UsageError(f"{where}: unknown key (known: {', '.join(LINK_KEYS)})")
        setting = LINK_KEYS[key]
        settings[setting.name] = _read(setting, value, where, key)
        if isinstance(setting.kind, File):  # beside the inventory unless absolute
            settings[setting.name] = str(beside(folder, settings[setting.name]))
    if "port" not in settings:
        raise UsageError(
            f'{path}: [links.{name}] has no target (such as "/dev/ttyUSB0" or "tcp://192.0.2.10")'
        )
    port = settings["port"]
    try:
        parse_target(port)
        connection = connection_of(**settings)
        check(connection)
        read_credentials(connection)  # before anything opens, not by a link's worker on each reconnect
    except UsageError as error:
        raise UsageError(f"{path}: [links.{name}]: {error}") from None
    return LinkSpec(name, connection)


def _read(setting: Setting, value, where: str, key: str):
    """A link setting's value as a profile's is read: one rule for what --timeout accepts."""
    try:
        return setting.read(value, key)
    except UsageError as error:
        raise UsageError(f"{where}: {error}") from None


def _one_link_a_target(links: dict[str, LinkSpec], path: str) -> None:
    """Two links on one target are refused: a serial port opens once (the second link's
    devices would never be polled, the port busy with mbtool itself), and two links to one
    TCP device or gateway are two masters polling it at once."""
    seen: dict[tuple, str] = {}
    for name, link in links.items():
        assert link.connection.port is not None  # a link without one is refused when read
        where = parse_target(link.connection.port)
        if where.scheme in IN_PROCESS:  # each sim:// link is a device of its own
            continue
        endpoint = where.endpoint()
        if endpoint in seen:
            raise UsageError(
                f"{path}: [links.{seen[endpoint]}] and [links.{name}] both open "
                f"{link.connection.port}: one link a target (put their devices on one link)"
            )
        seen[endpoint] = name


def _device(
    name: str,
    table: dict,
    path: str,
    links: dict,
    defaults: dict,
    loaded: dict[Path, RegisterMap],
    labels: dict[str, str],
) -> DeviceSpec:
    where = f"{path}: [devices.{name}]"
    for key in table:
        if key not in DEVICE_KEYS:
            raise UsageError(f"{where} {key}: unknown key (known: {', '.join(DEVICE_KEYS)})")
    link = table.get("link")
    if not isinstance(link, str):
        raise UsageError(f"{where}: link must name one of [links.NAME] ({', '.join(links) or 'none'})")
    if link not in links:
        raise UsageError(f"{where} link: no [links.{link}] (links: {', '.join(links) or 'none'})")
    unit = table.get("unit", 1)
    if isinstance(unit, bool) or not isinstance(unit, int) or not 0 <= unit <= 255:
        raise UsageError(f"{where} unit: expected a whole number, 0..255")
    try:
        check(replace(links[link].connection, unit=unit), "polling")
    except UsageError as error:
        raise UsageError(f"{where} unit: {error}") from None
    settings = {
        key: _setting(key, table[key], f"{where} {key}") if key in table else defaults.get(key, DEFAULTS[key])
        for key in DEFAULTS
    }
    measurement = table.get("measurement")  # -o influx's, for this device
    if measurement is not None and not isinstance(measurement, str):
        raise UsageError(
            f'{where} measurement: expected the name of an InfluxDB measurement, such as "meters"'
        )
    problem = "" if measurement is None else name_problem(measurement, "a measurement", influx=True)
    if problem:
        raise UsageError(f"{where} measurement: {problem}")
    _backoff(settings, table, defaults, where)
    for key in OWN_LINK_KEYS:  # checked as a link's are: one place for what --timeout accepts
        if key in table:
            settings[key] = _read(SETTINGS[key], table[key], f"{where} {key}", key)
    folder = Path(path).parent
    reader = _reader(table, where, folder, loaded)
    register_map = loaded[_map_path(table, folder)] if "map" in table else None
    return DeviceSpec(
        name,
        link,
        unit,
        reader,
        labels | _tags(table.get("tags", {}), where, labels),
        raw="read" in table,
        measurement=measurement,
        groups=_groups(table, where, reader, register_map, settings["interval"]),
        **settings,
    )


def _groups(
    table: dict, where: str, reader: MapReader, register_map: RegisterMap | None, interval: float
) -> tuple[Group, ...]:
    """A device's poll groups: its own (``groups``, ``once``), else its map's; each planned
    apart, and the points in none its default group at its interval.  None at all: ()."""
    own = [key for key in ("groups", "once") if key in table]
    if own and register_map is None:
        raise UsageError(
            f"{where} {own[0]}: groups are of a map's points; a device with read = [...] has none"
        )
    points = {point.name: point for point in reader.points}

    def fail(key: str, why: str) -> UsageError:
        """``groups.fast.points`` named as its table's key: ``[devices.d.groups.fast] points``."""
        parts = key.split(".", 2)
        if len(parts) == 1:
            return UsageError(f"{where} {key}: {why}")
        inside = f"{where[:-1]}.{parts[0]}.{parts[1]}]"
        return UsageError(f"{inside} {parts[2]}: {why}" if len(parts) == 3 else f"{inside}: {why}")

    if own:
        plans = read_groups(table.get("groups"), table.get("once"), points, fail)
    else:  # the map's, of the points the device reads (``points = [...]`` may pick some)
        given = register_map.groups if register_map else []
        plans = [
            GroupPlan(plan.name, plan.interval, kept)
            for plan in given
            if (kept := tuple(name for name in plan.points if name in points))
        ]
    if not plans:
        return ()
    grouped = {name for plan in plans for name in plan.points}
    rest = tuple(name for name in points if name not in grouped)
    if rest:
        plans.insert(0, GroupPlan(DEFAULT, interval, rest))
    max_gap = register_map.max_gap if register_map else 0
    return tuple(
        Group(plan.name, plan.interval, MapReader([points[name] for name in plan.points], max_gap))
        for plan in plans
    )


def _backoff(settings: dict, table: dict, defaults: dict, where: str) -> None:
    """An offline device is never tried more often than an online one is polled: a max_backoff
    below the interval (thousands of reconnects a second) is refused where it was given, and
    the default, where none was, follows a longer interval."""
    interval, longest = settings["interval"], settings["max_backoff"]
    if "max_backoff" not in table and "max_backoff" not in defaults:
        settings["max_backoff"] = max(longest, interval)
    elif longest < interval:
        source = "" if "max_backoff" in table else " (from [poll])"
        raise UsageError(
            f"{where} max_backoff: {longest:g} s{source} is below its interval, {interval:g} s: an offline "
            f"device would be tried more often than an online one is polled (give {interval:g} or more)"
        )


def _reader(table: dict, where: str, folder: Path, loaded: dict[Path, RegisterMap]) -> MapReader:
    """What the device reads: a map's points (all, or those ``points`` names), or the
    references ``read`` lists, each a point named by its reference.  ``loaded``: the maps
    this inventory has loaded so far, by path."""
    if ("map" in table) == ("read" in table):
        raise UsageError(f"{where}: give either map (a register map) or read (references with counts)")
    if "map" in table:
        if not isinstance(table["map"], str):
            raise UsageError(f"{where} map: expected the path of a register map")
        names = table.get("points", [])
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise UsageError(f"{where} points: expected a list of the map's point names")
        try:
            map_path = _map_path(table, folder)
            if map_path not in loaded:
                loaded[map_path] = load_map(map_path)
            register_map = loaded[map_path]
            return MapReader(register_map.select(names), register_map.max_gap)
        except MapError as error:
            raise UsageError(f"{where} map: {error}") from None
    if "points" in table:
        raise UsageError(f"{where} points: picks a map's points; read lists references")
    reads = table["read"]
    if not isinstance(reads, list) or not reads or not all(isinstance(r, str) for r in reads):
        raise UsageError(f'{where} read: expected references with counts, such as ["40001 10"]')
    points: dict[str, Point] = {}
    for text in reads:
        ref, _, count_text = text.strip().partition(" ")
        try:
            table_of, address = parse_reference(ref)
            count = int(count_text, 0) if count_text.strip() else 1
        except (RequestError, ValueError) as error:
            raise UsageError(f"{where} read: {text!r}: {error}") from None
        if not 1 <= count <= 2000 or address + count > 65536:
            raise UsageError(f"{where} read: {text!r}: a count of 1..2000 that stays below 65536")
        for item in range(address, address + count):
            point = Point(reference(table_of, item), table_of, item, "bool" if table_of.bits else "uint16")
            if point.name in points:
                raise UsageError(f"{where} read: {point.name} is read twice")
            points[point.name] = point
    return MapReader(points.values())


def _map_path(table: dict, folder: Path) -> Path:
    """A device's map: its path relative to the inventory's folder, ~ expanded; or a map's
    name (``map = "sdm630"``), looked up in the inventory's folder, the user's and the library."""
    return resolve_map(table["map"], [folder], base=folder)


def _tags(tags, where: str, labels: dict[str, str]) -> dict[str, str]:
    """A device's tags; a fleet label [poll] gives (and instance, always given) is no tag's name:
    a device's records would carry two values of one label."""
    if not isinstance(tags, dict):
        raise UsageError(f'{where} tags: expected a table, such as {{ site = "north" }}')
    reserved = (*RESERVED_TAGS, *labels)
    out = {}
    for key, value in tags.items():
        if not TAG_NAME.fullmatch(key) or key in reserved:
            raise UsageError(
                f"{where} tags: {key!r} is not a tag name (letters, digits and _, not {', '.join(reserved)})"
            )
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise UsageError(f"{where} tags.{key}: expected text or a number")
        text = str(value)
        problem = _tag_value_problem(text)
        if problem:
            raise UsageError(f"{where} tags.{key}: {problem}")
        out[key] = text
    return out


def _tag_value_problem(text: str) -> str:
    """What keeps ``text`` from being a tag's value (influx and Prometheus alike); "" for nothing."""
    if not text or not one_line(text) or text.endswith("\\"):
        return "a tag's value is one line, not empty, no trailing \\"
    return ""


# --- shards: N pollers, each the links whose names hash to its K ------------------------------


def shard_of(name: str, count: int) -> int:
    """The shard of ``count`` a link's name falls in, as Prometheus' ``hashmod`` relabelling
    computes it (model/relabel: the last 8 bytes of the name's MD5 sum, a big-endian uint64,
    modulo the count), so a scrape configuration and the pollers split one inventory alike."""
    import hashlib  # noqa: PLC0415 - OpenSSL's libcrypto, mapped whole: --shard runs only

    return int.from_bytes(hashlib.md5(name.encode()).digest()[8:], "big") % count  # noqa: S324 - a hash to split by, as Prometheus' hashmod


def shard(inventory: Inventory, number: int, count: int) -> Inventory:
    """The part of ``inventory`` shard ``number`` of ``count`` polls: the links whose names hash
    to it, with every device of theirs (a device is never split from its link).  A shard of no
    link is a UsageError: that poller would poll nothing."""
    links = {name: link for name, link in inventory.links.items() if shard_of(name, count) == number}
    if not links:
        raise UsageError(
            f"--shard {number}/{count}: no link of {inventory.path} hashes to {number} "
            f"({len(inventory.links)} links): give fewer shards"
        )
    devices = [device for device in inventory.devices if device.link in links]
    maps = {name: path for name, path in inventory.maps.items() if any(d.name == name for d in devices)}
    return replace(inventory, links=links, devices=devices, maps=maps)
