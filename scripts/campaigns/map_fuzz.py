#!/usr/bin/env python3
"""Map fuzz: random and mutated register maps fed to read -m, write -m, check -m and diff -m.

Each map (TOML or CSV) starts as a valid one with random points and is then bent:
deep nesting, huge and odd scale and offset, unicode, control characters and empty
strings in names, byte order marks, duplicate enum values, wrong types of every key,
overlaps, truncation and flipped bytes.  Each of the four commands runs against a
recording proxy in front of ``mbtool serve``, which counts connections and bytes.

Faults: a traceback (MBTOOL_DEBUG=1 turns an internal error into one), a run past its
deadline, and a run that connected or sent a byte when the map was one the loader
refuses, or that refused its input (exit 2) after it had connected.
"""

from __future__ import annotations

import csv
import io
import random
from collections import Counter
from pathlib import Path

import common
import tomli_w

HOSTILE_TEXT = [
    "",
    " ",
    "\x00",
    "\x1b[31mred",
    "a\nb",
    "a\r\nb",
    "tab\there",
    "\u2028",
    "\ufeff",
    "\u202eevil",
    "é",
    "温度",
    "🙂",
    "a" * 5000,
    "back\\slash",
    'quo"te',
    "com,ma",
    "semi;colon",
    "eq=ual",
    "#hash",
    "[points.x]",
    "1=a; 1=b",
    "x\x7fy",
    "\ud7ff",
]
ODD_NUMBERS = [
    0,
    -0.0,
    1,
    -1,
    1e308,
    -1e308,
    1.7976931348623157e308,
    5e-324,
    1e-320,
    float("inf"),
    float("-inf"),
    float("nan"),
    10**400,
    -(10**400),
    2**63,
    2**64,
    "1e5000",
    "1e-5000",
    "-1e400",
    "nan",
    "inf",
    "0x10",
    "1_000",
    " 2 ",
    "",
    "one",
    True,
    [],
    {},
    "1e309",
    "0.1",
    "1/3",
]
ODD_REFS = [0, 1, 40000, 40001, 465536, 465537, -1, 1.5, "", "abc", True, 10**30, "4x0108", "00000", "99999"]
ODD_VALUES = ["1", "0", "-1", "on", "off", "1e999", "1e999999", "-1e-999999", "1e-400", "nan", "inf", "-inf"]
ODD_VALUES += ["0x10", "65536", "1.5", "", "é", "\x00", "1_0", "٣", "1e308", "-0", "0b1", "+5"]
TABLES = (("coils", 0), ("discrete", 10000), ("input", 30000), ("holding", 40000))
TYPES = ("uint16", "int16", "uint32", "int32", "float32", "uint64", "int64", "float64", "hex", "string")
SIZE = {"uint32": 2, "int32": 2, "float32": 2, "uint64": 4, "int64": 4, "float64": 4}
COMMANDS = ("read", "write", "check", "diff")


def odd(rng: random.Random) -> object:
    pick = rng.random()
    if pick < 0.4:
        return rng.choice(ODD_NUMBERS)
    if pick < 0.7:
        return rng.choice(HOSTILE_TEXT)
    if pick < 0.85:
        return rng.choice(ODD_REFS)
    return rng.choice([None, [1, 2], {"a": 1}, [[[]]], "x" * rng.randint(1, 300)])


