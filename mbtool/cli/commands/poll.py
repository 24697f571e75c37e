"""``mbtool poll PLANT.toml``: every device of a plant, from one process.

One worker a link polls its devices one transaction at a time, every link at once
(mbtool.plant.schedule); this module turns what they report into output: plain lines,
JSON lines, long CSV, influx, Prometheus text or a textfile of the whole plant, a live
view on a terminal, one line on stderr for each change of state, and statistics on exit.
"""

from __future__ import annotations

import csv
import sys
import threading
import time

import click

from mbtool.cli.frames import HexTrace
from mbtool.cli.inventory import FORMATS, load_inventory
from mbtool.cli.json_text import to_json
from mbtool.cli.metrics import (
    KEY_SPECIALS,
    _escape,
    _field_value,
    check_textfile,
    influx_text,
    write_textfile,
)
from mbtool.cli.param_types import FilePath, PositiveFloat
from mbtool.cli.plant_text import LAST_SUCCESS, UP, event_line, prom_text, refuse_point_names
from mbtool.cli.render import wants_csv_header
from mbtool.cli.results import point_text, value_text
from mbtool.cli.session import warn_insecure
from mbtool.cli.stamps import local_time
from mbtool.codec.errors import RequestError
from mbtool.errors import ExitCode, PartialRead, Summary, exit_code_for
from mbtool.plant.schedule import OFFLINE, ONLINE, Event, Plant, Poll, limits
from mbtool.plant.stats import PollStats

CSV_HEADER = ["time", "device", "name", "value", "unit", "ref"]


@click.command(
    "poll",
    context_settings={"help_option_names": ["-h", "--help"]},
    short_help="Poll every device of a plant: several buses and gateways, from one process.",
)
@click.argument("inventory", type=FilePath(dir_okay=False))
@click.option(
    "-o",
    "--format",
    "output_format",
    type=click.Choice(FORMATS),
    help="Output: plain lines, JSON lines (one a device poll), CSV (long form), InfluxDB line "
    "protocol or Prometheus text. Default: the inventory's [poll] output, else a live view on "
    "a terminal and plain lines in a pipe.",
)
@click.option(
    "--textfile",
    metavar="PATH",
    type=FilePath(dir_okay=False),
    help="Rewrite the whole plant's metrics (Prometheus text) to PATH atomically after each "
    "round, for node_exporter's textfile collector; a dead device shows as modbus_up 0.",
)
@click.option("--once", is_flag=True, help="Poll every device once (each link at once) and exit: for cron.")
@click.option(
    "--rounds",
    type=click.IntRange(1),
    help="Poll every device that answers this many times, then exit. An offline device is tried "
    "again only where its back-off ends within those rounds: the last line says how many polls it got.",
)
@click.option("--duration", type=PositiveFloat(), metavar="SECONDS", help="Stop after this long.")
@click.option(
    "--stats",
    "stats_format",
    type=click.Choice(["table", "json"]),
    default="table",
    show_default=True,
    help="Statistics on exit, on stderr: a table per device and per link, or one JSON object.",
)
@click.option("--no-header", is_flag=True, help="CSV without its header row.")
@click.option(
    "--hex",
    "hex_trace",
    is_flag=True,
    help="Print every frame sent and received (stderr), each line labelled with its link and device: "
    "[bus1 meter1] TX ...",
)
@click.option(
    "--hex-link",
    "hex_links",
    metavar="LINK",
    multiple=True,
    help="--hex for this link alone (repeat it for several).",
)
def poll(
    inventory, output_format, textfile, once, rounds, duration, stats_format, no_header, hex_trace, hex_links
):
    """Poll every device of a plant from one process: PLANT.toml names its links (serial
    buses, gateways, TCP devices) and devices (unit, register map or references, tags).

    Each link has a worker of its own: one transaction at a time on it, with its silences
    and pause; every link at once. A device that fails 3 polls in a row is offline and tried
    again after a back-off that doubles up to max_backoff, so a dead unit costs one timeout
    a back-off, not one a round; one good poll brings it back. Each change of state is one
    line on stderr (and an event in JSON).

    Exit status: 0 when every device answered its last poll, 8 when some did and others
    did not, the failure's own status when none did; 2 for a bad inventory, with nothing
    opened; 130 when --once, --rounds or --duration is stopped (Ctrl-C, SIGTERM) before
    its end.
    """
    plant = load_inventory(inventory)

    for name, link in plant.links.items():
        warn_insecure(link.connection, name)
    fmt = output_format or plant.output
    live = fmt is None and textfile is None and sys.stdout.isatty()
    fmt = fmt or "plain"
    if fmt == "prom" or textfile:
        # A point named as a device's own metrics (up) would make two families of one name.
        refuse_point_names(plant, {UP, LAST_SUCCESS}, "mbtool's Prometheus text")
    if textfile:
        check_textfile(textfile)  # a folder that is not there: exit 7 now, not after a round
    if once:
        rounds = 1
    unknown = [name for name in hex_links if name not in plant.links]
    if unknown:
        raise RequestError(
            f"--hex-link {unknown[0]}: no [links.{unknown[0]}] in {inventory} (links: {', '.join(plant.links)})"
        )
    trace = HexTrace if hex_trace or hex_links else None  # made by each traced link, labelled
    output = PlantOutput(fmt, textfile, no_header, plant)
    view = LiveView(plant) if live else None
    runner = Plant(
        plant.links,
        plant.devices,
        view.report if view else output.report,
        rounds or 0,
        trace,
        hex_links or None,
    )
    output.states = runner.devices
    started = time.monotonic()
    interrupted = False
    try:
        if view:
            with view.running(runner.devices):
                runner.run(duration)
        else:
            runner.run(duration)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        runner.stop.set()
    output.close()
    _statistics(runner, stats_format, time.monotonic() - started)
    raise _verdict(runner, interrupted, rounds or 0, bool(rounds or duration))


