"""What ``poll`` and ``exporter`` say of a plant alike: the Prometheus text of its devices'
latest polls (poll's -o prom and --textfile, the exporter's /metrics) and the line a change
of state prints on stderr.  Commands do not import one another; this is the one place.
"""

from __future__ import annotations

from functools import lru_cache

from mbtool.cli.metrics import _exposition, _label_pairs, _label_value, _metric_name, _sample_value
from mbtool.cli.stamps import local_time

UP, LAST_SUCCESS = "modbus_up", "modbus_last_success_timestamp_seconds"


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
    return _metric_name(f"modbus_{name}"), (description or name) + (f" ({unit})" if unit else "")


def prom_text(states: list) -> str:
    """The exposition of the devices' latest polls: modbus_up and the last success a device,
    and a gauge a point read; a device down shows no value (it would be scraped as current).
    ``states``: what the scheduler knows of each device (plant.schedule.DeviceState)."""
    metrics = {
        UP: ("1 when the device answered its last poll, 0 when it could not be read", []),
        LAST_SUCCESS: ("When the device last answered a poll, in seconds since the epoch", []),
    }
    for state in states:
        device = state.spec
        base = {"device": device.name} | (device.tags or {})
        pairs = _label_pairs(base)
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
            shown = _sample_value(number)
            if shown is None:
                continue
            # The device's labels, then ref: _label_pairs(base | {"ref": ...}), escaped once a device.
            metrics.setdefault(name, (about, []))[1].append(
                f'{name}{{{pairs},ref="{_label_value(reading.point.ref)}"}} {shown}'
            )
    if not metrics[LAST_SUCCESS][1]:
        del metrics[LAST_SUCCESS]
    return _exposition(metrics)


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
