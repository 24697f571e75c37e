"""Home Assistant's MQTT discovery: a retained config a point, on
``homeassistant/<component>/<node_id>/<object_id>/config``, so each point is an entity, of
its device, with no YAML.

A bit is a ``binary_sensor``, any other point a ``sensor`` (an enum's labels its options).
Its state is the device's JSON message (a template picks the point; a message that lacks it,
as ``on_change`` sends, leaves the entity's state as it is) or the point's own topic.  The
entity is available while the poller and the device are both online.
"""

from __future__ import annotations

import json
import re

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
    """The component a point is and the config of its state."""
    per_point = settings.per_point
    state_topic = topics.point(device, point.name) if per_point else topics.device[device]
    key = json.dumps(point.name)
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
        return "binary_sensor", {"state_topic": state_topic, "value_template": shown,
                                 "payload_on": "ON", "payload_off": "OFF"}  # fmt: skip
    config = {"state_topic": state_topic}
    if not per_point:
        config["value_template"] = (
            f"{{% if {key} in value_json.points %}}{{{{ value_json.points[{key}] }}}}"
            "{% else %}{{ this.state }}{% endif %}"
        )
    if point.enum is not None:
        return "sensor", config | {"device_class": "enum", "options": list(point.enum.values())}
    if point.type == "string":
        return "sensor", config
    unit = UNIT_SPELLINGS.get(point.unit, point.unit)
    if unit:
        config["unit_of_measurement"] = unit
    device_class = DEVICE_CLASSES.get(unit)
    if device_class:
        config["device_class"] = device_class
    config["state_class"] = "total_increasing" if device_class in TOTALS else "measurement"
    return "sensor", config
