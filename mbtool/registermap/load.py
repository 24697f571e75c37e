"""Reading a register map: TOML, or CSV with a header row of the same keys plus ``name``.

Everything is checked when the map is loaded, before anything is sent: an
unknown key, a point that overlaps another, a bit of a float, a 32-bit value
that runs past register 65535 — each is one line naming the file, the point
and the key.
"""

from __future__ import annotations

import csv
import io
import math
import tomllib
import unicodedata
from decimal import Decimal, InvalidOperation
from pathlib import Path
from typing import Any

from mbtool.codec.errors import RequestError
from mbtool.codec.record import replace
from mbtool.codec.tables import Table, parse_reference, table_named
from mbtool.codec.values import ORDERS, TYPES, decode_values, encode_values, parse_value
from mbtool.errors import ExitCode, MbtoolError, UsageError
from mbtool.files import read_whole
from mbtool.registermap.groups import GroupPlan, read_groups
from mbtool.registermap.header import HEADER_KEYS, DeviceHeader, device_header
from mbtool.registermap.point import Point

POINT_KEYS = {
    "ref": 'a Modicon reference: 40108, "00001", 4x0108',
    "table": "coils, discrete, input or holding (with address)",
    "address": "the 0-based wire address (with table)",
    "type": "a --type name",
    "order": "ABCD, CDAB, BADC or DCBA",
    "count": "registers of a string",
    "scale": "value = raw × scale + offset",
    "offset": "value = raw × scale + offset",
    "unit": "the unit printed after the value",
    "description": "free text",
    "enum": "labels of raw values (whole numbers; a float's whole values)",
    "bit": "one bit (0-15) of a register",
    "access": "r or rw",
    "warn": "mbtool check's warning range (10, 10:, ~:10, 10:20, @10:20)",
    "crit": "mbtool check's critical range",
    "invalid": "raw values that mean no data, such as [65535] or [0x8000]: no value, never scaled",
    "scale_ref": "the point holding a power-of-ten scale factor (SunSpec's W_SF): value = raw × 10^that",
}
DEVICE_KEYS = ("type", "order", "access", "max_gap", "invalid")
NUMERIC_TYPES = [name for name in TYPES if name not in ("hex", "string")]
CSV_CELL_LIMIT = 128 * 1024  # characters: the csv module's own limit for a field


class MapError(MbtoolError, ValueError):
    """A map that cannot be used: exit 2, nothing sent."""

    exit_code = ExitCode.USAGE


class RegisterMap:
    def __init__(
        self,
        points: dict[str, Point],
        max_gap: int = 0,
        source: str = "",
        header: DeviceHeader | None = None,
        groups: list[GroupPlan] | None = None,
    ) -> None:
        self.points = points
        self.max_gap = max_gap
        self.source = source
        self.header = header  # what [device] says of the device (registermap/header.py), if anything
        self.groups = groups or []  # its poll groups (registermap/groups.py), for mbtool poll

    def select(self, names: tuple[str, ...] | list[str]) -> list[Point]:
        """The named points, in the order given; every point when none is named."""
        if not names:
            return list(self.points.values())
        unknown = [name for name in names if name not in self.points]
        if unknown:
            known = ", ".join(self.points)
            raise MapError(f"{self.source}: no point named {', '.join(unknown)} (the map has {known})")
        return [self.points[name] for name in names]


def load_map(path: str | Path) -> RegisterMap:
    path = Path(path)
    try:
        text = read_whole(path, "map").decode("utf-8")
    except UsageError as error:
        raise MapError(str(error)) from None
    except UnicodeDecodeError as error:
        raise MapError(f"{path}: not UTF-8 text (byte {error.start})") from None
    text = text.removeprefix("\ufeff")  # a byte order mark (Excel's "CSV UTF-8") is no text
    groups: dict = {}  # a map's poll groups: its groups table and its once list, as given
    if path.suffix.lower() == ".csv":
        device: dict = {}
        rows = _csv_rows(path, text)
    else:
        try:
            document = tomllib.loads(text)
        except tomllib.TOMLDecodeError as error:
            raise MapError(f"{path}: not a valid TOML map: {error}") from None
        except RecursionError:  # tomllib parses arrays and tables inside one another recursively
            raise MapError(
                f"{path}: nested too deeply to be a map (arrays or tables inside one another)"
            ) from None
        unknown = set(document) - {"device", "points", "groups", "once"}
        if unknown:
            raise MapError(
                f"{path}: unknown section {sorted(unknown)[0]} (a map has [device], [points.NAME], "
                "and poll groups: [groups.NAME], once)"
            )
        device, rows = document.get("device", {}), document.get("points", {})
        if not isinstance(rows, dict) or not all(isinstance(row, dict) for row in rows.values()):
            raise MapError(f"{path}: points are tables: [points.NAME] with keys such as ref and type")
        groups = {key: document[key] for key in ("groups", "once") if key in document}
    return build_map(path, device, rows, groups)


