"""What ``poll`` and ``exporter`` say of a plant alike: the Prometheus text of its devices'
latest polls (poll's -o prom and --textfile, the exporter's /metrics), the exporter's
statistics of each device and link beside them (``PlantMetrics``), and the line a change of
state prints on stderr.  Commands do not import one another; this is the one place.
"""

from __future__ import annotations

import sys
import threading
from functools import lru_cache

from mbtool.cli.log import INFO, WARNING, log, log_line
from mbtool.cli.sinks.prom import (
    VALUE_HELP,
    Family,
    family_of,
    gauges,
    label_pairs,
    label_value,
    le,
    metric_name,
    sample_value,
    warn_counter_names,
    written,
)
from mbtool.cli.stamps import local_time
from mbtool.errors import UsageError
from mbtool.link.stats import OUTCOMES
from mbtool.plant.budget import budgets
from mbtool.plant.schedule import OFFLINE, ONLINE, OVERRUN, Event, view_of, views

UP, LAST_SUCCESS = "modbus_up", "modbus_last_success_timestamp_seconds"
VALUE = "modbus_value"  # a device's raw registers and bits (read = [...]), one family as read -o prom has it


def point_metric(reading) -> tuple[str, str, int | float] | None:
    """A point's reading as a gauge: the metric's name, its help (the point's description
    and unit) and the number; None when it has no sample: the point failed, its value is
    one the map calls invalid (a sample would be scraped as current), or text."""
    if reading.error is not None or reading.value is None:
        return None
    point = reading.point
    number = point.number_of(reading.value)  # an enum label's raw value, 1 or 0 for a bit
    if number is None:
        return None
    return *_named(point.name, point.description, point.unit), number


@lru_cache(maxsize=4096)
def _named(name: str, description: str, unit: str) -> tuple[str, str]:
    """A point's metric name and help, worked out once: a plant writes them every poll."""
    return metric_name(f"modbus_{name}"), (description or name) + (f" ({unit})" if unit else "")


def prom_text(states: list) -> str:
    """The exposition of the devices' latest polls (``prom_families``), written."""
    return written(prom_families(states))


def prom_families(states: list) -> list[Family]:
    """The families of the devices' latest polls: modbus_up and the last success a device,
    and a gauge a point read, a map's point named after it, a raw register or bit in
    modbus_value{table,address,ref}; a device down shows no value (it would be scraped as
    current).  ``states``: what the scheduler knows of each device (plant.schedule.DeviceState)."""
    metrics: dict[str, tuple[str, list[str]]] = {
        UP: ("1 when the device answered its last poll, 0 when it could not be read", []),
        LAST_SUCCESS: ("When the device last answered a poll, in seconds since the epoch", []),
    }
    for state in states:
        device = state.spec
        base = {"device": device.name} | (device.tags or {})
        pairs = label_pairs(base)
        poll = state.last_poll
        up = poll is not None and poll.readings is not None
        metrics[UP][1].append(f"{UP}{{{pairs}}} {int(up)}")
        if state.last_success is not None:
            metrics[LAST_SUCCESS][1].append(f"{LAST_SUCCESS}{{{pairs}}} {state.last_success!r}")
        for reading in poll.readings if up else ():
            metric = point_metric(reading)
            if metric is None:
                continue
            name, about, number = metric
            shown = sample_value(number)
            if shown is None:
                continue
            # The device's labels, then the point's: label_pairs(base | {...}), escaped once a device.
            point = reading.point
            if device.raw:
                name, about = VALUE, VALUE_HELP
                where = f'table="{point.table.name}",address="{point.address}",ref="{point.ref}"'
            else:
                where = f'ref="{label_value(point.ref)}"'
            metrics.setdefault(name, (about, []))[1].append(f"{name}{{{pairs},{where}}} {shown}")
    if not metrics[LAST_SUCCESS][1]:
        del metrics[LAST_SUCCESS]
    return gauges(metrics)


def point_name_clash(points, own: set[str], whose: str) -> str:
    """The first point whose metric is one of ``own`` (``whose`` metrics: "the exporter"), as
    a sentence; "" for none.  Two families of one name are no exposition."""
    for point in points:
        name = metric_name(f"modbus_{point.name}")
        if name in own:
            return f"point {point.name}: its metric, {name}, is one {whose} has of its own; rename the point"
    return ""


