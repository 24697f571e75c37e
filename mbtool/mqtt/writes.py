"""Writes from the broker: a publish to ``<device topic>/<point>/set`` writes that point of
that device, through the device's own link, between its polls.

Nothing reaches a bus that is not valid: writes are off unless ``writes = true``; the point
must be one the device reads, marked writable by its map (``access = "rw"``), and on the
allow-list where there is one; the value must be one the point's type holds once scaled
(``Point.raw_for``: a number, a label, on/off).  A write refused for any of those is
answered on ``<point>/result`` (``refused: ...``) and never sent.  One that is valid is
handed to the link's worker (``LinkWorker.submit``), which runs it before its next poll,
so the port is never opened twice and no two requests are ever on the bus at once; the
point is then read back, and ``<point>/result`` says ``written``, ``differs: read ...``,
``refused: exception 02 ...`` (the device's answer) or ``not written: ...`` (no answer, the
link not open).
"""

from __future__ import annotations

from collections.abc import Callable

from mbtool.codec.errors import ModbusException
from mbtool.codec.record import record
from mbtool.errors import KNOWN_ERRORS, UsageError
from mbtool.mqtt.settings import MqttSettings
from mbtool.mqtt.topics import Topics, point_payload
from mbtool.registermap.plan import MapReader, write_request
from mbtool.registermap.point import Point


@record
class SetRequest:
    """A publish on a ``/set`` topic, as the broker delivered it."""

    device: str
    point: str
    text: str


@record
class WriteResult:
    device: str
    point: str
    result: str  # written, differs: ..., refused: ..., not written: ...


class Writes:
    def __init__(self, settings: MqttSettings, topics: Topics, devices: list) -> None:
        self.settings = settings
        self.topics = topics
        self.devices = {device.name: device for device in devices}
        self.by_topic = {topics.device[device.name]: device.name for device in devices}

    def subscriptions(self) -> list[str]:
        return [f"{topic}/+/set" for topic in self.by_topic]

    def request(self, topic: str, payload: bytes) -> SetRequest | None:
        """The request a ``/set`` publish makes; None for a topic of no device's."""
        prefix, _, point = topic.removesuffix("/set").rpartition("/")
        device = self.by_topic.get(prefix)
        if device is None:
            return None
        return SetRequest(device, point, payload.decode("utf-8", "replace").strip())

    def check(self, request: SetRequest):
        """The point and the Modbus request that write it; UsageError saying why not (the user's
        mistake), or the codec's RequestError (a request the spec forbids)."""
        device = self.devices[request.device]
        points = {point.name: point for point in device.reader.points}
        point = points.get(request.point)
        if point is None:
            raise UsageError(f"{device.name} reads no point {request.point}")
        allowed = self.settings.allow
        if allowed is not None and point.name not in allowed:
            raise UsageError(f"{point.name} is not on the allow-list ({', '.join(allowed) or 'empty'})")
        if not request.text:
            raise UsageError(f"{point.name}: no value")
        return point, write_request(point, request.text)

    def job(self, request: SetRequest, point: Point, write, done: Callable[[WriteResult], None]):
        """What the link's thread runs (``LinkWorker.submit``): the write, then the point read
        back, each through ``execute(request)``, a transaction with the device on its link."""
        device = self.devices[request.device]

        def run(execute) -> None:
            if execute is None:
                done(WriteResult(device.name, point.name, f"not written: link {device.link} is not open"))
                return
            try:
                execute(write)
            except ModbusException as error:
                done(WriteResult(device.name, point.name, f"refused: {error}"))
                return
            except (*KNOWN_ERRORS, OSError) as error:
                done(WriteResult(device.name, point.name, f"not written: {error}"))
                return
            try:
                value = MapReader([point]).read(execute)[0].value
            except (*KNOWN_ERRORS, OSError) as error:
                done(WriteResult(device.name, point.name, f"written; not read back: {error}"))
                return
            if value == _holds(point, point.raw_for(request.text)):
                result = "written"
            else:
                result = f"differs: read {point_payload(value).decode()}"
            done(WriteResult(device.name, point.name, result))

        return run


def _holds(point: Point, raw):
    """The value a point reads once ``raw`` (``raw_for``'s) is written: scaled, labelled,
    a float32's nearest."""
    if point.is_bit:
        return bool(raw)
    return point.value_of(point.registers_of(raw))
