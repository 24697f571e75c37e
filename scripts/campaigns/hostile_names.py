#!/usr/bin/env python3
"""Influx and Prometheus output with hostile names: maps (TOML and CSV), profiles and
measurements whose names, units, descriptions and labels hold newlines, carriage returns,
backslashes, quotes, commas, spaces, ``=``, ``#``, escape sequences, unicode and empty
strings, read with ``-o influx`` and ``-o prom`` from ``mbtool serve`` through a recording
proxy.

Every line of ``-o influx`` is parsed with line_protocol_parser, every ``-o prom`` output
with prometheus_client's text parser, and what they read is held to what the map says:

* influx: one line a read, the measurement given, tags ``unit`` (and ``device``, the
  profile's name), one field a point named exactly as the point;
* prom: one sample a point, labelled with its ref, ``unit`` (and ``device``), the point's
  description and unit in its family's HELP; families that carry no point (mbtool's own,
  if any) no more than a plain map's output has.

A line or sample more than that, a tag, label or field no point explains, is an injected
one; a name or text that does not read back as written is mangled.  A map or profile
mbtool refuses (exit 2) is a load-time refusal, and must have sent nothing.

Faults: a parse failure, an injected or mangled line, field or metric, a refusal after
connecting, a traceback.
"""

from __future__ import annotations

import csv
import io
import random
from collections import Counter
from pathlib import Path

import common
import tomli_w
from line_protocol_parser import parse_line
from prometheus_client.parser import text_string_to_metric_families

PIECES = [
    "\n",
    "\r",
    "\r\n",
    "\t",
    "\\",
    "\\n",
    '"',
    "'",
    ",",
    " ",
    "=",
    "#",
    "{",
    "}",
    "é",
    "温度",
    "🙂",
    "\u2028",
    "\x1b[1m",
    "\x00",
    "# HELP x y",
    "\nmodbus_injected 1",
    "\nmodbus,injected=1 x=1i",
    " x=1i",
    "a\\",
    "x=1,y=2 3",
    '\\"',
    "",
]
PLAIN = ["flow", "temp", "level", "power", "state"]
# (ref, type): holding registers of the demo data (0..99 hold their address; 100 is float32
# 21.5), a coil; none reads NaN, so every point is a field and a sample.
SLOTS = [("40001", "uint16"), ("40002", "int16"), ("40101", "float32"), ("40004", "uint16"), ("00001", None)]


# Pieces a printed name may well hold: no control character, no line separator.
PRINTABLE = [piece for piece in PIECES if piece.isprintable()]


def hostile_text(rng: random.Random, plain: str, pieces: list[str]) -> str:
    parts = [rng.choice(pieces) for _ in range(rng.randint(1, 3))]
    if plain:
        parts.insert(rng.randint(0, len(parts)), plain)
    return "".join(parts)


