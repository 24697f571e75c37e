"""The ``[mqtt]`` table of a plant inventory, and ``--mqtt URL``: checked whole before
anything is opened, every problem one UsageError (exit 2) naming the file and the key.

::

    [mqtt]
    url = "mqtts://broker.example:8883"   # mqtt://host[:1883] or mqtts://host[:8883]
    ca = "broker-ca.pem"                  # mqtts: as tls:// takes them (cert, key, insecure)
    username = "plant"
    password_file = "mqtt.secret"         # or password, or MBTOOL_MQTT_PASSWORD
    topic = "mbtool/{site}/{device}"      # {device}, {inventory}, {link}, {unit}, {site}, {instance}, a tag
    points = "device"                     # one message a device poll; "point": a topic a point
    qos = 1
    retain = false
    on_change = true                      # a point only when it changed...
    deadband = "1%"                       # ...by more than this (absolute, or % of its last)
    deadbands = { flow = 0.5 }            # a point's own
    heartbeat = 300                       # everything at least every 300 s
    discovery = "homeassistant"
    spool = "mqtt.spool"                  # QoS 1 messages kept on disk while the broker is away
    spool_size = 10000                    # the oldest dropped past this many (and counted)
"""

from __future__ import annotations

import os
import re
import socket
from pathlib import Path
from typing import Any

from mbtool.codec.record import field, record, replace
from mbtool.errors import UsageError
from mbtool.files import read_whole

KEYS = {
    "url": "mqtt://HOST[:PORT] or mqtts://HOST[:PORT]",
    "client_id": "the client id the broker knows this poller by (default mbtool-INSTANCE-INVENTORY)",
    "username": "a user name",
    "password": "a password",
    "password_file": "a file whose first line is the password",
    "keepalive": "seconds between pings when nothing else is sent, 5..3600",
    "version": '"3.1.1" or "5"',
    "topic": 'a topic template, such as "mbtool/{site}/{device}"',
    "status_topic": 'the poller\'s own availability topic (default "mbtool/{inventory}/status")',
    "events_topic": 'each change of state of a device or link, as JSON (default "mbtool/{inventory}/events")',
    "points": '"device" (one JSON message a poll) or "point" (a topic a point, its bare value)',
    "qos": "0 or 1",
    "retain": "true or false",
    "on_change": "true or false",
    "deadband": 'a point\'s change that is not published: a number, or a percentage such as "1%"',
    "deadbands": "a table of point names and their own deadband",
    "heartbeat": "seconds: every point published at least this often (0: only as on_change says)",
    "payload": '"json" (the default) or "sparkplug_b" (docs/mqtt.md, Sparkplug B)',
    "group": "sparkplug_b: the Sparkplug group id (default: [poll] site, or the site tag every device has, else the inventory's name)",
    "edge_node": "sparkplug_b: the Sparkplug edge node id (default: the inventory's name)",
    "primary_host": "sparkplug_b: the primary host application's id, whose STATE the node waits for before its births",
    "discovery": '"homeassistant"',
    "discovery_prefix": 'Home Assistant\'s discovery prefix (default "homeassistant")',
    "writes": "true: a publish to <device topic>/<point>/set writes a writable point (default false)",
    "allow": "the points that may be written, by name (default: every point the map marks rw)",
    "spool": "a file that keeps QoS 1 messages while the broker is away",
    "spool_size": "messages the spool keeps at most, the oldest dropped past it",
    "ca": "mqtts: the CA's certificate (PEM) the broker's is checked against",
    "cert": "mqtts: this client's certificate (PEM)",
    "key": "mqtts: this client's private key (PEM)",
    "insecure": "mqtts: check no certificate (true or false)",
}
PATH_KEYS = ("password_file", "spool", "ca", "cert", "key")
DEFAULT_PORTS = {"mqtt": 1883, "mqtts": 8883}
# Plain JSON's keys that Sparkplug B cannot honour, and why (Sparkplug 3.0: an edge node's
# topics are the spBv1.0 namespace's; NBIRTH, DBIRTH, DDATA and DDEATH are QoS 0 and NDEATH,
# the will, QoS 1, none of them retained).  on_change, deadband, heartbeat, writes and allow
# it honours: DDATA carries what changed, DCMD writes.
NOT_SPARKPLUG = {
    "qos": "Sparkplug B fixes each message's QoS (births, data and DDEATH 0, NDEATH 1)",
    "retain": "Sparkplug B retains none of an edge node's messages",
    "spool": "Sparkplug B's data is QoS 0, never replayed: the births on reconnection carry the values then",
    "spool_size": "Sparkplug B's data is QoS 0, never replayed: the births on reconnection carry the values then",
    "topic": "Sparkplug B's topics are spBv1.0/<group>/<type>/<edge node>/<device>: set group and edge_node",
    "status_topic": "the edge node's NBIRTH and NDEATH are its status, and DBIRTH and DDEATH its devices'",
    "events_topic": "the edge node's NBIRTH and NDEATH are its status, and DBIRTH and DDEATH its devices'",
    "points": "Sparkplug B carries a device's points as the metrics of one message",
    "discovery": 'Home Assistant\'s discovery reads JSON topics: it goes with payload = "json"',
    "discovery_prefix": 'Home Assistant\'s discovery reads JSON topics: it goes with payload = "json"',
}
PLACEHOLDER = re.compile(r"\{([^{}]*)\}")