def build_map(
    path: Path | str, device: dict, rows: dict[str, dict], groups: dict | None = None
) -> RegisterMap:
    """A map from its [device] table and its points' rows, as a file gives them (``path``
    names it in every error): what ``load_map`` makes of a file, and ``mbtool sunspec`` of
    what it found."""
    defaults = _device(path, device)
    max_gap = defaults.pop("max_gap", 0)
    header = {key: defaults.pop(key) for key in HEADER_KEYS if key in defaults}
    points = {name: _point(path, name, row, defaults) for name, row in rows.items()}
    if not points:
        raise MapError(f"{path}: the map has no points")
    _check_overlaps(path, points.values())
    _link_scale_refs(path, points, rows)

    def fail(key: str, why: str) -> MapError:
        return MapError(f"{path}: [device]: key {key}: {why}")

    def probe(name: str, row: dict) -> Point:
        if "scale_ref" in row:  # a probe's own keys are checked by device_header; this one is a point's
            raise fail(name, "a probe reads its registers as they are: no scale_ref")
        return _point(path, f"[device] {name}", row, defaults)

    def group_fail(key: str, why: str) -> MapError:
        return MapError(f"{path}: {key}: {why}")

    groups = groups or {}
    plans = read_groups(groups.get("groups"), groups.get("once"), points, group_fail)
    return RegisterMap(points, max_gap, str(path), device_header(header, probe, fail), plans)


def _csv_rows(path: Path, text: str) -> dict[str, dict]:
    """The rows by the csv module's rules: read as from a file opened with newline="", so a
    quoted newline stays in its cell and only CR and LF end a row (not U+2028, which
    str.splitlines would split at)."""
    # csv refuses a field over its limit with no word of which; so the limit is lifted
    # while this file is read, and a cell over it is refused below by its key.
    limit = csv.field_size_limit(max(len(text), CSV_CELL_LIMIT))
    reader = csv.reader(io.StringIO(text, newline=""))
    try:
        header = [cell.strip() for cell in next(reader, [])]
        table: list[tuple[int, list[str]]] = []
        line = reader.line_num + 1
        for cells in reader:
            table.append((line, cells))
            line = reader.line_num + 1
    except csv.Error as error:
        raise MapError(f"{path}: line {reader.line_num}: not valid CSV: {error}") from None
    finally:
        csv.field_size_limit(limit)
    _csv_header(path, header)
    rows: dict[str, dict] = {}
    for line, cells in table:
        if not any(cell.strip() for cell in cells):
            continue  # an empty row, as spreadsheets leave at the end
        if len(cells) > len(header):
            raise MapError(f"{path}: line {line} has more cells than the header")
        row = dict(zip(header, (cell.strip() for cell in cells), strict=False))
        unnamed = [i + 1 for i, cell in enumerate(cells) if not header[i] and cell.strip()]
        if unnamed:
            raise MapError(f"{path}: line {line}: a cell under no column name (column {unnamed[0]})")
        name = row.pop("name", "")
        if len(name) > CSV_CELL_LIMIT:
            raise MapError(f"{path}: line {line}: key name: a name of {len(name)} characters")
        if not name:
            raise MapError(f"{path}: line {line} has no name")
        if name in rows:
            raise MapError(f"{path}: line {line}: point {name} is named twice")
        for key, value in row.items():
            if len(value) > CSV_CELL_LIMIT:
                raise MapError(
                    f"{path}: line {line}: point {name}: key {key}: a cell of {len(value)} characters, "
                    f"over csv's limit of 128 KiB ({CSV_CELL_LIMIT})"
                )
        cells_given: dict[str, Any] = {key: value for key, value in row.items() if key and value}
        if "enum" in cells_given:
            cells_given["enum"] = _csv_enum(path, name, cells_given["enum"])
        rows[name] = cells_given
    return rows


