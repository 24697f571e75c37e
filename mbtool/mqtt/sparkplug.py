"""Sparkplug B (``payload = "sparkplug_b"``): the plant as one Sparkplug edge node.

The group is the ``group`` setting (default: ``[poll] site``, or a ``site`` tag every device shares, else the
inventory's name), the edge node the inventory's name (``edge_node``), and each inventory
device a Sparkplug device.  Topics are ``spBv1.0/<group>/<type>/<edge node>[/<device>]``:

- ``NDEATH`` is the MQTT will, with the connection's ``bdSeq``;
- ``NBIRTH`` on each connection: the same ``bdSeq`` and the ``Node Control/Rebirth`` metric;
- ``DBIRTH`` for a device with its first good poll, and again each time it comes back
  online: every point as a metric with its name, its alias and its datatype (from the map's
  type), and its value;
- ``DDATA``: the points that changed (on_change, deadband, heartbeat as for JSON), by alias;
- ``DDEATH`` when mbtool judges a device offline;
- every message but NDEATH carries ``seq``, 0 to 255 and round again, NBIRTH's 0.

With ``primary_host``, the node subscribes to ``spBv1.0/STATE/<primary_host>`` and is born
only while that host says it is online; when it says offline, the node publishes its NDEATH,
leaves the broker and connects again, to be born anew (with the next bdSeq) once the host is
back.  ``NCMD`` with ``Node Control/Rebirth`` true makes the node born again (NBIRTH, then every
online device's DBIRTH); ``DCMD`` metrics (by name or alias) are writes, checked and written by
the same path as a ``/set`` publish (``writes.py``).

The payload is the published Sparkplug B schema's ``Payload`` (Eclipse Tahu's
``sparkplug_b.proto``, Sparkplug 3.0), built here with protobuf's descriptor API from the
fields mbtool writes and reads -- their numbers and types as the schema gives them -- so no
generated module is vendored; a field this subset does not name is kept as an unknown field.
"""

from __future__ import annotations

import json

from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

NAMESPACE = "spBv1.0"
REBIRTH = "Node Control/Rebirth"
BDSEQ = "bdSeq"

# The schema's data types (its comment "Indexes of Data Types").
INT16, INT32, INT64 = 2, 3, 4
UINT16, UINT32, UINT64 = 6, 7, 8
FLOAT, DOUBLE, BOOLEAN, STRING = 9, 10, 11, 12
BY_TYPE = {
    "int16": INT16,
    "uint16": UINT16,
    "int32": INT32,
    "uint32": UINT32,
    "int64": INT64,
    "uint64": UINT64,
    "float32": FLOAT,
    "float64": DOUBLE,
}


def _payload_class():
    """``Payload`` and its ``Metric``, as the schema numbers their fields (proto2)."""
    fields = descriptor_pb2.FieldDescriptorProto
    file = descriptor_pb2.FileDescriptorProto(
        name="mbtool/sparkplug_b.proto", package="org.eclipse.tahu.protobuf", syntax="proto2"
    )
    payload = file.message_type.add(name="Payload")
    metric = payload.nested_type.add(name="Metric")
    metric.oneof_decl.add(name="value")
    metric_fields = [
        ("name", 1, fields.TYPE_STRING),
        ("alias", 2, fields.TYPE_UINT64),
        ("timestamp", 3, fields.TYPE_UINT64),
        ("datatype", 4, fields.TYPE_UINT32),
        ("is_null", 7, fields.TYPE_BOOL),
        ("int_value", 10, fields.TYPE_UINT32),
        ("long_value", 11, fields.TYPE_UINT64),
        ("float_value", 12, fields.TYPE_FLOAT),
        ("double_value", 13, fields.TYPE_DOUBLE),
        ("boolean_value", 14, fields.TYPE_BOOL),
        ("string_value", 15, fields.TYPE_STRING),
    ]
    for name, number, kind in metric_fields:
        field = metric.field.add(name=name, number=number, type=kind, label=fields.LABEL_OPTIONAL)
        if number >= 10:
            field.oneof_index = 0
    payload.field.add(name="timestamp", number=1, type=fields.TYPE_UINT64, label=fields.LABEL_OPTIONAL)
    payload.field.add(
        name="metrics",
        number=2,
        type=fields.TYPE_MESSAGE,
        label=fields.LABEL_REPEATED,
        type_name=".org.eclipse.tahu.protobuf.Payload.Metric",
    )
    payload.field.add(name="seq", number=3, type=fields.TYPE_UINT64, label=fields.LABEL_OPTIONAL)
    pool = descriptor_pool.DescriptorPool()  # its own: no clash with another copy of the schema
    pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName("org.eclipse.tahu.protobuf.Payload"))


Payload = _payload_class()


def datatype(point) -> int:
    """A point's Sparkplug datatype: a bit Boolean, an enum's label or text String, a scaled
    number Double, else its type's own."""
    if point.is_bit:
        return BOOLEAN
    if point.enum is not None or point.type not in BY_TYPE:
        return STRING
    if point.scale is not None or point.offset is not None or point.scale_ref is not None:
        return DOUBLE
    return BY_TYPE[point.type]


