"""Snapshots of a device: ``diff`` compares a dump with the device or with another dump,
and ``restore`` writes a dump's writable tables back into the device.  ``dump`` writes them
(commands/dump.py); their file is cli/data_files.py's."""

from __future__ import annotations

import sys
from functools import partial
from typing import Any

import click

from mbtool.cli.data_files import TABLE_SECTIONS, snapshot
from mbtool.cli.options import device_command, map_option
from mbtool.cli.param_types import FilePath
from mbtool.cli.results import Listing, change_parts, engineering_unit
from mbtool.cli.session import open_client
from mbtool.cli.sinks import default_format, render
from mbtool.cli.sinks.plain import change_line
from mbtool.cli.writes import CONFIRMED, DIFFERS, Step, failure, report, send_all
from mbtool.codec.data_access import (
    MAX_WRITE_COILS,
    MAX_WRITE_REGISTERS,
    WriteMultipleCoils,
    WriteMultipleRegisters,
)
from mbtool.codec.errors import ModbusException
from mbtool.codec.record import replace
from mbtool.codec.tables import reference, table_named
from mbtool.errors import KNOWN_ERRORS, ExitCode, UsageError, Verdict, exit_code_for
from mbtool.link.dump import Dumper, Span, TableDump, runs_of
from mbtool.words import counted

# --- diff: two snapshots, or a snapshot and the device ------------------------------------


def read_live(execute, wanted: dict[str, dict[int, int]]) -> dict[str, dict[int, int]]:
    """What the device holds at the addresses ``wanted`` lists: each run read exactly (an
    address the device lacks is left out, as a dump would)."""
    dumper = Dumper(execute)
    out: dict[str, dict[int, int]] = {}
    for name, values in wanted.items():
        table = table_named(name)
        into = TableDump(table)
        for first, last in runs_of(sorted(values)):
            dumper.dump(Span(table, first, last), into)
        out[name] = {first + i: int(v) for first, vs in into.runs for i, v in enumerate(vs)}
    return out


def _scale_factor(point, registers: dict) -> int | None:
    """What a scaled point's scale factor (its map's scale_ref) holds in a snapshot's
    registers; None when the point has none or the snapshot lacks it."""
    factor = point.scale_ref
    if factor is None:
        return None
    raw = [registers.get(factor.table.name, {}).get(address) for address in range(factor.address, factor.end)]
    return None if None in raw else factor.value_of(raw)


def differences(a: dict, b: dict, register_map=None) -> list[dict]:
    """Each difference: a map's point (by name, in its units) where one covers the address,
    else the table and address with the raw values; None where a side lacks the address."""
    out: list[dict] = []
    covered: set[tuple[str, int]] = set()
    for point in register_map.points.values() if register_map else ():
        name = point.table.name
        addresses = range(point.address, point.end)
        covered.update((name, address) for address in addresses)
        sides = [[side.get(name, {}).get(address) for address in addresses] for side in (a, b)]
        if sides[0] == sides[1]:
            continue
        values = [
            None if None in raw else point.value_of(raw, _scale_factor(point, side))
            for raw, side in zip(sides, (a, b), strict=True)
        ]
        out.append(
            {
                "table": name,
                "address": point.address,
                "ref": point.ref,
                "name": point.name,
                **engineering_unit(point.unit),
                "a": values[0],
                "b": values[1],
            }
        )
    for name in TABLE_SECTIONS:
        left, right = a.get(name, {}), b.get(name, {})
        for address in sorted(left.keys() | right.keys()):
            if (name, address) in covered or left.get(address) == right.get(address):
                continue
            out.append(
                {
                    "table": name,
                    "address": address,
                    "ref": reference(table_named(name), address),
                    "a": left.get(address),
                    "b": right.get(address),
                }
            )
    return out


DEVICE = "device"  # a side of diff that is the device itself, read through -p


def _as_read(difference: dict, register_map) -> tuple[object, object]:
    """A difference's two values as read -m shows them: a number an enum point's labels
    leave out says so (JSON keeps the number)."""
    sides = difference["a"], difference["b"]
    if "name" not in difference:
        return sides
    point = register_map.points[difference["name"]]
    a, b = (
        f"{value} (no label)" if value is not None and point.no_label(value) else value for value in sides
    )
    return a, b