def _csv_header(path: Path, header: list[str]) -> None:
    """Every column is a key a point may have, once; a column with no name is left alone
    only while its cells are empty (a spreadsheet's trailing commas)."""
    if "name" not in header:
        if len(header) == 1 and ";" in header[0]:
            raise MapError(f"{path}: line 1: columns are separated by commas, and this header has semicolons")
        raise MapError(f"{path}: the first row names the columns, one of them name")
    for i, key in enumerate(header):
        if key and key in header[:i]:
            raise MapError(f"{path}: line 1: column {key} is named twice")
        if key and key != "name" and key not in POINT_KEYS:
            raise MapError(f"{path}: line 1: unknown column {key} (known: name, {', '.join(POINT_KEYS)})")


def _csv_enum(path: Path, name: str, text: str) -> dict:
    """``0=stopped; 1=running`` in a CSV cell."""
    labels = {}
    for part in text.split(";"):
        raw, sep, label = part.partition("=")
        if not sep:
            raise MapError(f"{path}: point {name}: key enum: write it as 0=stopped; 1=running")
        if raw.strip() in labels:
            raise MapError(f"{path}: point {name}: key enum: raw value {raw.strip()} is labelled twice")
        labels[raw.strip()] = label.strip()
    return labels


def _device(path: Path | str, device: object) -> dict:
    if not isinstance(device, dict):
        raise MapError(f"{path}: [device] is a table of defaults ({', '.join(DEVICE_KEYS)})")
    for key in device:
        if key not in DEVICE_KEYS and key not in HEADER_KEYS:
            known = ", ".join([*DEVICE_KEYS, *HEADER_KEYS])
            raise MapError(f"{path}: [device]: unknown key {key} (known: {known})")
    defaults = dict(device)
    if "max_gap" in defaults:
        defaults["max_gap"] = _integer(path, "[device]", "max_gap", defaults["max_gap"], 0, 2000)
    return defaults