@record
class Deadband:
    """How far a point's value moves from the one last published before it is published anew."""

    amount: float = 0.0
    percent: bool = False

    def moved(self, before, now) -> bool:
        band = abs(before) * self.amount / 100 if self.percent else self.amount
        return abs(now - before) > band


@record
class MqttSettings:
    host: str
    port: int
    tls: bool
    client_id: str
    inventory: str  # the inventory's name: its file's, without .toml
    labels: dict = field(default=None, compare=False)  # [poll] site and instance: in every JSON message
    username: str | None = None
    password: str | None = None
    keepalive: int = 60
    version: str = "3.1.1"
    topic: str = "mbtool/{inventory}/{device}"
    status_topic: str = "mbtool/{inventory}/status"
    events_topic: str = "mbtool/{inventory}/events"
    per_point: bool = False
    qos: int = 1
    retain: bool = False
    on_change: bool = False
    deadband: Deadband = Deadband()
    deadbands: dict = field(default=None, compare=False)  # point name -> Deadband
    heartbeat: float = 0.0
    sparkplug: bool = False  # payload = "sparkplug_b"
    group: str = ""  # Sparkplug's group id and edge node id
    edge_node: str = ""
    primary_host: str | None = None
    discovery: str | None = None
    discovery_prefix: str = "homeassistant"
    writes: bool = False
    allow: tuple | None = None  # the points that may be written; None: every writable one
    spool: str | None = None
    spool_size: int = 10000
    ca: str | None = None
    cert: str | None = None
    key: str | None = None
    insecure: bool = False

    def deadband_of(self, point: str) -> Deadband:
        return (self.deadbands or {}).get(point, self.deadband)


def parse_url(url, where: str) -> tuple[str, int, bool]:
    """(host, port, TLS) of an mqtt:// or mqtts:// URL."""
    if not isinstance(url, str):
        raise UsageError(f"{where}: expected {KEYS['url']}")
    scheme, sep, rest = url.partition("://")
    if not sep or scheme.lower() not in DEFAULT_PORTS:
        raise UsageError(f"{where}: {url!r} is not {KEYS['url']}")
    scheme = scheme.lower()
    rest = rest.rstrip("/")
    host, port = rest, DEFAULT_PORTS[scheme]
    if rest.startswith("["):  # [::1]:1883
        host, _, tail = rest[1:].partition("]")
        if tail:
            port = _port(tail.removeprefix(":"), url, where)
    elif rest.count(":") == 1:
        host, _, text = rest.partition(":")
        port = _port(text, url, where)
    if not host or "/" in host or "@" in host:
        raise UsageError(f"{where}: {url!r} names no host (such as mqtt://broker.example:1883)")
    return host, port, scheme == "mqtts"


