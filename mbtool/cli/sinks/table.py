"""-o table: rich's tables, the default on a terminal; and every other thing mbtool draws
with rich (live views, progress bars).  This is the one module that imports rich: it is
imported inside each function, as it costs a one-shot that writes no table 12-20 ms.
"""

from __future__ import annotations

import sys
import threading
import time
from typing import TYPE_CHECKING, Any, TextIO

from mbtool.cli.results import (
    Listing,
    Points,
    Report,
    Result,
    by_order,
    change_parts,
    labels,
    points_heading,
    reading_text,
    value_text,
)
from mbtool.cli.sinks.plain import Polls as PlainPolls
from mbtool.cli.sinks.plain import Rows as PlainRows
from mbtool.codec.errors import function_code_text
from mbtool.words import counted

if TYPE_CHECKING:
    from rich.live import Live


def render(result: Result | Report | Points | Listing, out: TextIO, csv_header: bool = True) -> None:
    if isinstance(result, Listing):
        if result.draw is None:  # no table of its own: its plain lines
            out.write("".join(line + "\n" for line in result.lines()))
        else:
            result.draw()
    elif isinstance(result, Points):
        _points(result, out)
    elif isinstance(result, Report):
        _report(result, out)
    else:
        _result(result, out)


def console(out: TextIO | None = None, **options):
    """rich's console on ``out`` (stdout when None or stdout: rich then finds the terminal's
    width); ``options``: rich's (highlight, soft_wrap, stderr)."""
    from rich.console import Console  # noqa: PLC0415 - rich, 12-20 ms: tables only

    return Console(file=out, **options) if out is not None and out is not sys.stdout else Console(**options)


def escape(text: str) -> str:
    """Text shown as it is in rich's markup: a device's or a user's words are never read as markup."""
    from rich.markup import escape as escaped  # noqa: PLC0415 - rich, 12-20 ms: tables only

    return escaped(text)


def _result(result: Result, out: TextIO) -> None:
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

    bits = result.type is None
    orders = by_order(result)
    table = Table()
    if result.refs is not None:
        table.add_column("Ref", justify="right")
    if result.refs is None or not orders:
        table.add_column("Address", justify="right")
    for heading in orders or ["Value"]:
        table.add_column(heading, justify="right", overflow="fold")  # a value is never cut short
    plain_registers = result.type == "uint16"
    if plain_registers:
        table.add_column("Hex", justify="right")
    typed_registers = not bits and not plain_registers and result.registers is not None
    if typed_registers:
        from mbtool.codec.values import TYPES  # noqa: PLC0415 - typed registers only; crc loads this too

        assert result.type is not None  # not bits
        width = TYPES[result.type].registers
        table.add_column("Registers", justify="right")
    refs = result.refs if result.refs is not None else [None] * len(result.values)
    for index, (ref, address, value) in enumerate(zip(refs, result.addresses, result.values, strict=True)):
        cells = [] if ref is None else [ref]
        if ref is None or not orders:
            cells.append(str(address))
        if result.texts is not None:
            cells.append(result.texts[index])
        elif bits:
            cells.append("[green]ON[/]" if value else "[dim]OFF[/]")
        elif plain_registers:
            # The register as it holds the value: a write of -5 holds 0xFFFB.
            register = value if result.registers is None else result.registers[index]
            cells += [str(value), f"0x{register:04X}"]
        else:
            cells += [value_text(value[o]) for o in orders] if orders else [value_text(value)]
        if typed_registers:
            # The words behind each value: when a float looks wrong, they show the word order.
            start = address - result.address
            assert result.registers is not None  # typed_registers
            words = result.registers[start : start + (width or len(result.registers))]
            cells.append(" ".join(f"{w:04X}" for w in words))
        table.add_row(*cells)
    shown = console(out)
    shown.print(
        f"[bold]{result.name}[/] · {function_code_text(result.function)} · unit {result.unit}",
        highlight=False,
    )
    shown.print(table)
    if result.note:
        shown.print(result.note, style="dim")


