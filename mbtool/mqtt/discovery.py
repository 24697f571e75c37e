"""Home Assistant's MQTT discovery: a retained config a point, on
``homeassistant/<component>/<node_id>/<object_id>/config``, so each point is an entity, of
its device, with no YAML.

A bit is a ``binary_sensor``, any other point a ``sensor`` (an enum's labels its options);
with ``writes = true`` a point that may be written is a ``switch`` (a bit), a ``select`` (an
enum) or a ``number`` (its type's range, scaled, in steps of its scale), whose
``command_topic`` is its ``/set``.
Its state is the device's JSON message (a template picks the point; a message that lacks it,
as ``on_change`` sends, leaves the entity's state as it is) or the point's own topic.  The
entity is available while the poller and the device are both online.
"""

from __future__ import annotations

import json
import re
import struct
from decimal import Decimal

from mbtool.codec.values import TYPES
from mbtool.mqtt.settings import MqttSettings
from mbtool.mqtt.topics import Topics

# What Home Assistant makes of a unit: its device class, and its state class when the
# value only ever adds up (an energy meter's register).
DEVICE_CLASSES = {
    "V": "voltage", "mV": "voltage", "kV": "voltage",
    "A": "current", "mA": "current",
    "W": "power", "kW": "power", "MW": "power",
    "VA": "apparent_power", "kVA": "apparent_power",
    "var": "reactive_power", "kvar": "reactive_power",
    "Wh": "energy", "kWh": "energy", "MWh": "energy",
    "Hz": "frequency",
    "°C": "temperature", "°F": "temperature", "K": "temperature",
    "Pa": "pressure", "hPa": "pressure", "kPa": "pressure", "bar": "pressure", "mbar": "pressure",
    "psi": "pressure",
    "m³/h": "volume_flow_rate", "L/min": "volume_flow_rate", "m³": "volume", "L": "volume",
    "s": "duration", "min": "duration", "h": "duration",
}  # fmt: skip
# The spellings maps use for the units above.
UNIT_SPELLINGS = {"degC": "°C", "C": "°C", "degF": "°F", "m3/h": "m³/h", "m3": "m³", "l/min": "L/min", "VAr": "var",
                  "kVAr": "kvar"}  # fmt: skip
TOTALS = {"energy", "volume"}
SLUG = re.compile(r"[^a-zA-Z0-9_-]+")


def slug(text: str) -> str:
    """An id Home Assistant takes in a topic level: letters, digits, _ and -."""
    return SLUG.sub("_", text).strip("_") or "_"


def configs(settings: MqttSettings, topics: Topics, devices: list, headers: dict) -> list[tuple[str, bytes]]:
    """(topic, payload) of every point's config.  ``headers``: a device's map header
    (``registermap.header.DeviceHeader``), by device name, for those that have one."""
    out = []
    for device in devices:
        node = slug(f"mbtool_{settings.inventory}_{device.name}")
        header = headers.get(device.name)
        about = {"identifiers": [node], "name": device.name}
        if header is not None and header.manufacturer:
            about["manufacturer"] = header.manufacturer
        if header is not None and header.model:
            about["model"] = header.model
        for point in device.reader.points:
            component, config = _entity(settings, topics, device.name, point)
            object_id = slug(point.name)
            config |= {
                "name": point.name,
                "unique_id": f"{node}_{object_id}",
                "availability": [{"topic": topics.status}, {"topic": topics.device_status(device.name)}],
                "availability_mode": "all",
                "device": about,
            }
            topic = f"{settings.discovery_prefix}/{component}/{node}/{object_id}/config"
            out.append((topic, json.dumps(config, ensure_ascii=False).encode()))
    return out


def _entity(settings: MqttSettings, topics: Topics, device: str, point) -> tuple[str, dict]:
    """The component a point is and the config of its state (and its command)."""
    per_point = settings.per_point
    state_topic = topics.point(device, point.name) if per_point else topics.device[device]
    key = json.dumps(point.name)
    command = (
        {"command_topic": f"{topics.point(device, point.name)}/set"} if _writable(settings, point) else None
    )
    if point.is_bit:
        shown = (
            "{{ 'ON' if value == 'true' else 'OFF' }}"
            if per_point
            else (
                f"{{% if {key} in value_json.points %}}"
                f"{{{{ 'ON' if value_json.points[{key}] else 'OFF' }}}}"
                "{% else %}{{ this.state | upper }}{% endif %}"
            )
        )
        config = {
            "state_topic": state_topic,
            "value_template": shown,
            "payload_on": "ON",
            "payload_off": "OFF",
        }
        return ("switch", config | command) if command else ("binary_sensor", config)
    config = {"state_topic": state_topic}
    if not per_point:
        config["value_template"] = (
            f"{{% if {key} in value_json.points %}}{{{{ value_json.points[{key}] }}}}"
            "{% else %}{{ this.state }}{% endif %}"
        )
    if point.enum is not None:
        options = {"options": list(point.enum.values())}
        if command:
            return "select", config | options | command
        return "sensor", config | {"device_class": "enum"} | options
    if point.type == "string":
        return "sensor", config
    unit = UNIT_SPELLINGS.get(point.unit, point.unit)
    if unit:
        config["unit_of_measurement"] = unit
    device_class = DEVICE_CLASSES.get(unit)
    if device_class and not (command and device_class in TOTALS):  # a number has no energy class
        config["device_class"] = device_class
    if command and point.scale_ref is None:
        return "number", config | command | _range(point) | {"mode": "box"}
    config["state_class"] = "total_increasing" if device_class in TOTALS else "measurement"
    return "sensor", config


def _writable(settings: MqttSettings, point) -> bool:
    return settings.writes and point.writable and (settings.allow is None or point.name in settings.allow)


def _range(point) -> dict:
    """A number's min, max and step: its type's range, scaled (the step its scale)."""
    fmt = TYPES[point.type].fmt
    if fmt in ("f", "d"):
        low, high = -3.4e38, 3.4e38
    else:
        bits = 8 * struct.calcsize(fmt)
        low, high = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if fmt.islower() else (0, (1 << bits) - 1)
    scale, offset = point.scale or Decimal(1), point.offset or Decimal(0)
    ends = sorted(float(Decimal(end) * scale + offset) for end in (low, high))
    step = float(abs(scale)) if fmt not in ("f", "d") else 0.001
    return {"min": ends[0], "max": ends[1], "step": step}