def _port(text: str, url: str, where: str) -> int:
    if not text.isdigit() or not 1 <= int(text) <= 65535:
        raise UsageError(f"{where}: {url!r}: the port is 1..65535")
    return int(text)


# read --interval --mqtt: the one device's topic; its availability is that topic's /status.
READ_TOPIC = "mbtool/{instance}/{device}"


@record
class Device:
    """A device of no inventory (read --interval's), as a topic template names it."""

    name: str
    link: str
    unit: int
    tags: dict = field(default=None, compare=False)


def read_settings(url: str, name: str, unit: int) -> tuple[MqttSettings, Device]:
    """read --interval --mqtt URL: one JSON message a poll on ``mbtool/<instance>/<name>``
    (the instance is the host name: a one-liner has no [poll]), and one availability topic,
    ``.../<name>/status``: online at each connection and while polls are answered, offline
    after a failed poll, at a clean end and as the will.  ``name``: --name, one topic level."""
    if not name or re.search(r"[/+#{}\0]", name) or name.startswith("$"):
        raise UsageError(
            f"--name {name!r}: the device's name on the broker is one topic level (no / + # {{ }})"
        )
    labels = {"instance": socket.gethostname()}
    device = Device(name, "read", unit)
    instance = labels["instance"]
    table = {
        "topic": READ_TOPIC,
        "status_topic": READ_TOPIC.format(instance=instance, device=name) + "/status",
        "client_id": f"mbtool-{instance}-read-{name}",
    }
    settings = mqtt_settings(table, "read", [device], url, labels)
    assert settings is not None  # a url is given
    return settings, device


def check_table(table, path: str, devices: list, labels: dict) -> None:
    """The ``[mqtt]`` table checked as the inventory is loaded, its url too where it has one
    (poll's --mqtt may give it)."""
    if table is not None:
        stand_in = None if isinstance(table, dict) and "url" in table else "mqtt://localhost"
        mqtt_settings(table, path, devices, stand_in, labels)


