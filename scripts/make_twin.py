#!/usr/bin/env python3
"""Write a library map's twin: a sparse ``serve --data`` file holding a plausible value at
every point of the map and every register its signature reads (docs/maps-library.md).

    python scripts/make_twin.py sdm630 > mbtool/library/twins/sdm630.toml
    python scripts/make_twin.py abb-b23 power=-1520.5 --identity vendor_name=ABB

A point takes the value given as NAME=VALUE, else one that fits its unit (230.1 V, 5.2 A,
50.0 Hz...), else its enum's first label, else 1.  A signature probe's registers not held by
a point take what it expects (``equals``: its first value; ``within``: the middle; ``answers``:
1); a ``refuses`` probe's registers stay undefined, so the twin answers exception 02 there,
as the device does.  Only those registers exist (``sparse = true``).  FC 17 and FC 43 are
refused (exception 01) unless --identity gives the FC 43/14 objects the device has.
"""

from __future__ import annotations

import argparse
import sys

from mbtool.codec.values import encode_values
from mbtool.library import load_named_map

# A plausible reading by unit: the nth point of a unit gets a little more, so that three
# phases do not read alike and a point read in another's place is seen.
BY_UNIT = {
    "V": 230.1,
    "A": 5.2,
    "W": 1196.5,
    "kW": 1.2,
    "VA": 1220.0,
    "kVA": 1.22,
    "var": 240.5,
    "kvar": 0.24,
    "Hz": 50.0,
    "kWh": 12345.6,
    "Wh": 123456.0,
    "kvarh": 321.4,
    "°C": 35.5,
    "%": 55.0,
    "s": 3600.0,
    "h": 1234.0,
    "min": 15.0,
    "Ah": 50.0,
    "mA": 12.0,
}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("map", help="a library map's name, or a map file")
    parser.add_argument("values", nargs="*", help="NAME=VALUE: a point's value, in its units")
    parser.add_argument(
        "--identity", nargs="*", default=[], help="KEY=TEXT: FC 43/14 objects (vendor_name=ABB)"
    )
    args = parser.parse_args()
    register_map = load_named_map(args.map)
    given = dict(item.split("=", 1) for item in args.values)
    unknown = set(given) - set(register_map.points)
    if unknown:
        parser.error(f"no point named {sorted(unknown)[0]}")
    tables: dict[str, dict[int, tuple[int | bool, str]]] = {}
    seen_units: dict[str, int] = {}
    for point in register_map.points.values():
        text = given.get(point.name) or _plausible(point, seen_units)
        raw = point.raw_for(text)
        note = f"{point.name} {text} {point.unit}".rstrip()
        if point.table.bits:
            tables.setdefault(point.table.name, {})[point.address] = (bool(raw), note)
            continue
        held = tables.setdefault(point.table.name, {})
        if point.bit is not None:
            word = held.get(point.address, (0, ""))
            value = word[0] | (1 << point.bit) if raw else word[0]
            held[point.address] = (value, f"{word[1]}; {note}".lstrip("; "))
            continue
        words = encode_values([raw], point.type, point.order)
        words += [0] * (point.size - len(words))  # a string's unused registers hold NUL bytes
        for offset, word in enumerate(words):
            held[point.address + offset] = (word, note if offset == 0 else "")
    header = register_map.header
    for probe in header.signature if header else ():
        point = probe.point
        held = tables.setdefault(point.table.name, {})
        span = range(point.address, point.address + point.size)
        if probe.expect == "refuses":
            if any(address in held for address in span):
                sys.exit(f"signature: {probe.describe()}, but a point is there")
            continue
        if any(address in held for address in span):
            continue  # a point holds it: the gates check the point's value fits the probe
        value = probe.wanted[0] if probe.expect == "equals" else 1
        if probe.expect == "within":
            value = sum(probe.wanted) / 2
        value = int(value) if point.type not in ("float32", "float64") else value
        for offset, word in enumerate(encode_values([value], point.type, point.order)):
            held[point.address + offset] = (word, f"signature: {probe.describe()}" if offset == 0 else "")
    print(f"# The twin of map {args.map}: what `mbtool serve --data` answers as that device, made by")
    print("# scripts/make_twin.py; only these registers exist, a read of any other is exception 02.")
    print("sparse = true")
    names = {
        "coils": "coils",
        "discrete": "discrete_inputs",
        "input": "input_registers",
        "holding": "holding_registers",
    }
    for table, held in tables.items():
        print(f"\n[{names[table]}]")
        for address in sorted(held):
            value, note = held[address]
            shown = "true" if value is True else "false" if value is False else f"0x{value:04X}"
            print(f"{address} = {shown}" + (f"  # {note}" if note else ""))
    print("\n[identity]")
    if not args.identity:  # the device answers neither FC 17 nor FC 43, as most meters
        print("refused = [17, 43]")
    for item in args.identity:
        key, _, text = item.partition("=")
        print(f'{key} = "{text}"')
    return 0


def _plausible(point, seen_units: dict[str, int]) -> str:
    if point.table.bits or point.bit is not None:
        return "on"
    if point.enum:
        return next(iter(point.enum.values()))
    if point.type == "string":
        return "A1B2C3"[: point.count * 2]
    nth = seen_units.get(point.unit, 0)
    seen_units[point.unit] = nth + 1
    base = BY_UNIT.get(point.unit)
    if base is None:
        return "1" if point.scale is None else str(point.scale)
    value = base * (1 + 0.01 * nth)
    step = point.scale or 1
    if point.type in ("float32", "float64"):
        return f"{value:.1f}"
    # a whole number of the point's steps
    return str(round(value / float(step)) * step)


if __name__ == "__main__":
    sys.exit(main())