def _set(metric, kind: int, value) -> None:
    """``value`` in the metric's field for ``kind``; None (no data) is ``is_null``."""
    metric.datatype = kind
    if value is None:
        metric.is_null = True
    elif kind == BOOLEAN:
        metric.boolean_value = bool(value)
    elif kind == STRING:
        metric.string_value = str(value)
    elif kind == FLOAT:
        metric.float_value = float(value)
    elif kind == DOUBLE:
        metric.double_value = float(value)
    elif kind in (INT64, UINT64):  # a negative one as two's complement, as the schema says
        metric.long_value = int(value) & 0xFFFF_FFFF_FFFF_FFFF
    else:
        metric.int_value = int(value) & 0xFFFF_FFFF


def _value(metric):
    """The value a command's metric carries (None: none)."""
    which = metric.WhichOneof("value")
    return None if which is None else getattr(metric, which)


class EdgeNode:
    """The plant as a Sparkplug edge node: its topics, its sequence numbers and its payloads.
    Used by the publisher's thread alone, but ``connected``, called by paho's."""

    def __init__(self, settings, devices: list) -> None:
        self.group, self.node = settings.group, settings.edge_node
        self.devices = {device.name: device for device in devices}
        self.state_topic = f"{NAMESPACE}/STATE/{settings.primary_host}" if settings.primary_host else None
        self.bdseq = 0  # the will's: the connection's NBIRTH says the same
        self.seq = 0
        # Every point of the node an alias of its own, kept for the run.
        self.alias: dict[tuple[str, str], int] = {}
        for device in devices:
            for point in device.reader.points:
                self.alias[device.name, point.name] = len(self.alias) + 1
        self.by_alias = {alias: key for key, alias in self.alias.items()}

    def topic(self, kind: str, device: str | None = None) -> str:
        tail = f"/{device}" if device is not None else ""
        return f"{NAMESPACE}/{self.group}/{kind}/{self.node}{tail}"

    def commands(self, writes: bool) -> list[str]:
        """The topics a node subscribes to: its NCMD, with writes every device's DCMD, and
        the primary host's STATE where there is one."""
        topics = [self.topic("NCMD")] + ([self.topic("DCMD", "+")] if writes else [])
        return topics + ([self.state_topic] if self.state_topic else [])

    def will(self) -> bytes:
        """The next connection's will: NDEATH with the bdSeq its NBIRTH will say."""
        return self.node_death(self.bdseq)

    def node_death(self, bdseq: int) -> bytes:
        """NDEATH: no seq, the bdSeq of the connection it ends."""
        payload = Payload()
        _set(payload.metrics.add(name=BDSEQ), UINT64, bdseq)
        return payload.SerializeToString()

    def node_birth(self, bdseq: int, now: float) -> bytes:
        """NBIRTH: seq starts again at 0."""
        self.seq = 0
        payload = self._payload(now)
        _set(payload.metrics.add(name=BDSEQ), UINT64, bdseq)
        _set(payload.metrics.add(name=REBIRTH), BOOLEAN, False)
        return payload.SerializeToString()

    def device_birth(self, name: str, values: dict, now: float) -> bytes:
        """DBIRTH: every point of the device, named, aliased and typed, with its value."""
        payload = self._payload(now)
        for point in self.devices[name].reader.points:
            metric = payload.metrics.add(name=point.name, alias=self.alias[name, point.name])
            metric.timestamp = payload.timestamp
            _set(metric, datatype(point), values.get(point.name))
        return payload.SerializeToString()

    def device_data(self, name: str, values: dict, now: float) -> bytes:
        """DDATA: the points given, by alias."""
        points = {point.name: point for point in self.devices[name].reader.points}
        payload = self._payload(now)
        for point, value in values.items():
            metric = payload.metrics.add(alias=self.alias[name, point])
            metric.timestamp = payload.timestamp
            _set(metric, datatype(points[point]), value)
        return payload.SerializeToString()

    def device_death(self, now: float) -> bytes:
        return self._payload(now).SerializeToString()

    def _payload(self, now: float):
        payload = Payload(timestamp=int(now * 1000), seq=self.seq)
        self.seq = (self.seq + 1) % 256
        return payload

    @staticmethod
    def host_online(data: bytes) -> bool:
        """Whether a primary host's STATE says it is online: Sparkplug 3.0's JSON
        (``{"online": true, "timestamp": ...}``), or 2.2's ``ONLINE``."""
        text = data.decode("utf-8", "replace").strip()
        try:
            state = json.loads(text)
        except ValueError:
            return text == "ONLINE"
        return isinstance(state, dict) and state.get("online") is True

    def rebirth_asked(self, data: bytes) -> bool:
        """Whether an NCMD asks for a rebirth (``Node Control/Rebirth`` true)."""
        try:
            payload = Payload.FromString(data)
        except Exception:  # noqa: BLE001 - protobuf's DecodeError: any payload a peer sends
            return False
        return any(m.name == REBIRTH and _value(m) is True for m in payload.metrics)

    def writes(self, device: str, data: bytes) -> list[tuple[str, str]] | str:
        """A DCMD's writes: (point, the value as a /set's text) each; or why it is none."""
        try:
            payload = Payload.FromString(data)
        except Exception as error:  # noqa: BLE001 - protobuf's DecodeError: any payload a peer sends
            return f"not a Sparkplug B payload ({error})"
        writes = []
        for metric in payload.metrics:
            owner, name = self.by_alias.get(metric.alias, (device, f"alias {metric.alias}"))
            name = metric.name or (name if owner == device else f"alias {metric.alias}")
            value = _value(metric)
            if isinstance(value, bool):
                text = "on" if value else "off"
            elif isinstance(value, float):
                text = repr(value)
            else:
                text = "" if value is None else str(value)
            writes.append((name, text))
        return writes