def mqtt_settings(
    table,
    path: str,
    devices: list,
    url: str | None = None,
    labels: dict | None = None,
    part: tuple[int, int] | None = None,
) -> MqttSettings | None:
    """The ``[mqtt]`` table of the inventory at ``path`` (None: it has none), ``url`` (poll's
    --mqtt) in place of its url; None when neither is given.  ``devices``: the inventory's
    ``DeviceSpec``s, whose names and tags the topic template must be able to fill; ``labels``:
    its [poll] site and instance; ``part``: poll --shard's (K, N).

    Shards of one inventory on one broker must not collide: each is a client of its own (a
    second session of one client id throws the first off), with a status and a Sparkplug edge
    node of its own, so the shard (``0of2``) is added to the client id, the status topic (a
    level under it) and the edge node."""
    if table is None and url is None:
        return None
    if table is None:
        table = {}
    if not isinstance(table, dict):
        raise UsageError(f"{path}: mqtt must be a table, [mqtt]")
    for key in table:
        if key not in KEYS:
            raise UsageError(f"{path}: [mqtt] {key}: unknown key (known: {', '.join(KEYS)})")
    folder = Path(path).parent
    given = {
        key: (
            str(folder / Path(value).expanduser()) if key in PATH_KEYS and isinstance(value, str) else value
        )
        for key, value in table.items()
    }
    if url is not None:
        given["url"] = url
    if "url" not in given:
        raise UsageError(f'{path}: [mqtt] has no url (such as "mqtt://localhost:1883"), nor --mqtt')
    where = f"{path}: [mqtt]"
    host, port, tls = parse_url(given["url"], "--mqtt" if url is not None else f"{where} url")
    inventory = Path(path).stem
    labels = labels or {"instance": socket.gethostname()}
    settings = MqttSettings(host, port, tls, f"mbtool-{labels['instance']}-{inventory}", inventory, labels)
    changes: dict[str, Any] = {}  # each key's value, of the type MqttSettings gives it
    for key, value in given.items():
        if key == "url":
            continue
        at = f"{where} {key}"
        if key in (
            "client_id",
            "username",
            "password",
            "topic",
            "status_topic",
            "events_topic",
            "discovery_prefix",
            "group",
            "edge_node",
            "primary_host",
        ):
            changes[key] = _text(value, at)
        elif key == "password_file":
            changes["password"] = _password_file(value, at)
        elif key == "allow":
            if not isinstance(value, list) or not all(isinstance(name, str) for name in value):
                raise UsageError(f'{at}: expected a list of point names, such as ["setpoint"]')
            changes[key] = tuple(value)
        elif key in ("retain", "on_change", "insecure", "writes"):
            if not isinstance(value, bool):
                raise UsageError(f"{at}: expected true or false")
            changes[key] = value
        elif key == "keepalive":
            changes[key] = _whole(value, 5, 3600, at)
        elif key == "qos":
            changes[key] = _whole(value, 0, 1, at)
        elif key == "spool_size":
            changes[key] = _whole(value, 1, 10_000_000, at)
        elif key == "version":
            if value not in ("3.1.1", "5", 5):
                raise UsageError(f"{at}: expected {KEYS[key]}")
            changes[key] = str(value)
        elif key == "points":
            if value not in ("device", "point"):
                raise UsageError(f"{at}: expected {KEYS[key]}")
            changes["per_point"] = value == "point"
        elif key == "heartbeat":
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value <= 86400:
                raise UsageError(f"{at}: expected seconds, 0..86400")
            changes[key] = float(value)
        elif key == "deadband":
            changes[key] = _deadband(value, at)
        elif key == "deadbands":
            if not isinstance(value, dict):
                raise UsageError(f"{at}: expected {KEYS[key]}, such as {{ flow = 0.5 }}")
            changes[key] = {name: _deadband(band, f"{at}.{name}") for name, band in value.items()}
        elif key == "payload":
            if value not in ("json", "sparkplug_b"):
                raise UsageError(f"{at}: expected {KEYS[key]}")
            changes["sparkplug"] = value == "sparkplug_b"
        elif key == "discovery":
            if value != "homeassistant":
                raise UsageError(f"{at}: expected {KEYS[key]}")
            changes[key] = value
        elif key in PATH_KEYS:
            changes[key] = _text(value, at)
    if changes.get("sparkplug"):
        for key in given:
            if key in NOT_SPARKPLUG:
                raise UsageError(f'{where} {key}: not with payload = "sparkplug_b": {NOT_SPARKPLUG[key]}')
    sites = {(device.tags or {}).get("site") for device in devices}
    changes.setdefault("group", str(sites.pop()) if len(sites) == 1 and None not in sites else inventory)
    changes.setdefault("edge_node", inventory)
    if part is not None:
        ours = f"{part[0]}of{part[1]}"
        changes["client_id"] = f"{changes.get('client_id', settings.client_id)}-{ours}"
        changes["status_topic"] = f"{changes.get('status_topic', settings.status_topic)}/{ours}"
        changes["events_topic"] = f"{changes.get('events_topic', settings.events_topic)}/{ours}"
        changes["edge_node"] = f"{changes['edge_node']}-{ours}"
    if "password" not in changes and os.environ.get("MBTOOL_MQTT_PASSWORD"):
        changes["password"] = os.environ["MBTOOL_MQTT_PASSWORD"]
    settings = replace(settings, **changes)
    _check(settings, where, devices)
    return settings