class Case:
    """A map of hostile names and text, and the profile and measurement to read it with."""

    def __init__(self, rng: random.Random, folder: Path, index: int) -> None:
        # Half the maps hold printable names only, which must be written as they are; the
        # others control characters and line breaks too, which may also be refused.
        self.printable = rng.random() < 0.5

        def hostile(plain: str = "") -> str:
            return hostile_text(rng, plain, PRINTABLE if self.printable else PIECES)

        self.points: list[dict] = []
        names: set[str] = set()
        for i, (ref, kind) in enumerate(rng.sample(SLOTS, rng.randint(1, len(SLOTS)))):
            name = hostile(rng.choice(["", PLAIN[i]]))
            while name in names:
                name += rng.choice(PRINTABLE) or "_"
            names.add(name)
            point = {"name": name, "ref": ref}
            if kind:
                point["type"] = kind
            if rng.random() < 0.6:
                point["unit"] = hostile(rng.choice(["", "m3/h", "°C"]))
            if rng.random() < 0.6:
                point["description"] = hostile(rng.choice(["", "Outlet flow", "Phase 1"]))
            if kind == "uint16" and rng.random() < 0.4:
                labels = {hostile(f"state{raw}") for raw in range(3)}
                point["enum"] = {str(raw): label for raw, label in enumerate(sorted(labels))}
            self.points.append(point)
        self.kind = "csv" if rng.random() < 0.3 else "toml"
        if self.kind == "csv":  # a CSV map's cells are read stripped of surrounding white space
            for point in self.points:
                for key in ("name", "unit", "description"):
                    if key in point:
                        point[key] = point[key].strip()
        # The measurement and the profile's name are typed on a command line, which cannot carry NUL.
        self.measurement = hostile("plant").replace("\x00", "") if rng.random() < 0.3 else None
        self.profile = hostile("pump house").replace("\x00", "") if rng.random() < 0.3 else None
        self.map = folder / f"hostile{index}.{self.kind}"
        self.map.write_bytes(self._map_text(rng).encode("utf-8", "surrogatepass"))
        self.config = folder / f"config{index}.toml"
        if self.profile is not None:
            self.config.write_text(tomli_w.dumps({"profiles": {self.profile: {"unit": 1}}}))

    def _map_text(self, rng: random.Random) -> str:
        if self.kind == "toml":
            points = {p["name"]: {k: v for k, v in p.items() if k != "name"} for p in self.points}
            return tomli_w.dumps({"points": points})
        columns = ["name", "ref", "type", "unit", "description", "enum"]
        out = io.StringIO(newline="")
        writer = csv.writer(out, lineterminator=rng.choice(["\n", "\r\n"]))
        writer.writerow(columns)
        for point in self.points:
            enum = "; ".join(f"{raw}={label}" for raw, label in point.get("enum", {}).items())
            writer.writerow([point.get(key, "") for key in columns[:-1]] + [enum])
        return out.getvalue()

    def argv(self, fmt: str, target: str) -> list[str]:
        out = ["read", "-m", str(self.map), "-o", fmt, "-p", target]
        if self.measurement is not None:
            out += ["--measurement", self.measurement]
        if self.profile is not None:
            out += ["-P", self.profile]
        return out

    @property
    def names(self) -> set[str]:
        return {p["name"] for p in self.points}

    @property
    def tags(self) -> dict[str, str]:
        return {"unit": "1"} | ({"device": self.profile} if self.profile else {})


def reference_unescaped(text: str) -> str:
    """The line-protocol reference reads two contiguous backslashes as one (the first is an
    escape); line_protocol_parser keeps both, so the rule is applied to what it read."""
    return text.replace("\\\\", "\\")


def judge_influx(case: Case, out: str) -> list[tuple[str, str]]:
    """(fault, why) of one -o influx output."""
    lines = out.split("\n")
    if lines and lines[-1] == "":
        lines.pop()
    faults = []
    if len(lines) != 1:
        faults.append(("injected", f"{len(lines)} lines for one read"))
    for line in lines:
        try:
            parsed = parse_line(line)
        except Exception as error:  # LineFormatError, or whatever else the parser raises
            faults.append(("parse failure", f"{type(error).__name__}: {error}: {line!r}"))
            continue
        if parsed is None:  # what it makes of an empty line
            faults.append(("parse failure", f"no line protocol in {line!r}"))
            continue
        fields = {reference_unescaped(key) for key in parsed["fields"]}
        tags = {reference_unescaped(k): reference_unescaped(v) for k, v in parsed["tags"].items()}
        measurement = reference_unescaped(parsed["measurement"])
        if len(parsed["fields"]) > len(case.names) or set(tags) - set(case.tags):
            extra = sorted(fields - case.names) + sorted(set(tags) - set(case.tags))
            faults.append(("injected", f"fields or tags no point explains: {extra!r}"))
        elif fields != case.names or tags != case.tags or measurement != (case.measurement or "modbus"):
            faults.append(
                ("mangled", f"read {measurement!r} {tags!r} {sorted(fields)!r}; wrote {sorted(case.names)!r}")
            )
    return faults


def families_of(text: str):
    return list(text_string_to_metric_families(text))


SHARED = "shared metric name"  # a note, not a fault: the data model allows it, a reader may wonder