def points_table(points: Points, heading: str = ""):
    """The rich table of a map read (its heading above it, as polling draws it too)."""
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

    described = any(row.description for row in points.rows)
    table = Table()
    table.add_column("Name", justify="left")
    table.add_column("Value", justify="right")
    table.add_column("Unit", justify="left")
    table.add_column("Ref", justify="right")
    table.add_column("Raw", justify="right")
    if described:
        table.add_column("Description")
    for row in points.rows:
        raw = " ".join(value_text(b) if row.bits else f"{b:04X}" for b in row.raw)
        cells = [escape(row.name), escape(row.shown), escape(row.unit), row.ref, raw]
        if described:
            cells.append(escape(row.description))
        table.add_row(*cells)
    for failure in points.failed:  # refused by the device: the answer where the value would be
        table.add_row(escape(failure.name), f"[red]{escape(failure.error)}[/]", "", failure.ref, "")
    return table


def _points(points: Points, out: TextIO) -> None:
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: tables only

    shown = console(out)
    shown.print(f"[bold]{escape(points_heading(points))}[/]", highlight=False)
    shown.print(points_table(points))
    if points.note:
        shown.print(escape(points.note), style="dim")


def _report(report: Report, out: TextIO) -> None:
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

    with_raw = any(row.raw is not None for row in report.rows)
    table = Table()
    table.add_column("Field")
    if with_raw:
        table.add_column("Bytes")
    table.add_column("Value")
    for row in report.rows:
        cells = [row.name.replace("_", " ")]
        if with_raw:
            cells.append("" if row.raw is None else row.raw.hex(" ").upper())
        cells.append(escape(row.shown))
        table.add_row(*cells)
    shown = console(out)
    title = report.title
    if not title:
        title = f"[bold]{escape(report.name)}[/]"
        if report.function is not None:
            title += f" · {function_code_text(report.function)}"
        if report.unit is not None:
            title += f" · unit {report.unit}"
    shown.print(title, highlight=False)
    shown.print(table)
    if report.note:
        shown.print(escape(report.note), style="dim")


class Log:
    """A stream of items as they are seen, drawn in colour on a terminal:
    ``views.draw(item, console)`` prints it with rich's console, made now, not while the first
    item arrives: a frame read late, behind an import, would be stamped late."""

    events = True

    def __init__(self, out: TextIO, views, **console_options) -> None:
        self.out = out
        self.views = views
        self.console = console(out, **console_options)

    def write(self, item) -> None:
        self.views.draw(item, self.console)


class Rows(PlainRows):
    """A stream of rows (scan's units as they are found): the listing's table at the end."""

    def row(self, cells: list, line: str) -> None:
        pass

    def end(self, listing: Listing) -> None:
        render(listing, self.out)


class Polls(PlainPolls):
    """read --interval -o table: each poll's table under its heading, redrawn in place on a
    terminal; into a file or a pipe every poll's table stays."""

    def __init__(self, output) -> None:
        super().__init__(output)
        self.live: Live | None = None  # rich's, made at the first table on a terminal

    def result(self, when: str, result, stamp: float | None = None) -> None:
        from rich.text import Text  # noqa: PLC0415 - rich, 12-20 ms: tables only

        if result.__class__ is Points:
            self._show(Text(f"{points_heading(result)} · {when}"), points_table(result))
            return
        from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

        # The heading above, not as the table's title: a title wraps to the table's width.
        heading = Text(f"{result.name} · {function_code_text(result.function)} · unit {result.unit} · {when}")
        orders = by_order(result)
        table = Table()
        table.add_column("Ref" if result.refs is not None else "Address", justify="right")
        for column in orders or ["Value"]:
            table.add_column(column, justify="right")
        for label, value in zip(labels(result), result.values, strict=True):
            values = [value_text(value[o]) for o in orders] if orders else [value_text(value)]
            table.add_row(str(label), *values)
        self._show(heading, table)

    def values(self, when: str, read: Result, values: list, registers, stamp: float | None = None) -> None:
        self.result(when, read.polled(values, registers), stamp)

    def _show(self, heading, table) -> None:
        from rich.console import Group  # noqa: PLC0415 - rich, 12-20 ms: tables only
        from rich.live import Live  # noqa: PLC0415 - rich, 12-20 ms: tables only

        out = self.output.out
        if not out.isatty():
            # Into a file or a pipe every poll's table stays, each ending its line: a table
            # refreshed in place would leave only the last one, without a final newline.
            console(out).print(Group(heading, table))
            return
        live = self.live
        if live is None:
            live = self.live = Live(Group(heading, table), auto_refresh=False)
            live.start()
        live.update(Group(heading, table), refresh=True)

    def close(self) -> None:
        if self.live is not None:
            self.live.stop()
            self.live = None