def _check(settings: MqttSettings, where: str, devices: list) -> None:
    if settings.password is not None and settings.username is None:
        raise UsageError(f"{where}: a password goes with a username")
    if not settings.tls and (settings.ca or settings.cert or settings.key or settings.insecure):
        raise UsageError(f"{where}: ca, cert, key and insecure are mqtts:// settings")
    if settings.insecure and settings.ca:
        raise UsageError(f"{where}: insecure checks no certificate: ca would have nothing to check")
    if (settings.cert is None) != (settings.key is None):
        raise UsageError(f"{where}: cert and key go together")
    for name in ("ca", "cert", "key"):
        value = getattr(settings, name)
        if value is not None and not Path(value).is_file():
            raise UsageError(f"{where} {name}: no file {value}")
    if settings.allow is not None and not settings.writes:
        raise UsageError(f"{where} allow: goes with writes = true")
    for name in settings.allow or ():
        if not any(name in _points(device) for device in devices):
            raise UsageError(f"{where} allow: no device reads a point named {name}")
    for device in devices:
        for text, key in (
            (settings.topic, "topic"),
            (settings.status_topic, "status_topic"),
            (settings.events_topic, "events_topic"),
        ):
            _topic_problem(fill(text, settings, device if key == "topic" else None), f"{where} {key}", text)
        if settings.per_point:
            for point in _points(device):
                _topic_problem(point, f'{where} points = "point": {device.name}\'s point', point)
    if settings.sparkplug:
        for key in ("group", "edge_node", "primary_host"):
            if re.search(r"[/+#]", getattr(settings, key) or ""):
                raise UsageError(f"{where} {key}: {getattr(settings, key)!r}: a Sparkplug id has no / + or #")
        for device in devices:
            if re.search(r"[/+#]", device.name):
                raise UsageError(f"{where}: device {device.name!r}: a Sparkplug device id has no / + or #")
    elif settings.primary_host is not None:
        raise UsageError(f'{where} primary_host: goes with payload = "sparkplug_b"')
    if settings.topic == settings.status_topic or "{device}" not in settings.topic:
        raise UsageError(f"{where} topic: {settings.topic!r} must name {{device}}: a topic a device")


def _points(device) -> list[str]:
    return [point.name for point in device.reader.points]


def fill(template: str, settings: MqttSettings, device=None) -> str:
    """A topic template filled in for ``device`` (None: the poller's own topics, which may
    name {inventory}, {host} and the fleet's labels, {site} and {instance})."""
    values = {"inventory": settings.inventory, "host": socket.gethostname(), **(settings.labels or {})}
    if device is not None:
        values |= {"device": device.name, "link": device.link, "unit": str(device.unit)}
        values |= device.tags or {}  # the fleet's labels among them

    def one(match: re.Match) -> str:
        name = match.group(1)
        if name not in values:
            raise UsageError(
                f"{template!r}: {{{name}}} is not known"
                + (f" for device {device.name}" if device else "")
                + f" (known: {', '.join(values)}"
                + ('; [poll] site = "..." gives {site})' if name == "site" else ")")
            )
        return values[name]

    return PLACEHOLDER.sub(one, template)


def _topic_problem(topic: str, where: str, template: str) -> None:
    """A topic a publish may name: no wildcards, no empty level at either end, no NUL."""
    if not topic or "+" in topic or "#" in topic or "\0" in topic or topic.startswith("$"):
        raise UsageError(
            f"{where}: {template!r} makes {topic!r}: not a topic to publish on (no +, #, $ first)"
        )
    if len(topic.encode()) > 65535:
        raise UsageError(f"{where}: {template!r} makes a topic longer than MQTT allows")


def _text(value, where: str) -> str:
    if not isinstance(value, str) or not value:
        raise UsageError(f"{where}: expected text, not empty")
    return value


def _whole(value, low: int, high: int, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise UsageError(f"{where}: expected a whole number, {low}..{high}")
    return value


def _deadband(value, where: str) -> Deadband:
    if isinstance(value, str) and value.strip().endswith("%"):
        try:
            amount = float(value.strip()[:-1])
        except ValueError:
            amount = -1.0
        if not 0 <= amount < 1e6:
            raise UsageError(f'{where}: {value!r} is not a percentage such as "1%"')
        return Deadband(amount, True)
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value < 1e300:
        raise UsageError(f'{where}: expected a number of 0 or more, or a percentage such as "1%"')
    return Deadband(float(value))


def _password_file(value, where: str) -> str:
    text = read_whole(Path(_text(value, where)), "password file").decode("utf-8", "replace")
    line = text.splitlines()[0] if text else ""
    if not line:
        raise UsageError(f"{where}: {value} is empty")
    return line