def judge_prom(case: Case, out: str, status_families: int) -> list[tuple[str, str]]:
    """(fault, why) of one -o prom output; SHARED notes points that share one metric name."""
    try:
        families = families_of(out)
    except Exception as error:  # the parser's ValueError, or anything it chokes on
        return [("parse failure", f"{type(error).__name__}: {error}")]
    faults = []
    refs = Counter()
    unexplained = 0
    by_ref = {}
    for family in families:
        carried = [s.labels.get("ref") for s in family.samples if "ref" in s.labels]
        unexplained += not carried
        for sample in family.samples:
            if "ref" in sample.labels:
                refs[sample.labels["ref"]] += 1
                by_ref[sample.labels["ref"]] = family
            labels = {k: v for k, v in sample.labels.items() if k != "ref"}
            if set(labels) - {"unit", "device"}:
                faults.append(("injected", f"a label no point explains: {sample}"))
            elif labels != case.tags:
                faults.append(("mangled", f"labels {labels!r}, not {case.tags!r}"))
    wanted = Counter(p["ref"] for p in case.points)
    if unexplained > status_families or refs - wanted:
        faults.append(
            ("injected", f"samples {dict(refs)!r} and {unexplained} other families; wanted {dict(wanted)!r}")
        )
    elif refs != wanted:
        faults.append(("mangled", f"samples {dict(refs)!r}; wanted {dict(wanted)!r}"))
    for point in case.points:
        family = by_ref.get(point["ref"])
        if family is None:
            continue
        if sum("ref" in sample.labels for sample in family.samples) > 1:
            # Two names made one metric name (both sanitized alike): one HELP for both.
            faults.append((SHARED, f"{family.name} holds the samples of several points"))
            continue
        for key in ("description", "unit"):
            # The text format's parsers strip a line's ends: HELP cannot begin with white space.
            if point.get(key, "").strip() not in family.documentation:
                faults.append(("mangled", f"HELP {family.documentation!r} lacks the {key} {point[key]!r}"))
    return faults


def main() -> None:
    args = common.arguments(__doc__, cases=(int, 100, "maps to try (each read -o influx and -o prom)"))
    rng = random.Random(args.seed)
    report = common.Report("influx/prom with hostile names", args.verbose)
    outputs = Counter()
    refusals = Counter()
    found = Counter()
    codes = Counter()
    with common.scratch("names") as folder, common.serve() as device:
        folder = Path(folder)
        proxy = common.RecordingProxy((device.host, device.port))
        try:
            plain = folder / "plain.toml"
            plain.write_text('[points.flow]\nref = 40001\nunit = "m3/h"\n')
            baseline = common.run("read", "-m", plain, "-o", "prom", "-p", proxy.target)
            if baseline.code != 0:
                common.give_up(f"a plain map cannot be read:\n{baseline}")
            status_families = sum(
                not any("ref" in s.labels for s in family.samples) for family in families_of(baseline.out)
            )
            for index in range(args.cases):
                case = Case(rng, folder, index)
                extra = {"MBTOOL_CONFIG": str(case.config)}
                for fmt in ("influx", "prom"):
                    argv = case.argv(fmt, proxy.target)
                    proxy.take()
                    result = common.run(*argv, extra_env=extra)
                    connections, sent, _ = proxy.take()
                    codes[result.code] += 1
                    shown = f"{result}\n(map {case.map.read_bytes()[:700]!r}, profile {case.profile!r})"
                    if result.traceback:
                        report.fault("traceback", shown)
                        found["traceback"] += 1
                    if result.code == 2:
                        refusals[fmt] += 1
                        if connections or sent:
                            report.fault("refused after connecting", shown)
                            found["refused after connecting"] += 1
                        continue
                    if result.code != 0:
                        continue
                    outputs[fmt] += 1
                    judged = (
                        judge_influx(case, result.out)
                        if fmt == "influx"
                        else judge_prom(case, result.out, status_families)
                    )
                    for kind, why in dict(
                        reversed(judged)
                    ).items():  # each kind once an output, the first why
                        found[f"{fmt} {kind}"] += 1
                        if kind != SHARED:
                            report.fault(f"{fmt} {kind}", f"{why}\n{shown}")
        finally:
            proxy.close()
    report.figure("maps tried", f"{args.cases} (runs {2 * args.cases})")
    report.figure("exit codes", ", ".join(f"{code}: {n}" for code, n in sorted(codes.items(), key=str)))
    report.figure("outputs parsed", f"influx {outputs['influx']}, prom {outputs['prom']}")
    report.figure("load-time refusals (exit 2)", f"influx {refusals['influx']}, prom {refusals['prom']}")
    for fmt in ("influx", "prom"):
        report.figure(f"{fmt} outputs with a parse failure (must be 0)", found[f"{fmt} parse failure"])
        report.figure(
            f"{fmt} outputs with injected lines/fields/metrics (must be 0)", found[f"{fmt} injected"]
        )
        report.figure(f"{fmt} outputs with mangled names or text (must be 0)", found[f"{fmt} mangled"])
    report.figure("prom outputs where points share a metric name (one HELP)", found[f"prom {SHARED}"])
    report.figure("refused after connecting (must be 0)", found["refused after connecting"])
    report.figure("tracebacks (must be 0)", found["traceback"])
    report.finish()


if __name__ == "__main__":
    main()