def refuse_point_names(plant, own: set[str], whose: str) -> None:
    """UsageError (exit 2, before anything is opened) for an inventory whose map points
    would be named as ``own`` metrics, or as its raw registers' family (modbus_value); a
    warning for a point named as a counter (metrics.warn_counter_names)."""
    if any(spec.raw for spec in plant.devices):
        own = own | {VALUE}
    for spec in plant.devices:
        clash = point_name_clash(spec.reader.points, own, whose)
        if clash:
            raise UsageError(f"{plant.path}: [devices.{spec.name}] map: {clash}")
    warned: set[str] = set()  # a map's points once, however many devices read them
    for spec in plant.devices:
        if not spec.raw:
            warn_counter_names(spec.reader.points, where=f"{plant.maps[spec.name]}: ", warned=warned)


def check_budgets(plant, strict: bool, log_format: str) -> None:
    """Each serial link whose groups ask more line time than it has: a warning with the figures,
    or with poll --strict the refusal (exit 2), before anything is opened (poll's and the
    exporter's inventory alike)."""
    for budget in budgets(plant.links, plant.devices):
        if budget.seconds <= 1:
            continue
        line = f"{budget.line()}: more than the line has, the groups cannot keep their intervals"
        if strict:
            raise UsageError(f"{plant.path}: {line} (--strict)")
        log(WARNING, f"warning: {line}", log_format, link=budget.link)


def event_line(event) -> str:
    """A change of state (plant.schedule.Event) as one line: a device or a link going offline
    and why, with the wait before the next try, or coming back."""
    what = f"link {event.name}" if event.kind == "link" else event.name
    line = f"{local_time(event.time)} {what} {event.state}"
    if event.reason:
        line += f": {event.reason}"
    if event.retry_in is not None:
        line += f"; next try in {event.retry_in:g} s"
    return line


def event_log(event, fmt: str) -> str:
    """A change of state as a line of the run's log format: a device or link offline is a
    warning, its return information (Telegraf's execd: W! and I!, never E!)."""
    level = WARNING if event.state in (OFFLINE, OVERRUN) else INFO
    return log_line(
        level,
        event_line(event),
        fmt,
        **{event.kind: event.name},
        state=event.state,
        reason=event.reason or None,
        retry_in=event.retry_in,
    )


# --- inventory: the plant's metrics, rendered as each device reports --------------------------


class PlantMetrics:
    """The plant's exposition, kept ready for any number of scrapes.

    A device's families (its points, modbus_up and its last success, as poll's Prometheus
    text has them; its statistics) and its link's are written when the device's poll is
    reported, from the copies of the device's and the link's state that the Poll carries
    (plant.schedule: a reader never looks at a link thread's own state).  A scrape joins what
    was written, under a lock, and neither waits on a device nor renders the plant's
    samples itself: prometheus_client's generate_latest takes some 16 ms for 50 devices of
    10 points, and a scrape should answer in a few.  The statistics are written as poll's
    text is, not through generate_latest: 15 us a device report rather than 400, which
    matters when 50 devices report at once and a scrape waits for the interpreter."""

    def __init__(self, labels: dict[str, str] | None = None, log_format: str = "text") -> None:
        self.log_format = log_format  # of its lines on stderr (cli.log)
        self.labels = labels or {}  # the inventory's [poll] site and instance, on the statistics too
        self.lock = threading.Lock()
        self.blocks: dict[tuple[str, str], list[Family]] = {}  # key -> its families
        self.changes = 0  # blocks written so far
        self.joined: tuple[int, bytes] = (-1, b"")  # the text as of that many changes

    def watch(self, runner) -> None:
        """The plant's devices and links, each shown (down, unknown) before its first poll
        (before the plant runs: its links' threads have not started)."""
        for view in views([state.spec for state in runner.devices.values()]).values():
            self._device(view)
        for worker in runner.workers:
            self._link(worker.view())

    def report(self, item) -> None:
        """What a link's worker reports (plant.schedule): a poll, or a change of state."""
        if isinstance(item, Event):
            print(event_log(item, self.log_format), file=sys.stderr, flush=True)
            if item.link is not None:
                self._link(item.link)
            return
        self._device(view_of(item))
        self._link(item.link)

    def _device(self, state) -> None:
        self._keep(
            ("device", state.spec.name),
            prom_families([state]) + device_stats(state.spec.name, state.stats, self.labels),
        )

    def _link(self, link) -> None:
        # The link's totals as the worker keeps them (plant.schedule.LinkView): adding up its
        # every device again after each poll cost as much as the poll itself from a few hundred
        # devices on.
        families = link_stats(link.name, link.stats, link.state == ONLINE, link.open_failures, self.labels)
        self._keep(("link", link.name), families)

    def _keep(self, key: tuple[str, str], families: list[Family]) -> None:
        with self.lock:
            self.blocks[key] = families
            self.changes += 1

    def text(self) -> bytes:
        """Every device's and link's families, one HELP and TYPE a family, its samples together
        (joined again only when a device or link has reported since)."""
        with self.lock:
            changes, blocks = self.changes, list(self.blocks.values())
            if self.joined[0] == changes:
                return self.joined[1]
        heads: dict[str, str] = {}
        samples: dict[str, list[str]] = {}
        for families in blocks:
            for name, head, body in families:
                if name not in heads:
                    heads[name], samples[name] = head, []
                samples[name].append(body)
        text = "".join(head + "".join(samples[name]) for name, head in heads.items()).encode()
        with self.lock:
            if self.changes == changes:
                self.joined = (changes, text)
        return text


