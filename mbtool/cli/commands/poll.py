"""``mbtool poll PLANT.toml``: every device of a plant, from one process.

One worker a link polls its devices one transaction at a time, every link at once
(mbtool.plant.schedule); this module turns what they report into output: plain lines,
JSON lines, long CSV, influx, Prometheus text or a textfile of the whole plant, a live
view on a terminal, one line on stderr for each change of state, and statistics on exit.
"""

from __future__ import annotations

import math
import sys
import time

import click

from mbtool.cli.broker import hand_writes, make_publisher, stats_line
from mbtool.cli.frames import HexTrace
from mbtool.cli.log import INFO, WARNING, log, log_format_option, run_log_format
from mbtool.cli.metrics import name_problem
from mbtool.cli.notify import systemd_notifier
from mbtool.cli.param_types import FilePath, PositiveFloat, shard_option
from mbtool.cli.plant_text import (
    LAST_SUCCESS,
    UP,
    check_budgets,
    event_line,
    event_log,
    prom_text,
    refuse_point_names,
)
from mbtool.cli.session import warn_insecure
from mbtool.cli.sinks import PLANT, formats, sink
from mbtool.cli.sinks.json import event_record, to_json
from mbtool.cli.sinks.prom import check_textfile, write_textfile
from mbtool.cli.sinks.table import PlantView
from mbtool.cli.stamps import local_time
from mbtool.errors import ExitCode, PartialRead, UsageError, Verdict, exit_code_for
from mbtool.link.stats import OUTCOMES
from mbtool.mqtt.settings import mqtt_settings
from mbtool.mqtt.topics import PlantEvent, iso_time
from mbtool.plant.inventory import load_inventory, shard
from mbtool.plant.schedule import OFFLINE, Event, Pace, Plant, Poll, limits, view_of, views
from mbtool.plant.stats import PollStats
from mbtool.words import counted


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
    type=click.Choice(formats(PLANT)),
    help="Output: plain lines, JSON lines (one a device poll), CSV (long form), InfluxDB line "
    "protocol or Prometheus text. Default: the inventory's [poll] output, else a live view on "
    "a terminal and plain lines in a pipe.",
)
@click.option(
    "--textfile",
    metavar="PATH",
    type=FilePath(dir_okay=False),
    help="Rewrite the whole plant's metrics (Prometheus text) to PATH atomically after each "
    "round of the fastest devices, for node_exporter's textfile collector; a dead device shows "
    "as modbus_up 0.",
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
@click.option(
    "--measurement",
    metavar="NAME",
    help="-o influx: the measurement of the devices that name none of their own "
    "(measurement = in the inventory). Default: modbus.",
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
    "--strict",
    is_flag=True,
    help="Refuse (exit 2, nothing opened) an inventory whose poll groups ask a serial link for "
    "more line time than it has, as the budget check at load figures it; without it, a warning.",
)
@shard_option
@log_format_option
@click.option(
    "--hex-link",
    "hex_links",
    metavar="LINK",
    multiple=True,
    help="--hex for this link alone (repeat it for several).",
)
@click.option(
    "--mqtt",
    "mqtt_url",
    metavar="URL",
    help="Publish every poll to the MQTT broker at URL (mqtt://HOST[:PORT], mqtts://HOST[:PORT]) "
    "as well: the inventory's [mqtt] settings with this url, else the defaults (docs/mqtt.md).",
)
def poll(
    inventory,
    output_format,
    textfile,
    once,
    rounds,
    duration,
    stats_format,
    measurement,
    no_header,
    hex_trace,
    hex_links,
    mqtt_url,
    shard_part,
    strict,
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
    plant = load_inventory(inventory, formats(PLANT))
    if shard_part is not None:
        plant = shard(plant, *shard_part)

    for name, link in plant.links.items():
        warn_insecure(link.connection, name)
    log_format = run_log_format()
    check_budgets(plant, strict, log_format)
    fmt = output_format or plant.output
    live = fmt is None and textfile is None and sys.stdout.isatty()
    fmt = fmt or "plain"
    polls = sink(fmt).PlantPolls
    if measurement is not None:
        problem = name_problem(measurement, "a measurement", influx=True)
        if not polls.measured:
            problem = "--measurement names InfluxDB's measurement: it goes with -o influx"
        if problem:
            raise UsageError(f"--measurement {measurement!r}: {problem}")
    if polls.exposes or textfile:
        # A point named as a device's own metrics (up) would make two families of one name.
        refuse_point_names(plant, {UP, LAST_SUCCESS}, "mbtool's Prometheus text")
    if textfile:
        check_textfile(textfile)  # a folder that is not there: exit 7 now, not after a round
    if once:
        rounds = 1
    unknown = [name for name in hex_links if name not in plant.links]
    if unknown:
        raise UsageError(
            f"--hex-link {unknown[0]}: no [links.{unknown[0]}] in {inventory} (links: {', '.join(plant.links)})"
        )
    trace = HexTrace if hex_trace or hex_links else None  # made by each traced link, labelled
    mqtt = mqtt_settings(plant.mqtt, inventory, plant.devices, mqtt_url, plant.labels, shard_part)
    output = PlantOutput(fmt, textfile, no_header, plant, measurement or "modbus", log_format)
    view = LiveView(plant) if live else None
    report = view.report if view else output.report
    publisher = None
    if mqtt is not None:
        publisher = make_publisher(mqtt, plant.devices, plant.maps, quiet=live)
        report = _both(report, publisher.report, plant.labels)
        if view:
            view.publisher = publisher
    runner = Plant(
        plant.links,
        plant.devices,
        report,
        rounds or 0,
        trace,
        hex_links or None,
    )
    if publisher is not None:
        if mqtt is not None and mqtt.writes:  # a publisher is made for [mqtt]
            hand_writes(publisher, runner)
        publisher.start()
    started = time.monotonic()
    interrupted = False
    notifier = systemd_notifier()  # systemd's Type=notify: ready now, the watchdog fed while it runs
    if notifier:
        notifier.ready(
            f"polling {counted(len(plant.devices), 'device')} on {counted(len(plant.links), 'link')}",
            runner.moved,
        )
    try:
        if view:
            with view.running():
                runner.run(duration)
        else:
            runner.run(duration)
    except KeyboardInterrupt:
        interrupted = True
    finally:
        runner.stop.set()
        if publisher is not None:
            publisher.close()
        if notifier:
            notifier.stopping()
    output.close()
    _statistics(runner, stats_format, time.monotonic() - started, log_format, publisher)
    return _verdict(runner, interrupted, rounds or 0, bool(rounds or duration))


def _both(first, publish, labels: dict):
    """The plant's one report, on the thread that runs it, handed to the output and the MQTT
    publisher (which only enqueues): its Polls, and each Event as -o json's record."""

    def report(item: Poll | Event) -> None:
        first(item)
        if isinstance(item, Poll):
            publish(item)
        else:
            publish(PlantEvent(event_record(item, iso_time(item.time), labels)))

    return report


class PlantOutput:
    """What the workers report, written as it comes, on the one thread that runs the plant, by
    the format's sink (its PlantPolls); the whole plant's Prometheus text a round, for -o prom
    and --textfile."""

    def __init__(
        self, fmt: str, textfile: str | None, no_header: bool, plant, measurement: str, log_format: str
    ) -> None:
        # [poll] site and instance: keys of every JSON record
        self.polls = sink(fmt).PlantPolls(sys.stdout, not no_header, measurement, plant.labels)
        self.log_format = log_format  # of the lines on stderr (cli.log)
        self.textfile = textfile
        self.swept = False  # a killed run's temporaries are looked for at the first write only
        self.states = views(plant.devices)  # each device as its latest Poll left it
        self.pending = {device.name for device in plant.devices}  # not yet polled this round
        self.unwritten = False  # a device has reported since the last exposition
        self.exposed = False  # the first round is written
        self.labels = plant.labels  # [poll] site and instance: keys of every JSON record

    def report(self, item: Poll | Event) -> None:
        if isinstance(item, Event):
            print(event_log(item, self.log_format), file=sys.stderr, flush=True)
            self.polls.event(item, local_time(item.time))
        else:
            self._poll(item)
        sys.stdout.flush()

    def _poll(self, poll: Poll) -> None:
        device, when = poll.device, local_time(poll.time)
        self.states[device.name] = view_of(poll)
        if poll.readings is None:
            if poll.state != OFFLINE:  # an offline device's probes: its event said why
                message = f"{when} {device.name}: {poll.error}"
                log(WARNING, message, self.log_format, device=device.name, error=str(poll.error))
        else:
            for reading in poll.readings:
                if reading.error is not None:  # its message names the point (plan.PointException)
                    message = f"{when} {device.name} {reading.error}"
                    log(WARNING, message, self.log_format, device=device.name, point=reading.point.name)
        self.polls.poll(poll, when)
        if self.polls.exposes or self.textfile:
            # The Prometheus text is the whole plant's, one exposition a round.
            self.pending.discard(device.name)
            self.unwritten = True
            if self._round_done():
                self._expose()

    def _round_done(self) -> bool:
        """The first round: every device has reported since the start, but those offline, tried
        once a back-off, which would hold every other device's values back.  After it, a round
        of the fastest devices not offline: one polled hourly must not hold back the values of
        one polled every second, and each device's samples carry its own last success."""
        live = [state for state in self.states.values() if state.state != OFFLINE]
        if self.exposed and live:
            shortest = min(state.spec.fastest for state in live)  # a device's fastest group's
            live = [state for state in live if state.spec.fastest == shortest]
        return not any(state.spec.name in self.pending for state in live)

    def _expose(self) -> None:
        """The plant's exposition: on stdout (-o prom; a run is a stream of whole ones) and to
        the textfile, rewritten whole."""
        text = prom_text(list(self.states.values()))
        if self.polls.exposes:
            sys.stdout.write(text)
        if self.textfile:
            write_textfile(text, self.textfile, sweep=not self.swept)
            self.swept = True
        self.pending = set(self.states)
        self.unwritten = False
        self.exposed = True

    def close(self) -> None:
        if self.unwritten:
            self._expose()  # the last state of every device, whatever the round
        sys.stdout.flush()


# --- on a terminal: a live view ------------------------------------------------------------


class LiveView(PlantView):
    """poll's live view of ``plant`` on a terminal (cli.sinks.table.PlantView), its changes of
    state in the words stderr has."""

    def __init__(self, plant, clock=time.time) -> None:
        super().__init__(plant, event_line, clock)
        self.publisher = None  # poll --mqtt's: the broker's state in the title

    def title_note(self) -> str:
        return "" if self.publisher is None else "; " + stats_line(self.publisher.stats())


# --- on exit: statistics and the verdict ----------------------------------------------------


def _statistics(runner: Plant, stats: str, seconds: float, log_format: str, publisher=None) -> None:
    """The statistics on stderr (``stats``: --stats, a table or one JSON object): in the text
    log format as they are, in the others each line an information record."""
    links, link_of = {}, {}
    for worker in runner.workers:
        total = PollStats()
        for device_state in worker.devices:
            total.add(device_state.stats)
        links[worker.spec.name] = (total, worker.state)
        link_of[worker.spec.name] = worker.spec
    # The timeout and retries each device's transactions had (its own, else its link's); a link's own.
    device_limits = {name: limits(s.spec, link_of[s.spec.link]) for name, s in runner.devices.items()}
    link_limits = {name: (spec.connection.timeout, spec.connection.retries) for name, spec in link_of.items()}
    if stats == "json":
        record = {
            "seconds": round(seconds, 3),
            "devices": {
                name: {
                    "link": s.spec.link,
                    "state": s.state,
                    **_limits(device_limits[name]),
                    **s.stats.as_dict(),
                    **(
                        {"groups": {g.group.name: _pace_record(g.pace()) for g in s.groups}}
                        if s.spec.groups
                        else {}
                    ),
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
        if publisher is not None:
            record["mqtt"] = publisher.stats()
        _stats_line(to_json(record), log_format)
        return
    rows = [("device", name, s.state, s.stats, device_limits[name]) for name, s in runner.devices.items()]
    rows += [("link", name, state, total, link_limits[name]) for name, (total, state) in links.items()]
    # A column for every outcome a transaction may have (link.stats), the exceptions last, by code.
    outcomes = [outcome for outcome in OUTCOMES if outcome != "exception"]
    lines = [
        ["", "name", "state", "polls", "trans", *(o.replace("_", " ") for o in outcomes), "exc", "recovered",
         "rtt min/avg/p95/max ms", "timeout s", "retries"]
    ]  # fmt: skip
    for kind, name, state, totals, (timeout, retries) in rows:
        counts = [str(totals.outcomes[outcome]) for outcome in outcomes]
        lines.append(
            [kind, name, state, str(totals.polls), str(totals.transactions), *counts, totals.exceptions_text(),
             str(totals.recovered), totals.rtt.cell(), f"{timeout:g}", str(retries)]
        )  # fmt: skip
    widths = [max(len(line[i]) for line in lines) for i in range(len(lines[0]))]
    for line in lines:
        _stats_line(
            "  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip(),
            log_format,
        )
    _group_table(runner, log_format)
    if publisher is not None:
        _stats_line(stats_line(publisher.stats()), log_format)
    sys.stderr.flush()


def _group_table(runner: Plant, log_format: str) -> None:
    """The poll groups of the devices that have them: the interval each asked, the one achieved
    (the mean between its polls), its polls and its overruns (polls that started late, slots skipped)."""
    lines = [["group", "device", "asked s", "achieved s", "polls", "overruns"]]
    for name, state in runner.devices.items():
        for pace in (group.pace() for group in state.groups if state.spec.groups):
            asked = "once" if pace.asked == math.inf else f"{pace.asked:g}"
            achieved = "-" if pace.achieved is None else f"{pace.achieved:.3f}"
            lines.append([pace.group, name, asked, achieved, str(pace.polls), str(pace.overruns)])
    if len(lines) == 1:
        return
    widths = [max(len(line[i]) for line in lines) for i in range(len(lines[0]))]
    for line in lines:
        _stats_line(
            "  ".join(cell.ljust(width) for cell, width in zip(line, widths, strict=True)).rstrip(),
            log_format,
        )


def _pace_record(pace: Pace) -> dict:
    """A group's pace in --stats json: ``once`` for a group read once (it has no interval)."""
    if pace.asked == math.inf:
        return {"once": True, "polls": pace.polls}
    achieved = None if pace.achieved is None else round(pace.achieved, 6)
    return {
        "interval_seconds": pace.asked,
        "achieved_seconds": achieved,
        "polls": pace.polls,
        "overruns": pace.overruns,
    }


def _stats_line(line: str, log_format: str) -> None:
    if log_format == "text":
        print(line, file=sys.stderr, flush=True)
    else:
        log(INFO, line, log_format)


def _limits(pair: tuple[float, int]) -> dict:
    """A device's or link's timeout and retries, beside its counts (``timeout`` counts timeouts)."""
    return {"timeout_seconds": pair[0], "retries": pair[1]}


def _verdict(runner: Plant, interrupted: bool, rounds: int, ends: bool) -> Verdict:
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
    text = f"{len(answered)} of {counted(len(runner.devices), 'device')} answered" + (
        f", {partial} in part" if partial else ""
    )
    if interrupted and (not polls or (ends and not runner.completed())):
        return Verdict("interrupted before the run's end; " + text, ExitCode.INTERRUPTED)
    if interrupted:
        text = "interrupted; " + text
    elif rounds:  # --rounds counts the rounds of devices that answer: say what an offline one got
        short = [s for s in runner.devices.values() if s.polls < rounds]
        text += "".join(
            f"; {s.spec.name} polled {counted(s.polls, 'time')} of {rounds} ({s.state})" for s in short
        )
    if not failed and not partial and not unpolled:
        return Verdict(text, ExitCode.OK)
    if answered or partial:
        return Verdict(text, ExitCode.PARTIAL)
    if not failed:
        return Verdict(text, ExitCode.INTERRUPTED)
    error = failed[0].error
    assert error is not None  # a poll without readings is one that failed
    return Verdict(text + f": {error}", exit_code_for(error))