class PlantOutput:
    """What the workers report, written as it comes (one writer at a time: a lock)."""

    def __init__(self, fmt: str, textfile: str | None, no_header: bool, plant) -> None:
        self.fmt = fmt
        self.textfile = textfile
        self.swept = False  # a killed run's temporaries are looked for at the first write only
        self.lock = threading.Lock()
        self.states: dict = {}
        self.header = fmt == "csv" and not no_header and wants_csv_header(sys.stdout)
        self.writer = csv.writer(sys.stdout, lineterminator="\n") if fmt == "csv" else None
        self.pending = {device.name for device in plant.devices}  # not yet polled this round

    def report(self, item: Poll | Event) -> None:
        with self.lock:
            if isinstance(item, Event):
                self._event(item)
            else:
                self._poll(item)
            sys.stdout.flush()

    def _event(self, event: Event) -> None:
        print(f"mbtool: {event_line(event)}", file=sys.stderr, flush=True)
        if self.fmt == "json":
            record = {"time": local_time(event.time), "event": event.state, event.kind: event.name}
            if event.reason:
                record["reason"] = event.reason
            if event.retry_in is not None:
                record["retry_in"] = event.retry_in
            sys.stdout.write(to_json(record) + "\n")

    def _poll(self, poll: Poll) -> None:
        device, when = poll.device, local_time(poll.time)
        if poll.readings is None:
            if poll.state != OFFLINE:  # an offline device's probes: its event said why
                print(f"mbtool: {when} {device.name}: {poll.error}", file=sys.stderr, flush=True)
        else:
            for reading in poll.readings:
                if reading.error is not None:
                    point = reading.point
                    print(
                        f"mbtool: {when} {device.name} {point.name} ({point.ref}): {reading.error}",
                        file=sys.stderr,
                    )
        if self.fmt == "plain":
            for reading in poll.readings or ():
                if reading.error is None:
                    unit = (
                        f" {reading.point.unit}" if reading.point.unit and reading.value is not None else ""
                    )
                    sys.stdout.write(f"{when} {device.name} {reading.point.name} {_shown(reading)}{unit}\n")
        elif self.fmt == "json":
            sys.stdout.write(to_json(_json_record(poll, when)) + "\n")
        elif self.fmt == "csv":
            if self.header:
                self.writer.writerow(CSV_HEADER)
                self.header = False
            for reading in poll.readings or ():
                if reading.error is None:
                    point = reading.point
                    self.writer.writerow(
                        [when, device.name, point.name, _csv_value(reading), point.unit, point.ref]
                    )
        elif self.fmt == "influx":
            line = influx_line(poll)
            if line:
                sys.stdout.write(line)
        elif self.fmt == "prom":
            sys.stdout.write(prom_text([self.states[device.name]]))
        if self.textfile:
            # A round: every device has reported since the last write, but those offline,
            # tried once a back-off, which would hold every other device's values back.
            self.pending.discard(device.name)
            if all(self.states[name].state == OFFLINE for name in self.pending):
                self._write_textfile()
                self.pending = set(self.states)

    def _write_textfile(self) -> None:
        write_textfile(prom_text(list(self.states.values())), self.textfile, sweep=not self.swept)
        self.swept = True

    def close(self) -> None:
        with self.lock:
            if self.textfile and self.states:
                self._write_textfile()  # the last state of every device, whatever the round
            sys.stdout.flush()


