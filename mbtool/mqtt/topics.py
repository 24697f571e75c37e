"""The topic tree and the payloads of plain JSON::

    mbtool/{inventory}/status                  online / offline (the birth, and the last will)
    mbtool/{inventory}/events                  {"time": ..., "event": "offline", "device": "m1", "reason": ...}
    mbtool/{inventory}/{device}                {"time": ..., "instance": "edge7", "unit": 1, "points": {"flow": 21.5}}
    mbtool/{inventory}/{device}/status         online / offline, as mbtool judges the device
    mbtool/{inventory}/{device}/{point}        the bare value (points = "point")

(the device's topic as the ``topic`` template makes it).  A value is JSON: a number, true or
false, a label as a string, null for a value the device marks invalid and for NaN and the
infinities, which JSON has no words for.
"""

from __future__ import annotations

import json
import math
from datetime import UTC, datetime

from mbtool.codec.record import record
from mbtool.mqtt.settings import MqttSettings, fill

ONLINE, OFFLINE = "online", "offline"


@record
class PlantEvent:
    """A change of state of a plant's device or link, as poll -o json's record says it
    (``cli.sinks.json.event_record``), for the poller's events topic."""

    record: dict


@record
class DevicePoll:
    """A poll of a device that is no plant's (read --interval --mqtt), as the publisher takes
    it: its values by name (None: the poll failed) and the device's state after it."""

    device: str
    time: float  # time.time(): when its request went out
    values: dict | None
    state: str
    group: str = ""  # read --interval's points are one group, as a plant device's default is


class Topics:
    """Every topic of a plant, filled in once."""

    def __init__(self, settings: MqttSettings, devices: list) -> None:
        self.status = fill(settings.status_topic, settings)
        self.events = fill(settings.events_topic, settings)
        self.device = {device.name: fill(settings.topic, settings, device) for device in devices}

    def device_status(self, device: str) -> str:
        return f"{self.device[device]}/status"

    def point(self, device: str, point: str) -> str:
        return f"{self.device[device]}/{point}"


def json_value(value):
    """A point's value as JSON holds it."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def device_payload(when: float, labels: dict, unit: int, values: dict[str, object]) -> bytes:
    """One device poll's message: its time (UTC, ISO 8601), the fleet's labels ([poll] site
    and instance, keys of their own as in poll -o json's records), unit id and points."""
    record = {"time": iso_time(when), **labels, "unit": unit, "points": values}
    try:
        return _dumps(record)
    except ValueError:  # NaN or an infinity, which JSON has no words for: null, in a copy
        record["points"] = {name: json_value(value) for name, value in values.items()}
        return _dumps(record)


def event_payload(record: dict) -> bytes:
    """A change of state's message: the record as it is."""
    return _dumps(record)


# One encoder for every message: json.dumps makes a new one at each call that sets any of these.
_ENCODER = json.JSONEncoder(ensure_ascii=False, separators=(",", ":"), allow_nan=False)


def _dumps(record: dict) -> bytes:
    return _ENCODER.encode(record).encode()


def point_payload(value) -> bytes:
    """A point's bare value: a label as its text, anything else as JSON writes it."""
    if isinstance(value, str):
        return value.encode()
    return json.dumps(json_value(value)).encode()


def iso_time(when: float) -> str:
    return datetime.fromtimestamp(when, UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")