def _point(path: Path | str, name: str, row: dict, defaults: dict) -> Point:
    if not name:
        raise MapError(f"{path}: a point with an empty name (read, check and the monitoring formats show it)")
    if not one_line(name):
        raise MapError(f"{path}: point {name!r}: the name {ONE_LINE}")
    where = f"{path}: {name}" if name.startswith("[") else f"{path}: point {name}"

    def fail(key: str, why: str) -> MapError:
        return MapError(f"{where}: key {key}: {why}")

    for key in row:
        if key not in POINT_KEYS:
            raise MapError(f"{where}: unknown key {key} (known: {', '.join(POINT_KEYS)})")
    table, address = _location(path, name, row, fail)
    # [device] defaults apply where they mean something: a type or order to registers,
    # rw to the tables that can be written.
    if not table.bits:
        row = {key: defaults[key] for key in ("type", "order") if key in defaults} | row
    if table.writable and "access" in defaults:
        row = {"access": defaults["access"]} | row
    if "invalid" in defaults and not table.bits and "bit" not in row and "invalid" not in row:
        # The device's "no data" values are its default type's (uint16 unless [device] says):
        # 0xFFFF is no data in a uint16, and -1 or 65535.0 may be real values of another type.
        device_type = str(defaults.get("type", "uint16")).lower()
        if str(row.get("type", device_type)).lower() == device_type:
            row = {"invalid": defaults["invalid"]} | row
    kind = str(row.get("type", "bool" if table.bits else "uint16")).lower()
    access = str(row.get("access", "r")).lower()
    if access not in ("r", "rw"):
        raise fail("access", f"{row['access']} is neither r nor rw")
    if access == "rw" and not table.writable:
        raise fail("access", f"{table.items} are read-only")
    unit = _string(row, "unit", fail)
    if not one_line(unit):
        raise fail("unit", f"{unit!r} {ONE_LINE}")
    options: dict[str, Any] = {
        "unit": unit,
        "description": _string(row, "description", fail),
        "writable": access == "rw",
        "warn": _range(row, "warn", fail),
        "crit": _range(row, "crit", fail),
    }
    if table.bits:
        for key in ("order", "count", "scale", "offset", "enum", "bit", "invalid", "scale_ref"):
            if key in row:
                raise fail(key, f"{table.items} hold one bit each; {key} is for registers")
        if kind != "bool":
            raise fail("type", f"{table.items} hold one bit each, not {kind}")
        return Point(name, table, address, "bool", **options)
    if kind not in TYPES:
        raise fail("type", f"unknown type {kind} (known: {', '.join(TYPES)})")
    order = str(row.get("order", "ABCD")).upper()
    if order not in ORDERS:
        raise fail("order", f"unknown order {row['order']} (known: {', '.join(ORDERS)})")
    count = 1
    if kind == "string":
        if "count" not in row:
            raise fail("count", "a string needs count, the registers it spans (2 characters each)")
        count = _integer(path, name, "count", row["count"], 1, 125)
    elif "count" in row:
        raise fail("count", f"count is for strings; a {kind} spans {TYPES[kind].registers} register(s)")
    bit = None
    if "bit" in row:
        if TYPES[kind].registers != 1 or kind not in ("uint16", "int16", "hex"):
            raise fail("bit", f"a bit is one of a 16-bit register's bits, not of a {kind}")
        bit = _integer(path, name, "bit", row["bit"], 0, 15)
        for key in ("scale", "offset", "enum", "invalid", "scale_ref"):
            if key in row:
                raise fail(key, f"a bit reads on or off; {key} does not apply")
        kind = "bool"
    scale = _decimal(row, "scale", fail)
    offset = _decimal(row, "offset", fail)
    if scale == 0:
        raise fail("scale", "a scale of 0 makes every value the same")
    if (scale is not None or offset is not None) and kind not in NUMERIC_TYPES:
        raise fail("scale" if scale is not None else "offset", f"a {kind} has no number to scale")
    enum = None
    if "enum" in row:
        if kind not in NUMERIC_TYPES:
            raise fail("enum", f"labels are for numbers, not {kind}")
        enum = _enum(row, kind, fail)
    invalid = _invalid(row, kind, fail) if "invalid" in row else frozenset()
    if "scale_ref" in row:
        _scale_ref(row, kind, fail)
    point = Point(
        name,
        table,
        address,
        kind,
        order,
        count,
        scale,
        offset,
        enum=enum,
        bit=bit,
        invalid=invalid,
        **options,
    )
    if point.end > 65536:
        raise fail(
            "ref" if "ref" in row else "address",
            f"a {point.size}-register {kind} at {point.ref} runs past the last register (65535)",
        )
    return point


def _location(path: Path | str, name: str, row: dict, fail) -> tuple[Table, int]:
    if "ref" in row:
        if "table" in row or "address" in row:
            raise fail("ref", "give either ref or table and address, not both")
        ref = row["ref"]
        if isinstance(ref, bool) or not isinstance(ref, (int, str)):
            raise fail("ref", f'{ref} is not a reference such as 40108 or "00001"')
        try:
            return parse_reference(str(ref))
        except RequestError as error:
            raise fail("ref", str(error)) from None
    if "table" not in row or "address" not in row:
        raise MapError(f"{path}: point {name}: no location: give ref, or table and address")
    try:
        table = table_named(str(row["table"]))
    except RequestError as error:
        raise fail("table", str(error)) from None
    return table, _integer(path, name, "address", row["address"], 0, 65535)


def _integer(path: Path | str, name: str, key: str, value: object, low: int, high: int) -> int:
    where = f"{path}: {name}" if name.startswith("[") else f"{path}: point {name}"
    try:
        number = int(value, 0) if isinstance(value, str) else value
    except ValueError:
        number = None
    if isinstance(number, bool) or not isinstance(number, int) or not low <= number <= high:
        raise MapError(f"{where}: key {key}: {value} is not a whole number in {low}..{high}")
    return number