def valid_points(rng: random.Random) -> dict[str, dict]:
    """A valid map's points: registers and bits at addresses that do not overlap."""
    points: dict[str, dict] = {}
    cursor = {name: rng.randint(0, 90) for name, _ in TABLES}
    for i in range(rng.randint(1, 8)):
        table, base = rng.choice(TABLES)
        point: dict = {}
        address = cursor[table]
        if table in ("coils", "discrete"):
            size = 1
        else:
            kind = rng.choice(TYPES)
            size = SIZE.get(kind, 1)
            if kind == "string":
                size = rng.randint(1, 4)
                point["count"] = size
            if kind != "uint16" or rng.random() < 0.3:
                point["type"] = kind
            if size > 1 and rng.random() < 0.5:
                point["order"] = rng.choice(["ABCD", "CDAB", "BADC", "DCBA"])
            if kind not in ("hex", "string"):
                if rng.random() < 0.4:
                    point["scale"] = rng.choice([0.1, 10, 0.01, 2, -1, 0.5])
                if rng.random() < 0.3:
                    point["offset"] = rng.choice([-40, 1.5, 100, 0])
                if rng.random() < 0.3 and "scale" not in point and "offset" not in point:
                    point["enum"] = {str(v): f"state{v}" for v in rng.sample(range(0, 8), 3)}
            if (
                kind in ("uint16", "int16")
                and rng.random() < 0.2
                and not point.keys() & {"scale", "offset", "enum"}
            ):
                point["bit"] = rng.randint(0, 15)
            if rng.random() < 0.3:
                point["unit"] = rng.choice(["V", "A", "m3/h", "%", "°C"])
        if rng.random() < 0.5:
            ref = f"{base + address + 1:05d}"  # coils' references are written as strings: "00001"
            point["ref"] = int(ref) if base and rng.random() < 0.5 else ref
        else:
            point["table"], point["address"] = table, address
        if table in ("coils", "holding") and rng.random() < 0.7:
            point["access"] = "rw"
        if rng.random() < 0.2:
            point["description"] = rng.choice(["Outlet flow", "Phase 1 voltage", "état"])
        if rng.random() < 0.25:
            point["warn"] = rng.choice(["10", "10:", "~:10", "10:20", "@10:20"])
        if rng.random() < 0.2:
            point["crit"] = rng.choice(["20", "5:", "~:30", "0:100"])
        cursor[table] = address + size + rng.randint(0, 5)
        points[rng.choice(["flow", "volt", "state", "pump", "temp", "p"]) + str(i)] = point
    return points


ODD_BUT_VALID_NUMBERS = [
    1e300,
    -1e300,
    1e-300,
    1.7976931348623157e308,
    2.2250738585072014e-308,
    -0.001,
    3,
    1e20,
]


def bend_points(rng: random.Random, points: dict[str, dict], device: dict) -> None:
    """Odd things a valid map may hold: scales near a double's ends, names and text in any script
    or with control characters, many labels, the widest gap."""
    for name in list(points):
        point = points[name]
        if rng.random() < 0.3 and point.get("type") not in ("hex", "string") and "bit" not in point:
            table = point.get("table") or str(point.get("ref", "4"))[0]
            if table not in ("coils", "discrete", "0", "1"):
                point[rng.choice(["scale", "offset"])] = rng.choice(ODD_BUT_VALID_NUMBERS)
                point.pop("enum", None)
        if rng.random() < 0.2:
            point[rng.choice(["unit", "description"])] = rng.choice(HOSTILE_TEXT)
        if rng.random() < 0.15:
            points[rng.choice(HOSTILE_TEXT) + name] = points.pop(name)
    if rng.random() < 0.1:
        device["max_gap"] = 2000


def mutate_points(rng: random.Random, points: dict[str, dict], device: dict) -> None:
    """Structural mutations that break a map: odd keys and values, overlaps, enums labelled twice."""
    for _ in range(rng.randint(1, 3)):
        if not points:
            break
        name = rng.choice(list(points))
        point = points[name]
        if not isinstance(point, dict):  # bent into no table already
            continue
        what = rng.random()
        if what < 0.15:  # an odd name
            points[rng.choice(HOSTILE_TEXT) + rng.choice(["", name])] = points.pop(name)
        elif what < 0.45:  # an odd value in a known key
            key = rng.choice(
                ["ref", "table", "address", "type", "order", "count", "scale", "offset", "unit"]
                + ["description", "enum", "bit", "access", "warn", "crit"]
            )
            if key in ("scale", "offset") and rng.random() < 0.7:
                point[key] = rng.choice(ODD_NUMBERS)
            else:
                point[key] = odd(rng)
        elif what < 0.55:  # labels given twice, or labels the type cannot hold
            point["enum"] = rng.choice(
                [
                    {"1": "a", "01": "b"},
                    {"1": "a", "0x1": "b"},
                    {"1": "on", "2": "ON"},
                    {"1": "a", "2": "a"},
                    {"70000": "big"},
                    {"-1": "neg"},
                    {"16777217": "past float32"},
                    {"1.5": "half"},
                    {"1": ""},
                    {"1": 5},
                    {},
                    {"99999999999999999999999": "huge"},
                ]
            )
        elif what < 0.65:  # an unknown key
            point[rng.choice(["Ref", "scaling", "", "name", "\x00", "points"])] = 1
        elif what < 0.75:  # a second point on the same place
            points[name + "_twin"] = dict(point)
        elif what < 0.85:  # a point that is no table
            points[name] = odd(rng)
        else:  # the [device] defaults
            device[rng.choice(["type", "order", "access", "max_gap", "unit"])] = odd(rng)