# --- the other things mbtool draws with rich ----------------------------------------------


class ScanProgress:
    """scan's progress bar on stderr (the unit probed, how many found) when ``enabled`` (a
    terminal); nothing otherwise."""

    def __init__(self, total: int, enabled: bool) -> None:
        self.bar = None
        if not enabled:
            return
        from rich.console import Console  # noqa: PLC0415 - rich, 12-26 ms: a progress bar only
        from rich.progress import (  # noqa: PLC0415 - rich, 12-26 ms: a progress bar only
            BarColumn,
            MofNCompleteColumn,
            TextColumn,
            TimeRemainingColumn,
        )
        from rich.progress import Progress as Bar  # noqa: PLC0415 - rich, 12-26 ms: a progress bar only

        self.bar = Bar(
            TextColumn("{task.description}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("found {task.fields[found]}"),
            TimeRemainingColumn(),
            console=Console(stderr=True),
            transient=True,
            # Lines written meanwhile (found units, notes) go above the bar, not through it.
            redirect_stdout=sys.stdout.isatty(),
            redirect_stderr=True,
        )
        self.task = self.bar.add_task("scan", total=total, found=0)
        self.bar.start()

    def at(self, setting, unit: int) -> None:
        """``setting``: the serial settings being swept (scan.Setting), or None."""
        if self.bar is not None:
            where = f"{setting} " if setting else ""
            self.bar.update(self.task, description=f"{where}unit {unit}")

    def advance(self, steps: int = 1) -> None:
        if self.bar is not None:
            self.bar.advance(self.task, steps)

    def found(self, count: int) -> None:
        if self.bar is not None:
            self.bar.update(self.task, found=count)

    def stop(self) -> None:
        if self.bar is not None:
            self.bar.stop()
            self.bar = None


class ProgressBar:
    """A progress bar on a terminal's stderr (dump: addresses covered of all asked for)."""

    def __init__(self, total: int, what: str) -> None:
        from rich.console import Console  # noqa: PLC0415 - rich, 12-26 ms: a progress bar only
        from rich.progress import Progress  # noqa: PLC0415 - rich, 12-26 ms: a progress bar only

        self.done = 0
        self.progress = Progress(console=Console(stderr=True), transient=True)
        self.task = self.progress.add_task(what, total=total)
        self.progress.start()

    def past(self, start: int, count: int) -> None:
        """``count`` more done since ``start`` (a span's progress as its dump reports it)."""
        self.at(start + count)

    def at(self, done: int) -> None:
        self.done = done
        self.progress.update(self.task, completed=done)

    def close(self) -> None:
        self.progress.stop()


def serve_live(server, device, framer: str, unit_text: str, units: frozenset[int], shown) -> None:
    """serve's live display on a terminal: what it listens on and has served, the units'
    FC 08 counters and the last frames, redrawn 4 times a second while ``server`` runs.
    ``shown(data, framer)``: a frame's bytes as serve writes them."""
    from rich.console import Console, Group  # noqa: PLC0415 - rich, 12-20 ms: the live display only
    from rich.live import Live  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only
    from rich.text import Text  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only

    console = Console()
    shown_units = sorted(units)[:4]

    def view():
        stats = server.stats
        uptime = time.monotonic() - stats.started
        head = Table.grid(padding=(0, 2))
        head.add_row(
            f"[b]mbtool serve[/b] {stats.listening}",
            f"framer {framer}" + (", read-only" if device.read_only else ""),
            f"units {unit_text}",
            f"up {uptime:.0f} s",
            f"clients {stats.clients}"
            + (f", {stats.refused} refused" if stats.refused else "")
            + (f", {stats.evicted} gave their slot" if stats.evicted else "")
            + (f", {stats.expired + stats.unused} timed out" if stats.expired + stats.unused else ""),
        )
        head.add_row(
            f"requests {stats.requests}",
            f"replies {stats.replies}",
            f"dropped {stats.dropped}",
            f"corrupted {stats.corrupted}",
            "Ctrl-C stops",
        )
        counters = Table(title="FC08 counters", title_justify="left")
        counters.add_column("counter")
        for unit in shown_units:
            counters.add_column(f"unit {unit}", justify="right")
        names = list(device.counters(shown_units[0])) if shown_units else []
        values = {unit: device.counters(unit) if unit in device.stations else {} for unit in shown_units}
        for name in names:
            counters.add_row(name, *(str(values[u][name]) if values[u] else "-" for u in shown_units))
        counters.add_row(
            "listen only",
            *(
                "yes" if u in device.stations and device.stations[u].listen_only else "no"
                for u in shown_units
            ),
        )
        served = Table(title="served", title_justify="left")
        served.add_column("FC", justify="right")
        served.add_column("requests", justify="right")
        for code, count in sorted(device.served.items()):
            served.add_row(f"{code:02X}", str(count))
        frames = Table(title="last frames", title_justify="left")
        frames.add_column("t", justify="right")
        frames.add_column("dir")
        frames.add_column("peer")
        frames.add_column("bytes", overflow="fold")
        frames.add_column("note", overflow="fold")
        for at, direction, peer, data, note in stats.frames:
            # Text, never markup: the frame is whatever a peer sent ("[/x]" in an ASCII frame),
            # and the peer and the note come from outside too.
            frames.add_row(f"{at:.3f}", direction, Text(peer), Text(shown(data, framer)), Text(note))
        side = Table.grid(padding=(0, 4))
        side.add_row(counters, served)
        return Group(head, side, frames)

    last = [0.0]
    with Live(view(), console=console, auto_refresh=False, transient=False) as live:

        def tick() -> None:
            now = time.monotonic()
            if now - last[0] >= 0.25:
                last[0] = now
                live.update(view(), refresh=True)

        server.run(tick)


def write_items(items, head: dict) -> None:
    """The items of a write or restore (cli.writes), a row each, under what was written."""
    from rich.console import Console  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: tables only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: tables only

    statuses = any("status" in item for item in items)
    olds = any("old" in item for item in items)
    table = Table()
    for column, shown in (("Status", statuses), ("What", True), ("Old", olds), ("New", True)):
        if shown:
            table.add_column(column, justify="right" if column in ("Old", "New") else "left")
    for item in items:
        where, old, new = change_parts(item, item.get("old"), item["new"], item.get("unit", ""))
        cells = ([item.get("status", "")] if statuses else []) + [where] + ([old] if olds else []) + [new]
        table.add_row(*(escape(cell) for cell in cells))
    console = Console()
    source = head.get("file") or head.get("map") or ""
    console.print(f"[bold]{escape(source)}[/] · unit {head.get('unit')}", highlight=False)
    console.print(table)


class PlantView:
    """The plant on one screen, fit to the terminal whatever its size: a title with the count
    of devices online and offline, a row a device (its state in colour, the age of its last
    good poll, its round-trip time and error counts, and its points' latest values, a changed
    one highlighted, cut at the row's end), and below them a band of the latest changes of
    state, newest first.  The band is the only place that says why a device or a link is
    offline, so it keeps its rows: a screen too short for the plant cuts the table, with a
    line that counts the devices left out."""

    EVENT_ROWS = 5  # the band's rows, below its heading
    COLUMNS: tuple[str, ...] = (
        "device",
        "link",
        "state",
        "last good",
        "rtt avg",
        "timeout",
        "corrupt",
        "exc",
        "values",
    )

    def __init__(self, plant, describe, clock=time.time) -> None:
        """``describe(event)``: a change of state as its line (cli.plant_text.event_line)."""
        # The scheduler's records and states: poll's alone, no other command pays for them.
        from mbtool.plant import schedule  # noqa: PLC0415 - the plant's scheduler, 2-4 ms: poll only

        self.schedule = schedule
        self.colours = {schedule.ONLINE: "green", schedule.OFFLINE: "bold red", schedule.UNKNOWN: "yellow"}
        self.plant = plant
        self.describe = describe
        self.clock = clock  # the time "last good" is counted to (scripts/gen_docs.py: a fixed one)
        self.lock = threading.Lock()
        self.changed: dict[str, set[str]] = {}
        self.previous: dict[str, dict[str, object]] = {}
        self.events: list[str] = []
        self.states = schedule.views(plant.devices)  # each device as its latest Poll left it
        # Poll groups (issue 44): each group's pace as its latest poll left it, in a column of
        # their own when a device has groups
        self.paces: dict[str, dict[str, Any]] = {}  # device -> group -> plant.schedule.Pace
        self.grouped = any(device.groups for device in plant.devices)
        if self.grouped:
            self.COLUMNS = (*self.COLUMNS[:-1], "groups: achieved/asked s", self.COLUMNS[-1])

    def running(self):
        from rich.live import Live  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only

        return Live(self, refresh_per_second=4, transient=False)

    def title_note(self) -> str:
        """What the title says after the devices' counts (poll --mqtt: the broker's state)."""
        return ""

    def __rich_console__(self, console, options):
        """The screen as it is now, built when rich draws it (4 times a second), not on every
        poll of every device, and for the terminal's size then (it may have been resized)."""
        with self.lock:
            yield from self._screen(console, options.max_width, options.size.height)

    def report(self, item) -> None:
        with self.lock:
            if isinstance(
                item, self.schedule.Event
            ):  # the line stderr gets too, the latest a band holds kept
                self.events = (self.events + [self.describe(item)])[-self.EVENT_ROWS :]
                return
            self.states[item.device.name] = self.schedule.view_of(item)
            if item.pace is not None and item.device.groups:
                self.paces.setdefault(item.device.name, {})[item.group] = item.pace
            if item.readings is not None:
                values = {r.point.name: r.value for r in item.readings if r.error is None}
                before = self.previous.get(item.device.name, {})
                self.changed[item.device.name] = {
                    name for name, value in values.items() if before.get(name, value) != value
                }
                self.previous[item.device.name] = before | values  # a group's poll: its points

    def _screen(self, console, width: int, height: int) -> list:
        from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only
        from rich.text import Text  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only

        states = list(self.states.values())
        offline = sum(state.state == self.schedule.OFFLINE for state in states)
        online = sum(state.state == self.schedule.ONLINE for state in states)
        title = Text(f"mbtool poll {self.plant.path}: ", style="bold", no_wrap=True, overflow="ellipsis")
        title.append(
            f"{counted(len(states), 'device')}, {online} online, {offline} offline" + self.title_note()
        )
        # A row a device in the room the title, the table's header and the band leave.
        room = height - 2 - (1 + self.EVENT_ROWS)
        shown = states if len(states) <= room else states[: max(room - 1, 0)]
        # Every column but the values keeps its width, and the values' column takes what is
        # left of the row (rich narrows the columns that may wrap first): the values are cut
        # at the row's end, with an ellipsis, never folded a point a line.
        table = Table(box=None, padding=(0, 1, 0, 0), pad_edge=False, header_style="bold", expand=False)
        for column in self.COLUMNS:
            table.add_column(column, no_wrap=column != "values")
        now = self.clock()
        for state in shown:
            table.add_row(*self._row(state, now))
        screen = [title, table]
        if len(shown) < len(states):
            hidden = states[len(shown) :]
            down = sum(state.state == self.schedule.OFFLINE for state in hidden)
            screen.append(
                Text(f"+{len(hidden)} more devices" + (f" ({down} offline)" if down else ""), no_wrap=True)
            )
        screen.append(Text("changes of state, newest first:", style="dim", no_wrap=True))
        screen.extend(self._band(console, width))
        return screen

    def _row(self, state, now: float) -> tuple:
        from rich.text import Text  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only

        stats = state.stats
        figures = stats.rtt_figures()
        age = "-" if state.last_success is None else f"{now - state.last_success:.1f} s ago"
        values = Text(no_wrap=True, overflow="ellipsis")
        changed = self.changed.get(state.spec.name, ())
        for reading in (state.last_poll.readings or ()) if state.last_poll else ():
            if reading.error is None:
                style = "reverse" if reading.point.name in changed else ""
                values.append(f"{reading.point.name}={reading_text(reading)}", style=style)
                values.append(" ")
        values.rstrip()
        return (
            Text(state.spec.name),  # Text: a name is never read as rich's markup
            Text(state.spec.link),
            Text(state.state, style=self.colours.get(state.state, "")),
            age,
            "-" if figures is None else f"{figures['avg'] * 1000:.1f} ms",
            str(stats.outcomes["timeout"]),
            str(stats.outcomes["corrupt"]),
            str(stats.outcomes["exception"]),
            *((self._paces(state.spec.name),) if self.grouped else ()),
            values,
        )

    def _paces(self, device: str) -> str:
        """Each group's achieved and asked interval, and its overruns: ``fast 1.02/1 (3 late)``."""
        cells = []
        for pace in self.paces.get(device, {}).values():
            if pace.asked == float("inf"):
                continue  # read once: no pace to keep
            achieved = "-" if pace.achieved is None else f"{pace.achieved:.2f}"
            cells.append(
                f"{pace.group} {achieved}/{pace.asked:g}"
                + (f" ({pace.overruns} late)" if pace.overruns else "")
            )
        return ", ".join(cells)

    def _band(self, console, width: int) -> list:
        """The band's rows: the latest changes of state, newest first, each folded whole onto
        as many rows as it needs (its reason is at its end), blank rows below them."""
        from rich.text import Text  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only

        rows: list = []  # rich Text lines
        for line in reversed(self.events):
            rows.extend(Text(line).wrap(console, width))
        rows = rows[: self.EVENT_ROWS]
        if not self.events:
            rows = [Text("none yet", style="dim")]
        return rows + [Text("")] * (self.EVENT_ROWS - len(rows))


def scan_answers(answers, sweeping: bool, title: str) -> None:
    """scan's units found (and garbled answers), a row each, under ``title``."""
    from rich.console import Console  # noqa: PLC0415 - rich, 12-20 ms: -o table only
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: -o table only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: -o table only

    table = Table()
    table.add_column("Unit", justify="right")
    table.add_column("Answer")
    if sweeping:
        table.add_column("Baud", justify="right")
        table.add_column("Parity")
    table.add_column("Detail")
    table.add_column("ms", justify="right")
    for answer in answers:
        where = [str(answer.setting.baud), answer.setting.parity] if answer.setting else []
        style = "dim" if answer.answer == "garbled" else None
        table.add_row(
            str(answer.unit),
            answer.answer,
            *where,
            escape(answer.text),
            "" if answer.ms is None else f"{answer.ms:g}",
            style=style,
        )
    console = Console()
    console.print(title, highlight=False)
    console.print(table)


def titled_tables(blocks: list[tuple]) -> None:
    """Titles, errors and tables, one under another (sunspec's models): each block
    ("title", TEXT), ("error", TITLE, ERROR) or ("table", [(COLUMN, JUSTIFY)...], ROWS).
    Every text is the device's or the user's: shown as it is, never read as markup."""
    from rich.markup import escape  # noqa: PLC0415 - rich, 12-20 ms: -o table only
    from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: -o table only

    shown = console()
    for kind, *parts in blocks:
        if kind == "title":
            shown.print(f"[bold]{escape(parts[0])}[/]", highlight=False)
        elif kind == "error":
            shown.print(f"{escape(parts[0])}: [red]{escape(parts[1])}[/]", highlight=False)
        else:
            columns, rows = parts
            table = Table()
            for column, justify in columns:
                table.add_column(escape(column), justify=justify)
            for row in rows:
                table.add_row(*map(escape, row))
            shown.print(table)