@device_command("diff")
@click.argument("a", metavar="A")
@click.argument("b", metavar="[B]", required=False)
@map_option("differences at its points by name, in their units")
def diff(connection, settings, a, b, map):
    """Compare two dumps, or a dump with the device itself (-p and friends).

    A side named device (B when left out) is the device: only the dump's addresses are
    read from it. One line per difference, such as holding 5: 5 -> 99 (or setpoint (40006): 22.5 m3/h
    -> 23 m3/h with -m, a bit off -> on); "missing" where a side lacks the address. Exit 0 when equal, 1
    when they differ (as diff(1)), other codes as everywhere.
    """
    register_map = None
    if map:
        from mbtool.library import load_named_map  # noqa: PLC0415 - the map loader, 4-8 ms: -m only

        register_map = load_named_map(map)
    b = b or DEVICE
    if a == DEVICE == b:
        raise UsageError(f"diff compares a dump with the device, or two dumps: at most one side is {DEVICE}")
    files = {side: snapshot(side)[0] for side in (a, b) if side != DEVICE}
    if DEVICE in (a, b):
        (dumped,) = files.values()
        with open_client(connection, settings, "Read Holding Registers") as client:
            files[DEVICE] = read_live(partial(client.execute, connection.unit), dumped)
    left, right = files[a], files[b]
    found = differences(left, right, register_map)
    listing = Listing(
        data=lambda: {"a": a, "b": b, "equal": not found, "differences": found},
        table=lambda: (
            ["table", "address", "ref", "name", "a", "b", "unit"],
            [
                [d["table"], d["address"], d["ref"], d.get("name", ""), d["a"], d["b"], d.get("unit", "")]
                for d in found
            ],
        ),
        lines=lambda: [change_line(d, *_as_read(d, register_map), d.get("unit", "")) for d in found],
    )
    render(listing, settings.output_format or default_format(), csv_header=settings.csv_header)
    if found:
        return Verdict(counted(len(found), "difference"), ExitCode(1))
    return None


# --- restore: a dump's writable tables back into the device --------------------------------


def write_requests(changes: dict[str, dict[int, int]], spans=()) -> list:
    """FC 15/16 requests for the values to write: one a run of consecutive addresses, cut at
    the spec's limits (1968 coils, 123 registers a request): the fewest such requests.

    ``spans``: (table, first, end) ranges no request may cut, a map's points: a meter
    refuses half a float32, so a cut that would fall inside one falls before it."""
    requests: list[WriteMultipleCoils | WriteMultipleRegisters] = []
    tables: tuple[tuple[str, Any, int], ...] = (  # Any: either write's class, given its values
        ("coils", WriteMultipleCoils, MAX_WRITE_COILS),
        ("holding", WriteMultipleRegisters, MAX_WRITE_REGISTERS),
    )
    for name, kind, limit in tables:
        values = changes.get(name, {})
        whole = [(first, end) for table, first, end in spans if table == name]
        for first, last in runs_of(sorted(values)):
            start = first
            while start <= last:
                end = min(last + 1, start + limit)
                end = next((low for low, high in whole if start < low < end < high), end)
                run = [values[a] for a in range(start, end)]
                requests.append(kind(start, tuple(bool(v) for v in run) if name == "coils" else tuple(run)))
                start = end
    return requests


def restore_plan(current: dict, wanted: dict, register_map=None, everything: bool = False):
    """The writes that make the device hold ``wanted`` (from ``current``): one item a
    difference, named as diff names it, and one Step a request.  A map's point is written
    whole, its registers in one request, when any of them differs.  Also the points the
    dump holds only in part, which are not written."""
    changes: dict[str, dict[int, int]] = {}
    spans, halves, placed = [], [], []
    for difference in differences(current, wanted, register_map):
        table = difference["table"]
        held = wanted.get(table, {})
        if "name" in difference:
            point = register_map.points[difference["name"]]
            addresses = list(range(point.address, point.end))
            if any(address not in held for address in addresses):
                if any(address in held for address in addresses):
                    halves.append(point.name)
                continue  # a point the dump lacks, whole or in part: nothing to write it whole
            spans.append((table, point.address, point.end))
        else:
            addresses = [difference["address"]]
        changes.setdefault(table, {}).update((address, held[address]) for address in addresses)
        item = {
            key: difference[key] for key in ("table", "address", "ref", "name", "unit") if key in difference
        }
        if not everything:  # --all reads nothing first: what the device held is not known
            item["old"] = difference["a"]
        item["new"] = difference["b"]
        placed.append((item, addresses))
    # The requests come table by table, in address order, as the items sorted so: each takes
    # the items from where the one before stopped, up to its end.
    placed.sort(key=lambda pair: (pair[0]["table"] != "coils", pair[1][0]))
    steps, taken = [], 0
    for request in write_requests(changes, spans):
        table = "coils" if request.function_code == 0x0F else "holding"
        end, first = request.address + len(request.values), taken
        while taken < len(placed) and placed[taken][0]["table"] == table and placed[taken][1][0] < end:
            taken += 1
        mine = placed[first:taken]
        items = tuple(item for item, _ in mine)
        if len(items) == 1:
            label = change_parts(items[0], None, None)[0]
        else:
            label = f"{table} {request.address}-{end - 1}"
        steps.append(Step(label, items, (request, [addresses for _, addresses in mine])))
    return steps, changes, halves