def _decimal(row: dict, key: str, fail) -> Decimal | None:
    if key not in row:
        return None
    value = row[key]
    if isinstance(value, bool) or not isinstance(value, (int, float, str)):
        raise fail(key, f"{value} is not a number")
    try:
        number = Decimal(str(value))
    except InvalidOperation:
        raise fail(key, f"{value} is not a number") from None
    if not number.is_finite():
        raise fail(key, f"{value} is not a finite number")
    # Values are doubles (point.py): a scale or offset a double cannot hold would fail
    # only once the device was read (decimal.Overflow, a whole number too long to print).
    if math.isinf(float(number)):
        raise fail(key, f"{value} is beyond a double's range (±1.8e308)")
    if key == "scale" and number and float(number) == 0:
        raise fail(key, f"{value} is too small: a double holds it as 0")
    return number


def _range(row: dict, key: str, fail) -> str | None:
    """A threshold range as text; its grammar is mbtool check's to read (the plugin guidelines')."""
    value = row.get(key)
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, (str, int, float)):
        raise fail(key, f"{value} is not a range such as 10, 10:20 or @10:20")
    return str(value)


# Names, units and labels are written on one line in every output: a plain NAME VALUE UNIT
# line, check's plugin line, an InfluxDB line (whose protocol has no escape for a newline:
# it ends the point) and a Prometheus sample.
ONE_LINE = "is written on one line: no control characters (newline, tab...)"


def one_line(text: str) -> bool:
    """No control character, line or paragraph separator: the text stays on its line."""
    return not any(unicodedata.category(char) in ("Cc", "Zl", "Zp") for char in text)


def name_problem(name: str, what: str, influx: bool) -> str:
    """Why ``name`` (``what``: "a measurement", "a tag or label") cannot be written in InfluxDB's
    line protocol (``influx``) or Prometheus's text; "" when it can.

    Each is written on one line: the line protocol has no escape for a newline, which would
    end the point and make the rest a point of its own (in a measurement of its own).  It
    cannot be empty; to InfluxDB a measurement starting with # makes the line a comment."""
    if not name:
        return f"{what} has a name"
    if not one_line(name):
        return f"{what} is written on one line: no control characters"
    if influx and what == "a measurement" and name.startswith("#"):
        return "a line starting with # is a comment to InfluxDB"
    if influx and name.endswith("\\"):
        # Even doubled: InfluxDB 1.x (and line_protocol_parser) take the character after a
        # backslash in a measurement or tag value as escaped, the separator too.
        return f"a backslash at the end of {what} escapes the separator after it to InfluxDB 1.x"
    return ""


def _string(row: dict, key: str, fail) -> str:
    value = row.get(key, "")
    if not isinstance(value, str):
        raise fail(key, f"{value} is not text")
    return value


def _as_held(kind: str, value):
    """A raw value as the point's type reads it: a signed type's bit pattern written as an
    unsigned number (0x8000, SunSpec's int16 'not implemented') is its negative value."""
    bits = 16 * TYPES[kind].registers
    signed = TYPES[kind].fmt.islower() and TYPES[kind].fmt not in ("f", "d")
    if signed and isinstance(value, int) and 1 << (bits - 1) <= value < 1 << bits:
        return value - (1 << bits)
    return value


def _held_exactly(kind: str, number, key: str, fail):
    """``number`` as the point's type holds it, refused under ``key`` when the type cannot
    hold it exactly (a float32 past 2**24 skips whole numbers) or at all."""
    try:
        held = decode_values(encode_values([parse_value(str(number), kind)], kind), kind)[0]
    except RequestError as error:
        raise fail(key, str(error)) from None
    if held != number:
        raise fail(key, f"a {kind} cannot hold {number}: the nearest it holds is {held}")
    return held


def _invalid(row: dict, kind: str, fail) -> frozenset:
    """The raw values a device sends for "no data" (0xFFFF from a meter at night, 0x8000 for
    SunSpec's int16, NaN for its float32), each one the point's type holds; for a string,
    "" (registers of NUL only: SunSpec's unimplemented string)."""
    values = row["invalid"]
    if kind == "string":
        if values != [""]:
            raise fail("invalid", 'a string\'s no data is [""]: registers holding NUL bytes only')
        return frozenset(values)
    if kind not in NUMERIC_TYPES:
        raise fail("invalid", f"a {kind} has no number that could mean no data")
    if not isinstance(values, list) or not values:
        raise fail("invalid", "a list of raw values, such as [65535] or [0x8000]")
    out = set()
    for value in values:
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise fail("invalid", f"{value!r} is not a number")
        value = _as_held(kind, value)
        if isinstance(value, float) and math.isnan(value):
            if TYPES[kind].fmt not in ("f", "d"):
                raise fail("invalid", f"a {kind} holds no NaN")
            out.add(value)  # Point.is_invalid looks for a NaN as NaN
            continue
        out.add(_held_exactly(kind, value, "invalid", fail))
    return frozenset(out)