def deep(rng: random.Random) -> str:
    """TOML nested past any reasonable depth: arrays, inline tables or dotted keys."""
    depth = rng.choice([100, 1000, 10000, 100000])
    return rng.choice(
        [
            "[points.x]\nref = 40001\ndescription = " + "[" * depth + "]" * depth + "\n",
            "[points.x]\nref = 40001\nenum = " + "{a=" * depth + "1" + "}" * depth + "\n",
            "[points]\n" + ".".join(["a"] * depth) + " = 1\n",
            "x = " + "[" * depth + "\n",
        ]
    )


def to_toml(points: dict, device: dict) -> str:
    document = {"points": points} | ({"device": device} if device else {})
    try:
        return tomli_w.dumps(_clean(document))
    except (TypeError, ValueError):
        return ""


def _clean(value: object) -> object:
    """What TOML can carry: None becomes an empty table, whole numbers past 64 bits text."""
    if value is None:
        return {}
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_clean(v) for v in value]
    if isinstance(value, int) and not isinstance(value, bool) and not -(2**63) <= value < 2**63:
        return str(value)
    return value


def to_csv(points: dict, rng: random.Random) -> str:
    rows = [p for p in points.values() if isinstance(p, dict)]
    columns = ["name"] + sorted({key for p in rows for key in p})
    out = io.StringIO(newline="")
    writer = csv.writer(out, lineterminator=rng.choice(["\n", "\r\n"]))
    writer.writerow(columns)
    for name, point in points.items():
        if not isinstance(point, dict):
            continue
        cells = [name]
        for key in columns[1:]:
            value = point.get(key, "")
            if isinstance(value, dict):
                value = "; ".join(f"{k}={v}" for k, v in value.items())
            cells.append(str(value))
        writer.writerow(cells)
    return out.getvalue()


def mutate_text(rng: random.Random, text: str, kind: str) -> bytes:
    """Textual mutations: BOMs, control characters, truncation, flipped bytes, odd line ends."""
    data = text.encode("utf-8", errors="surrogatepass")
    for _ in range(rng.randint(0, 3)):
        what = rng.random()
        spot = rng.randint(0, len(data))
        if what < 0.15:
            data = rng.choice([b"\xef\xbb\xbf", b"\xef\xbb\xbf\xef\xbb\xbf", b"\xff\xfe"]) + data
        elif what < 0.3:
            data = (
                data[:spot]
                + rng.choice([b"\x00", b"\r", b"\x1b", b"\x7f", b"\xe2\x80\xa8", b"\x0c"])
                + data[spot:]
            )
        elif what < 0.4:
            data = data[:spot]
        elif what < 0.55 and data:
            at = rng.randrange(len(data))
            data = data[:at] + bytes([data[at] ^ (1 << rng.randrange(8))]) + data[at + 1 :]
        elif what < 0.65:
            lines = data.split(b"\n")
            line = rng.randrange(len(lines))
            lines.insert(line, lines[line])
            data = b"\n".join(lines)
        elif what < 0.75:
            data = data.replace(b"\n", rng.choice([b"\r", b"\r\n", b"\n\n"]))
        elif what < 0.85 and kind == "csv":
            data = data.replace(b",", rng.choice([b";", b"\t", b',"', b",,"]), rng.randint(1, 3))
        elif kind == "csv":
            data += rng.choice([b'"unterminated\n', b"x," * 50 + b"\n", b"," * 5 + b"\n", b'"a""b",1\n'])
        else:
            data += rng.choice([b"[points.x]\n", b"ref = 1\n", b"= 1\n", b'"\n', b"[[points]]\n"])
    return data


def make_map(rng: random.Random, folder: Path, index: int) -> tuple[Path, list[str], list[str]]:
    """A map file, the names its points had before they were bent and those marked rw."""
    points = valid_points(rng)
    names = list(points)
    writable = [name for name, point in points.items() if point.get("access") == "rw"]
    kind = "csv" if rng.random() < 0.35 else "toml"
    device: dict = {}
    if kind == "toml" and rng.random() < 0.3:
        device = {"order": rng.choice(["ABCD", "CDAB"]), "max_gap": rng.randint(0, 10)}
    bend_points(rng, points, device)
    if rng.random() < 0.5:
        mutate_points(rng, points, device)
    if kind == "toml" and rng.random() < 0.07:
        text = deep(rng)
    else:
        text = to_toml(points, device) if kind == "toml" else to_csv(points, rng)
    data = mutate_text(rng, text, kind) if rng.random() < 0.3 else text.encode("utf-8", "surrogatepass")
    path = folder / f"map{index}.{kind}"
    path.write_bytes(data)
    return path, names, writable