@device_command("restore")
@click.argument("file", type=FilePath(dir_okay=False))
@click.option(
    "--all", "everything", is_flag=True, help="Write every coil and register, not only those that differ."
)
@map_option("each point written whole, its registers in one request, and named in the report")
def restore(connection, settings, file, everything, map):
    """Write a dump's holding registers and coils back into the device, then read back.

    Only what differs from the device is written (--all: everything), in the fewest FC
    15/16 requests; then every written address is read back to confirm it. Each write is
    listed as diff lists a difference, with its fate: confirmed, differs (reads back
    otherwise), written, refused, failed or not-sent. The first write that fails stops the
    rest, and the exit code is the failure's own. --dry-run reads the device and lists the
    writes it would make, sending none. With -m MAP a point that differs is written whole
    (a meter may refuse half a float32) and named. Input registers and discrete inputs
    cannot be written: they are reported as skipped.
    """
    snap, complete = snapshot(file)
    register_map = None
    if map:
        from mbtool.library import load_named_map  # noqa: PLC0415 - the map loader, 4-8 ms: -m only

        register_map = load_named_map(map)
    if not complete:
        print(
            f"mbtool: warning: {file} is marked complete = false: the dump stopped early, and only "
            "what it holds is restored",
            file=sys.stderr,
        )
    wanted = {name: snap[name] for name in ("coils", "holding") if name in snap}
    skipped = ", ".join(
        counted(len(snap[name]), noun)
        for name, noun in (("input", "input register"), ("discrete", "discrete input"))
        if snap.get(name)
    )
    head = {"unit": connection.unit, "file": file} | ({"map": map} if map else {})
    read_back, trouble = False, None
    # The reads are needed even for --dry-run: it lists only the writes that differ.
    with open_client(connection, replace(settings, dry_run=False), "Read Holding Registers") as client:
        execute = partial(client.execute, connection.unit)

        current = {} if everything else read_live(execute, wanted)
        steps, changes, partial_points = restore_plan(current, wanted, register_map, everything)
        items = [item for step in steps for item in step.items]
        if settings.dry_run:
            from mbtool.cli.dryrun import DryRunDone  # noqa: PLC0415 - describe, 0.8 ms: --dry-run only

            report(settings, items, head)
            raise DryRunDone(
                f"dry run: the device was read; nothing was sent: {counted(len(steps), 'request')} "
                f"would write {counted(len(items), 'value')}"
            )
        outcome = send_all(steps, lambda step: execute(step.work[0]))
        # Read back what the device acknowledged, while it still answers: after a refusal it
        # does; after silence or a hang-up another read would only wait for nothing.
        if outcome.error is None or isinstance(outcome.error, ModbusException):
            sent: dict[str, dict[int, int]] = {}
            for step in outcome.steps[: outcome.done]:
                request, _ = step.work
                table = "coils" if request.function_code == 0x0F else "holding"
                sent.setdefault(table, {}).update(
                    (request.address + i, int(value)) for i, value in enumerate(request.values)
                )
            try:
                after = read_live(execute, sent)
            except KNOWN_ERRORS as error:
                trouble = error
            else:
                read_back = True
                for step in outcome.steps[: outcome.done]:
                    _confirm(step, sent, after, register_map)
    code = exit_code_for(outcome.error) if outcome.error else ExitCode.OK
    if outcome.error is not None:
        summary = failure("restore", outcome, read_back)
    else:
        nouns = {"coils": "coil", "holding": "holding register"}
        wrote = ", ".join(counted(len(values), nouns[name]) for name, values in changes.items() if values)
        text = f"restore: wrote {wrote or 'nothing'} in {counted(len(steps), 'request')}"
        if skipped:
            text += f"; skipped {skipped} (read-only)"
        if partial_points:
            text += f"; not written: {', '.join(partial_points)} (the dump holds part of each)"
        differ = sum(item["status"] == DIFFERS for item in items)
        if trouble is not None:
            text += f"; not read back: {trouble}"
            code = exit_code_for(trouble)
        elif differ:
            text += f"; {differ} read back differently"
            code = ExitCode.INVALID_RESPONSE
        elif items:
            text += "; read back and confirmed"
        summary = Verdict(text, code)
    end = {"error": str(summary)} if code else {}
    report(settings, items, head, end | {"exit_code": int(code)})
    return summary


def _confirm(step, sent: dict, after: dict, register_map) -> None:
    """Each item of a step written: confirmed when every address it covers reads back as
    written, else differs, with what it reads (its point's value with a map)."""
    _, spans = step.work
    for item, addresses in zip(step.items, spans, strict=True):
        table = item["table"]
        raw = [after.get(table, {}).get(address) for address in addresses]
        if raw == [sent[table][address] for address in addresses]:
            item["status"] = CONFIRMED
            continue
        item["status"] = DIFFERS
        if None in raw:
            item["reads"] = None
        elif "name" in item:
            point = register_map.points[item["name"]]
            item["reads"] = point.value_of(raw, _scale_factor(point, after))
        else:
            item["reads"] = raw[0]