def _shown(reading) -> str:
    """A reading as read -m shows it: on/off, invalid, a label, or a number (no label)."""
    return point_text(reading.value) + (" (no label)" if reading.point.no_label(reading.value) else "")


def _csv_value(reading) -> str:
    if reading.value is None:
        return ""  # no data: an empty cell, as a spreadsheet leaves one
    return _shown(reading) if isinstance(reading.value, bool) else value_text(reading.value)


def _json_record(poll: Poll, when: str) -> dict:
    device = poll.device
    record = {"time": when, "device": device.name, "tags": device.tags or {}, "unit": device.unit}
    if poll.readings is None:
        record["state"] = poll.state
        record["error"] = str(poll.error)
        record["exit_code"] = int(exit_code_for(poll.error))
        return record
    points, failed = [], []
    for reading in poll.readings:
        point = reading.point
        if reading.error is None:
            entry = {"name": point.name, "value": reading.value, "unit": point.unit, "ref": point.ref}
            if reading.value is None:
                entry["invalid"] = True  # the device sent a value its map says means no data
            points.append(entry)
        else:
            failed.append({"name": point.name, "ref": point.ref, "error": str(reading.error)})
    record["state"] = poll.state
    record["points"] = points
    if failed:
        record["failed"] = failed
    return record


# --- influx: tagged by device (Prometheus: cli.plant_text) -----------------------------------------------


def influx_line(poll: Poll) -> str:
    """One line a device poll: measurement modbus, tags device, unit and the device's tags, a
    field a point read (its type fixed by its map entry; NaN and infinities left out)."""
    device = poll.device
    fields = []
    for reading in poll.readings or ():
        if reading.error is not None or reading.value is None:
            continue
        number = reading.point.number_of(reading.value)
        shown = _field_value(reading.value if number is None else number)
        if shown is not None:
            fields.append(f"{_escape(reading.point.name, KEY_SPECIALS)}={shown}")
    tags = {"device": device.name, "unit": str(device.unit)} | (device.tags or {})
    return influx_text("modbus", tags, fields, int(poll.time * 1_000_000_000))


# --- on a terminal: a live view ------------------------------------------------------------


class LiveView:
    """One row a device: its state in colour, the age of its last good poll, its round-trip
    time and error counts, and its points' latest values, a changed one highlighted."""

    COLOURS = {ONLINE: "green", OFFLINE: "bold red", "unknown": "yellow"}

    def __init__(self, plant) -> None:
        self.plant = plant
        self.lock = threading.Lock()
        self.changed: dict[str, set[str]] = {}
        self.previous: dict[str, dict[str, object]] = {}
        self.events: list[str] = []
        self.states: dict = {}

    def running(self, states: dict):
        from rich.live import Live  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only

        self.states = states
        return Live(self, refresh_per_second=4, transient=False)

    def __rich__(self):
        """The screen as it is now, built when rich draws it (4 times a second), not on every
        poll of every device."""
        with self.lock:
            return self._table()

    def report(self, item: Poll | Event) -> None:
        with self.lock:
            if isinstance(item, Event):  # the line stderr gets too, the last five kept
                self.events = (self.events + [event_line(item)])[-5:]
            elif item.readings is not None:
                values = {r.point.name: r.value for r in item.readings if r.error is None}
                before = self.previous.get(item.device.name, {})
                self.changed[item.device.name] = {
                    name for name, value in values.items() if before.get(name, value) != value
                }
                self.previous[item.device.name] = values

    def _table(self):
        from rich.console import Group  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only
        from rich.table import Table  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only
        from rich.text import Text  # noqa: PLC0415 - rich, 12-20 ms: the live display on a terminal only

        table = Table(title="mbtool poll", expand=False)
        for column in (
            "device",
            "link",
            "state",
            "last good",
            "rtt avg",
            "timeouts",
            "corrupt",
            "exceptions",
            "values",
        ):
            table.add_column(column)
        now = time.time()
        for name, state in self.states.items():
            stats = state.stats
            figures = stats.rtt_figures()
            age = "-" if state.last_success is None else f"{now - state.last_success:.1f} s ago"
            values = Text()
            for reading in (state.last_poll.readings or ()) if state.last_poll else ():
                if reading.error is not None:
                    continue
                style = "reverse" if reading.point.name in self.changed.get(name, ()) else ""
                values.append(f"{reading.point.name}={_shown(reading)} ", style=style)
            table.add_row(
                Text(name),
                Text(state.spec.link),
                Text(state.state, style=self.COLOURS.get(state.state, "")),
                age,
                "-" if figures is None else f"{figures['avg'] * 1000:.1f} ms",
                str(stats.outcomes["timeout"]),
                str(stats.outcomes["corrupt"]),
                str(stats.outcomes["exception"]),
                values,
            )
        return Group(table, *(Text(line, style="dim") for line in self.events))