def _scale_ref(row: dict, kind: str, fail) -> None:
    """What a point's own keys say of its scale_ref; the point it names is checked once
    every point is read (``_link_scale_refs``)."""
    name = row["scale_ref"]
    if not isinstance(name, str) or not name:
        raise fail("scale_ref", f"{name!r} is not a point's name")
    if kind not in NUMERIC_TYPES:
        raise fail("scale_ref", f"a {kind} has no number to scale")
    for key in ("scale", "offset"):
        if key in row:
            raise fail("scale_ref", f"the scale is read from {name}; {key} does not go with it")


def _link_scale_refs(path: Path | str, points: dict[str, Point], rows: dict[str, dict]) -> None:
    """Each scale_ref names a point of the map that holds a whole number and is read as it
    is: a SunSpec sunssf register (int16, -10..10)."""
    for name, row in rows.items():
        if "scale_ref" not in row:
            continue
        where = f"{path}: point {name}: key scale_ref"
        target = points.get(row["scale_ref"])
        if target is None:
            raise MapError(f"{where}: the map has no point named {row['scale_ref']}")
        if target.name == name:
            raise MapError(f"{where}: a point cannot be its own scale factor")
        if target.is_bit or target.type not in NUMERIC_TYPES or not TYPES[target.type].integer:
            raise MapError(f"{where}: {target.name} is not a whole number (a scale factor is an int16)")
        if target.scale is not None or target.offset is not None or target.enum is not None:
            raise MapError(f"{where}: {target.name} is scaled or labelled; a scale factor is read as it is")
        if "scale_ref" in rows[target.name]:
            raise MapError(
                f"{where}: {target.name} has a scale_ref of its own; a scale factor is read as it is"
            )
        points[name] = replace(points[name], scale_ref=target)


def _enum(row: dict, kind: str, fail) -> dict[int, str]:
    """Labels of whole raw values, each one the type holds: on a float point they label
    the float's whole values (2.0 is 2), and a fraction has no label."""
    labels = row["enum"]
    if not isinstance(labels, dict) or not labels:
        raise fail("enum", 'a table of labels: enum = { 0 = "stopped", 1 = "running" }')
    out: dict[int, str] = {}
    for raw, label in labels.items():
        try:
            number = int(str(raw), 0)
        except ValueError:
            raise fail("enum", f"{raw} is not a whole number") from None
        if number in out:
            raise fail("enum", f"raw value {number} is labelled twice ({out[number]} and {label})")
        _held_exactly(kind, number, "enum", fail)
        if not isinstance(label, str) or not label:
            raise fail("enum", f"the label of {raw} is not text")
        if not one_line(label):
            raise fail("enum", f"{label!r} {ONE_LINE}")
        if label.lower() in (known.lower() for known in out.values()):
            raise fail("enum", f"the label {label} is given twice")
        out[number] = label
    return out


def _check_overlaps(path: Path | str, points) -> None:
    """Two points may share a register only as different bits of it."""
    by_table: dict[str, list[Point]] = {}
    for point in points:
        by_table.setdefault(point.table.name, []).append(point)
    for table_points in by_table.values():
        table_points.sort(key=lambda p: (p.address, p.end))
        for before, after in zip(table_points, table_points[1:], strict=False):
            if after.address >= before.end:
                continue
            if before.bit is not None and after.bit is not None and before.address == after.address:
                if before.bit != after.bit:
                    continue
                raise MapError(
                    f"{path}: point {after.name}: key bit: bit {after.bit} of {after.ref} is also point {before.name}"
                )
            raise MapError(
                f"{path}: point {after.name}: key ref: {after.ref} overlaps point {before.name} "
                f"({before.ref}, {before.size} {before.table.item}{'s' if before.size > 1 else ''})"
            )