def refused_by_loader(path: Path) -> tuple[bool, str]:
    """Whether mbtool's map loader refuses the map (the one place its rules live)."""
    from mbtool.registermap.load import load_map

    try:
        load_map(path)
    except Exception as error:  # a MapError, or the loader's own bug: either way not a usable map
        return True, f"{type(error).__name__}: {error}"[:300]
    return False, ""


def command(
    rng: random.Random, which: str, path: Path, names: list[str], writable: list[str], dump: Path
) -> list[str]:
    chosen = rng.sample(names, rng.randint(0, min(3, len(names)))) if names else []
    if rng.random() < 0.1:
        chosen.append(rng.choice(HOSTILE_TEXT[:12]))
    if which == "read":
        fmt = rng.choice(
            [[], ["-o", "json"], ["-o", "csv"], ["-o", "influx"], ["-o", "prom"], ["-o", "plain"]]
        )
        return ["read", "-m", str(path), *chosen, *fmt]
    if which == "write":
        if writable and rng.random() < 0.9:
            chosen = rng.sample(writable, rng.randint(1, len(writable)))
        plain = ["1", "2", "10", "0", "on", "off", "state1", "state2", "0.5", "-3"]
        pairs = [f"{name}={rng.choice(ODD_VALUES if rng.random() < 0.3 else plain)}" for name in chosen]
        return ["write", "-m", str(path), *(pairs or [f"{names[0] if names else 'x'}=1"])]
    if which == "check":
        limits = rng.choice([[], ["-w", "10"], ["-w", "10:20", "-c", "~:30"], ["-c", "@1:2"]])
        return ["check", "-m", str(path), *chosen, *limits]
    return ["diff", "-m", str(path), str(dump)]


def main() -> None:
    args = common.arguments(__doc__, maps=(int, 60, "maps to try (each with all four commands)"))
    rng = random.Random(args.seed)
    report = common.Report("map fuzz", args.verbose)
    codes: dict[str, Counter] = {which: Counter() for which in COMMANDS}
    refused_maps = tracebacks = hangs = 0
    sent_while_refused = sent_then_refused = runs = 0
    with common.scratch("maps") as folder, common.serve() as device:
        folder = Path(folder)
        dump = folder / "dump.toml"
        dump.write_text(
            "sparse = true\n[holding_registers]\n0 = ["
            + ", ".join(str(i) for i in range(100))
            + "]\n[coils]\n0 = [1, 0, 1, 1]\n[input_registers]\n0 = [1000, 1001]\n"
        )
        proxy = common.RecordingProxy((device.host, device.port))
        try:
            for index in range(args.maps):
                path, names, writable = make_map(rng, folder, index)
                refused, why = refused_by_loader(path)
                refused_maps += refused
                for which in COMMANDS:
                    # A command line cannot carry NUL: names holding one are typed without it.
                    argv = [
                        arg.replace("\x00", "") for arg in command(rng, which, path, names, writable, dump)
                    ]
                    proxy.take()
                    result = common.run(*argv, "-p", proxy.target, "-t", "2")
                    connections, sent, _ = proxy.take()
                    runs += 1
                    codes[which]["hang" if result.hung else result.code] += 1
                    shown = f"{result}\n(map {path.name}: {path.read_bytes()[:600]!r})"
                    if result.hung:
                        hangs += 1
                        report.fault("hang", shown)
                    if result.traceback:
                        tracebacks += 1
                        report.fault("traceback", shown)
                    touched = connections or sent
                    if refused and touched:
                        sent_while_refused += 1
                        report.fault("connected while the map was refused", f"{shown}\nloader: {why}")
                    elif result.code == 2 and which != "check" and touched:
                        sent_then_refused += 1
                        report.fault("exit 2 after connecting", shown)
        finally:
            proxy.close()
    report.figure("maps tried", f"{args.maps} ({refused_maps} refused by the loader)")
    report.figure("runs", runs)
    for which in COMMANDS:
        seen = ", ".join(f"{code}: {count}" for code, count in sorted(codes[which].items(), key=str))
        report.figure(f"exit codes, {which} -m", seen)
    report.figure("tracebacks (must be 0)", tracebacks)
    report.figure("runs past the deadline (must be 0)", hangs)
    report.figure("connected or sent while the map was refused (must be 0)", sent_while_refused)
    report.figure("exit 2 after connecting (must be 0)", sent_then_refused)
    report.finish()


if __name__ == "__main__":
    main()