def _transactions(prefix: str, pair: str, whose: str, stats) -> list[Family]:
    """Every transaction's outcome, the exceptions by code, the retries that recovered and
    the round-trip histogram (link.stats), each sample labelled ``pair``."""
    name = f"{prefix}request_duration_seconds"
    return [
        family_of(
            f"{prefix}transactions_total",
            "counter",
            f"Transactions {whose}, by outcome: answered, exception, timeout, corrupt (a CRC/LRC or "
            "framing error), not_ours (a frame for another unit or transaction), link_lost (the peer "
            "hung up), connection (the link could not be opened or reached)",
            (f'{prefix}transactions_total{{{pair},outcome="{o}"}} {stats.outcomes[o]}' for o in OUTCOMES),
        ),
        family_of(
            f"{prefix}exceptions_total",
            "counter",
            f"Exception responses {whose}, by exception code (hex, as the spec writes them)",
            (
                f'{prefix}exceptions_total{{{pair},code="{code:02X}"}} {count}'
                for code, count in sorted(stats.exceptions.items())
            ),
        ),
        family_of(
            f"{prefix}retries_recovered_total",
            "counter",
            f"Transactions {whose} answered on a retry",
            [f"{prefix}retries_recovered_total{{{pair}}} {stats.recovered}"],
        ),
        family_of(
            f"{prefix}untimed_replies_total",
            "counter",
            f"Replies {whose} whose round trip is not known (they came while mbtool was busy, or "
            "after a retry without transaction ids): left out of the histogram",
            [f"{prefix}untimed_replies_total{{{pair}}} {stats.untimed}"],
        ),
        family_of(
            name,
            "histogram",
            f"Round-trip time of the replies {whose}: from a request's last byte written to its "
            "reply's last byte read, in seconds",
            [
                *(
                    f'{name}_bucket{{{pair},le="{le(bound)}"}} {count}'
                    for bound, count in stats.rtt.buckets()
                ),
                f"{name}_sum{{{pair}}} {stats.rtt.total!r}",
                f"{name}_count{{{pair}}} {stats.rtt.count}",
            ],
        ),
    ]


def device_stats(name: str, stats, labels: dict | None = None) -> list[Family]:
    """A device's statistics in the text format: its polls and its transactions (``labels``:
    the fleet's site and instance)."""
    pair = label_pairs({"device": name} | (labels or {}))
    return [
        family_of(
            "modbus_polls_total",
            "counter",
            "Polls of the device",
            [f"modbus_polls_total{{{pair}}} {stats.polls}"],
        ),
        family_of(
            "modbus_failed_polls_total",
            "counter",
            "Polls of the device that read nothing",
            [f"modbus_failed_polls_total{{{pair}}} {stats.failed_polls}"],
        ),
        *_transactions("modbus_", pair, "with the device", stats),
    ]


def link_stats(name: str, stats, up: bool, open_failures: int, labels: dict | None = None) -> list[Family]:
    """A link's state and statistics in the text format: its devices' transactions added up
    (``labels``: the fleet's site and instance)."""
    pair = label_pairs({"link": name} | (labels or {}))
    return [
        family_of(
            "modbus_link_up",
            "gauge",
            "1 when the link is open, 0 when it cannot be opened or has not been",
            [f"modbus_link_up{{{pair}}} {int(up)}"],
        ),
        family_of(
            "modbus_link_open_failures_total",
            "counter",
            "Times the link could not be opened",
            [f"modbus_link_open_failures_total{{{pair}}} {open_failures}"],
        ),
        *_transactions("modbus_link_", pair, "over the link", stats),
    ]