# --- on exit: statistics and the verdict ----------------------------------------------------


def _statistics(runner: Plant, fmt: str, seconds: float) -> None:
    links, link_of = {}, {}
    for worker in runner.workers:
        total = PollStats()
        for state in worker.devices:
            total.add(state.stats)
        links[worker.spec.name] = (total, worker.state)
        link_of[worker.spec.name] = worker.spec
    # The timeout and retries each device's transactions had (its own, else its link's); a link's own.
    device_limits = {name: limits(s.spec, link_of[s.spec.link]) for name, s in runner.devices.items()}
    link_limits = {name: (spec.connection.timeout, spec.connection.retries) for name, spec in link_of.items()}
    if fmt == "json":
        record = {
            "seconds": round(seconds, 3),
            "devices": {
                name: {
                    "link": s.spec.link,
                    "state": s.state,
                    **_limits(device_limits[name]),
                    **s.stats.as_dict(),
                }
                for name, s in runner.devices.items()
            },
            "links": {
                worker.spec.name: {
                    "state": worker.state,
                    "open_failures": worker.open_failures,
                    **_limits(link_limits[worker.spec.name]),
                    **links[worker.spec.name][0].as_dict(),
                }
                for worker in runner.workers
            },
        }
        print(to_json(record), file=sys.stderr, flush=True)
        return
    rows = [("device", name, s.state, s.stats, device_limits[name]) for name, s in runner.devices.items()]
    rows += [("link", name, state, total, link_limits[name]) for name, (total, state) in links.items()]
    head = [
        "",
        "name",
        "state",
        "polls",
        "trans",
        "answered",
        "timeout",
        "corrupt",
        "not ours",
        "exc",
        "recovered",
        "rtt min/avg/p95/max ms",
        "timeout s",
        "retries",
    ]
    lines = [head]
    for kind, name, state, stats, (timeout, retries) in rows:
        rtt = stats.rtt.cell()
        exceptions = stats.exceptions_text()
        lines.append(
            [kind, name, state, str(stats.polls), str(stats.transactions), str(stats.outcomes["answered"]),
             str(stats.outcomes["timeout"]), str(stats.outcomes["corrupt"]), str(stats.outcomes["not_ours"]),
             exceptions, str(stats.recovered), rtt, f"{timeout:g}", str(retries)]
        )  # fmt: skip
    widths = [max(len(line[i]) for line in lines) for i in range(len(head))]
    for line in lines:
        print(
            "  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip(),
            file=sys.stderr,
        )
    sys.stderr.flush()


def _limits(pair: tuple[float, int]) -> dict:
    """A device's or link's timeout and retries, beside its counts (``timeout`` counts timeouts)."""
    return {"timeout_seconds": pair[0], "retries": pair[1]}


def _verdict(runner: Plant, interrupted: bool, rounds: int, ends: bool) -> Summary:
    """0 when every device answered its last poll, 8 when some did, else the failure's code;
    130 for a run that was to end (``ends``: --once, --rounds, --duration) stopped before it did,
    and for any stopped before a poll."""
    polls = [state.last_poll for state in runner.devices.values() if state.last_poll is not None]
    answered = [
        poll for poll in polls if poll.readings is not None and not isinstance(poll.error, PartialRead)
    ]
    failed = [poll for poll in polls if poll.readings is None]
    partial = len(polls) - len(answered) - len(failed)
    unpolled = len(runner.devices) - len(polls)  # stopped before its first poll: no answer either
    text = f"{len(answered)} of {len(runner.devices)} devices answered" + (
        f", {partial} in part" if partial else ""
    )
    if interrupted and (not polls or (ends and not runner.completed())):
        return Summary("interrupted before the run's end; " + text, ExitCode.INTERRUPTED)
    if interrupted:
        text = "interrupted; " + text
    elif rounds:  # --rounds counts the rounds of devices that answer: say what an offline one got
        short = [s for s in runner.devices.values() if s.polls < rounds]
        text += "".join(
            f"; {s.spec.name} polled {s.polls} time{'s' if s.polls != 1 else ''} of {rounds} ({s.state})"
            for s in short
        )
    if not failed and not partial and not unpolled:
        return Summary(text, ExitCode.OK)
    if answered or partial:
        return Summary(text, ExitCode.PARTIAL)
    if not failed:
        return Summary(text, ExitCode.INTERRUPTED)
    return Summary(text + f": {failed[0].error}", exit_code_for(failed[0].error))
