"""The MQTT client of a plant: what the links' workers report, published on a thread of its
own, so that a slow or absent broker never holds a poll up.

``report`` only enqueues (a full queue drops the record, counted).  The publisher's thread
turns each record into messages: the device's status when mbtool's judgement of it changes,
and its points (all, or those ``change.ChangeFilter`` picks).  While the broker is connected
they go to paho-mqtt, which sends them from its own network thread; while it is away a QoS 1
message goes to the spool (``spool.py``) and a QoS 0 one is dropped, counted.  On each
(re)connection the publisher says it is online (the birth, beside the last will that says
offline for it), publishes each device's status and Home Assistant's discovery configs
again (all retained), then the spooled messages in the order they were kept, before
anything newer; paho reconnects with a back-off of 1 s doubling to 30 s.
"""

from __future__ import annotations

import queue
import ssl
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion, MQTTErrorCode

from mbtool.codec.errors import RequestError
from mbtool.errors import UsageError
from mbtool.mqtt.change import ChangeFilter
from mbtool.mqtt.discovery import configs
from mbtool.mqtt.settings import MqttSettings
from mbtool.mqtt.spool import Message, Spool
from mbtool.mqtt.topics import (
    OFFLINE,
    ONLINE,
    DevicePoll,
    PlantEvent,
    Topics,
    device_payload,
    event_payload,
    point_payload,
)
from mbtool.mqtt.writes import SetRequest, WriteResult, Writes

if TYPE_CHECKING:
    from mbtool.mqtt.sparkplug import EdgeNode  # protobuf: imported when sparkplug_b is asked

QUEUED = 10_000  # records waiting for the publisher's thread at most
STOP = object()
WAKE = object()  # queued when a connection is owed its announcement (or its end): see _owe
IDLE = 1.0  # seconds the publisher's thread waits for a record at most (it is woken for any)
INFLIGHT_MQTT5 = 100  # QoS 1 messages unacknowledged at once, on an MQTT 5 connection
RECONNECT = (1, 30)  # paho's back-off: from 1 s, doubling, to 30 s
GATHER = 0.05  # seconds the publisher's thread waits for more once a record comes


class MqttPublisher:
    def __init__(
        self,
        settings: MqttSettings,
        devices: list,
        headers: dict | None = None,
        notify: Callable[[str], None] = lambda line: None,
        submit: Callable[[str, Callable], None] | None = None,
    ) -> None:
        """``headers``: each device's map header, for discovery; ``notify``: a line for each
        change of the broker's state (connected, lost, refused) and each write; ``submit``:
        hands a write to the worker of a device's link (``writes = true``)."""
        self.settings = settings
        self.devices = devices
        self.headers = headers or {}
        self.notify = notify
        self.topics = Topics(settings, devices)
        self.units = {device.name: device.unit for device in devices}
        self.floating: dict[str, list[str]] = {}  # a device's float points, by name
        self.changes = ChangeFilter(settings)
        self.spool = Spool(settings.spool_size, settings.spool)
        # C's queue: put and get take no Condition a record, as queue.Queue's do; its bound is
        # report's own.
        self.queue: queue.SimpleQueue = queue.SimpleQueue()
        self.lock = threading.Lock()
        # Once a message each, so written without the lock, each by one thread alone: handed to
        # paho by the publisher's; published, sent (QoS 0) or acknowledged (QoS 1), by paho's.
        self.handed = self.published = 0
        self.counts = {"dropped": 0}  # lost; and the writes' counts (under the lock)
        self.writes = Writes(settings, self.topics, devices) if settings.writes else None
        self.submit = submit
        if self.writes is not None:
            self.counts |= {
                "writes_received": 0,
                "writes_refused": 0,
                "writes_written": 0,
                "writes_failed": 0,
            }
        self.state = "connecting"
        self.live = False  # connected, and what the connection owes sent: new messages go to paho
        self.announce = threading.Event()  # a connection came up: birth, statuses, the spool
        self.device_states: dict[str, str] = {}  # what the broker has been told of each device
        # payload = "sparkplug_b": the edge node, each device's last values (its DBIRTH's), the
        # devices born on this connection, and the bdSeq of the connection's will.
        self.node: EdgeNode | None = None
        if settings.sparkplug:
            from mbtool.mqtt.sparkplug import EdgeNode  # noqa: PLC0415 - protobuf: sparkplug_b only

            self.node = EdgeNode(settings, devices)
        self.values: dict[str, dict] = {}
        self.born: set[str] = set()
        self.bdseq = 0
        self.rehome = threading.Event()  # the primary host went offline: NDEATH, connect again
        self.host_online = False  # the primary host's STATE on this connection
        self.client = self._client()
        self.thread = threading.Thread(target=self._run, name="mqtt", daemon=True)

    # --- the plant's side ---------------------------------------------------------------

    def report(self, item) -> None:
        """A plant's ``Poll`` or ``PlantEvent`` (as the thread that runs the plant hands them
        on), read --interval's ``DevicePoll``, or a write's request or result, queued for the
        publisher's thread; never waits."""
        if self.queue.qsize() < QUEUED:
            self.queue.put(item)
        else:
            self._count("dropped")

    def start(self) -> None:
        settings = self.settings
        self.client.connect_async(settings.host, settings.port, settings.keepalive)
        self.client.loop_start()
        self.thread.start()

    def close(self, wait: float = 5.0) -> None:
        """The records queued so far published, the poller's status set offline, the
        connection closed: within ``wait`` seconds."""
        deadline = time.monotonic() + wait
        self.queue.put(STOP)
        self.thread.join(max(0.0, deadline - time.monotonic()))
        if self.live and self.node is not None:  # a node that leaves says so, as its will would
            self._publish(Message(self.node.topic("NDEATH"), self.node.node_death(self.bdseq), 1, False))
        elif self.live:
            self._publish(Message(self.topics.status, OFFLINE.encode(), 1, True))
            while self._unsent() and self.live and time.monotonic() < deadline:
                time.sleep(0.01)
        self.client.disconnect()
        self.client.loop_stop()

    def _unsent(self) -> int:
        return self.handed - self.published

    def stats(self) -> dict:
        with self.lock:
            return {
                "broker": f"{self.settings.host}:{self.settings.port}",
                "state": self.state,
                "published": self.published,
                **self.counts,
                "spooled": self.spool.kept,  # while the broker was away
                "spool_sent": self.spool.sent,  # sent once the broker was back
                "in_spool": len(self.spool),  # still to send
                "spool_dropped": self.spool.dropped,
            }

    # --- the client ---------------------------------------------------------------------

    def _client(self) -> paho.Client:
        settings = self.settings
        version = paho.MQTTv5 if settings.version == "5" else paho.MQTTv311
        client = paho.Client(CallbackAPIVersion.VERSION2, client_id=settings.client_id, protocol=version)
        if settings.username is not None:
            client.username_pw_set(settings.username, settings.password)
        if settings.tls:
            client.tls_set(
                ca_certs=settings.ca,
                certfile=settings.cert,
                keyfile=settings.key,
                cert_reqs=ssl.CERT_NONE if settings.insecure else ssl.CERT_REQUIRED,
            )
            client.tls_insecure_set(settings.insecure)
        if self.node is not None:
            client.will_set(self.node.topic("NDEATH"), self.node.will(), qos=1, retain=False)
        else:
            client.will_set(self.topics.status, OFFLINE, qos=1, retain=True)
        client.reconnect_delay_set(*RECONNECT)
        # QoS 1 messages waiting for their PUBACK at once: MQTT 3.1.1 sets no bound, nor does
        # mbtool (and unbounded, paho looks for held-back messages at no PUBACK); an MQTT 5
        # broker says its own in its CONNACK (Receive Maximum, 3.2.2.3.3), too late for paho,
        # whose bound is fixed before it connects.
        client.max_inflight_messages_set(INFLIGHT_MQTT5 if version == paho.MQTTv5 else 0)
        client.on_connect = self._connected
        client.on_connect_fail = lambda client, userdata: self._state("unreachable (trying again)")
        client.on_disconnect = self._disconnected
        client.on_publish = self._published
        client.on_message = self._message
        return client

    def _connected(self, client, userdata, flags, reason, properties) -> None:
        if reason.is_failure:
            self._state(f"refused: {reason}")
            return
        self._state("connected")
        topics = self.writes.subscriptions() if self.writes else []
        if self.node is not None:
            # This connection's NBIRTH says the bdSeq its will said; the next one's is one more.
            self.bdseq, self.node.bdseq = self.node.bdseq, (self.node.bdseq + 1) % 256
            client.will_set(self.node.topic("NDEATH"), self.node.will(), qos=1, retain=False)
            topics = self.node.commands(self.writes is not None)
        for topic in topics:
            client.subscribe(topic, qos=1)
        self.host_online = False
        if self.node is None or self.node.state_topic is None:
            self._owe(self.announce)  # else once the primary host's STATE says it is online

    def _disconnected(self, client, userdata, flags, reason, properties) -> None:
        self.live = False
        if self.state == "connected":
            self._state(f"lost: {reason}" if reason.is_failure else "disconnected")

    def _message(self, client, userdata, message) -> None:
        if self.node is not None:
            self._command(message)
            return
        request = self.writes.request(message.topic, message.payload) if self.writes else None
        if request is None:
            return
        self._count("writes_received")
        if message.retain:  # a value left on the broker is no command: it would be written at each connection
            self.report(WriteResult(request.device, request.point, "refused: a retained /set is not obeyed"))
            return
        self.report(request)

    def _command(self, message) -> None:
        """An NCMD (a rebirth asked: the node born again) or a DCMD (writes, by /set's path)."""
        node = self.node
        assert node is not None  # payload = "sparkplug_b", the only one with a node
        if message.topic == node.state_topic:
            self.host_online = node.host_online(message.payload)
            if self.host_online and not self.live:
                self._owe(self.announce)
            elif self.live:  # born while the host was online: it is gone, so is this node
                self._owe(self.rehome)
            return
        if message.topic == node.topic("NCMD"):
            if node.rebirth_asked(message.payload) and (node.state_topic is None or self.host_online):
                self.notify("rebirth asked (NCMD)")
                self._owe(self.announce)
            return
        device = message.topic.rpartition("/")[2]
        if message.topic != node.topic("DCMD", device) or device not in node.devices or self.writes is None:
            return
        writes = node.writes(device, message.payload)
        if isinstance(writes, str):
            self._count("writes_received")
            self.report(WriteResult(device, "DCMD", f"refused: {writes}"))
            return
        for point, text in writes:
            self._count("writes_received")
            self.report(SetRequest(device, point, text))

    def _owe(self, duty: threading.Event) -> None:
        """A duty for the publisher's thread (paho's callbacks run on paho's thread), which is
        woken for it: it waits on its queue, so that it wakes only when there is work, not
        to look for some (each wake of a thread costs, in a process of many)."""
        duty.set()
        self.queue.put(WAKE)

    def _published(self, client, userdata, mid, reason, properties) -> None:
        self.published += 1  # by paho's thread alone

    def _state(self, state: str) -> None:
        with self.lock:
            changed, self.state = self.state != state, state
        if changed:
            self.notify(f"broker {self.settings.host}:{self.settings.port} {state}")

    def _count(self, key: str, more: int = 1) -> None:
        with self.lock:
            self.counts[key] += more

    # --- the publisher's thread ---------------------------------------------------------

    def _run(self) -> None:
        gathered: deque = deque()  # records taken from the queue, to handle in order
        while True:
            # Between any two records: a connection's announcement comes before anything newer.
            if self.rehome.is_set():
                self.rehome.clear()
                self._rehome()
            if self.announce.is_set():
                self.announce.clear()
                self._announce()
            if not gathered:
                try:
                    gathered.append(self.queue.get(timeout=IDLE))
                except queue.Empty:
                    continue
                # The polls of a round come together: gathered for a moment, they are published
                # in one wake of this thread and of paho's, not a wake of each a poll.
                time.sleep(GATHER)
                while not self.queue.empty():
                    gathered.append(self.queue.get_nowait())
            item = gathered.popleft()
            if item is STOP:
                return
            if item is not WAKE:  # a wake's duty is done at the loop's top
                self._handle(item)

    def _handle(self, item) -> None:
        """A Poll (or DevicePoll) published, or a write's request or result handled."""
        if isinstance(item, SetRequest):
            self._write(item)
        elif isinstance(item, WriteResult):
            self._result(item)
        elif isinstance(item, PlantEvent):
            # A log, for a flow that alerts: not retained (each device's status is), QoS 1.
            if self.node is None:  # Sparkplug says it with DDEATH and DBIRTH
                self._send(Message(self.topics.events, event_payload(item.record), 1, False))
        else:
            for message in self._messages(item):
                self._send(message)

    def _announce(self) -> None:
        """What a new connection owes: the birth, every device's status, the discovery
        configs, then what was spooled while the broker was away, in order."""
        if self.node is not None:
            self._births()
            return
        owed = [Message(self.topics.status, ONLINE.encode(), 1, True)]
        owed += [
            Message(self.topics.device_status(name), state.encode(), 1, True)
            for name, state in self.device_states.items()
        ]
        if self.settings.discovery == "homeassistant":
            owed += [
                Message(topic, payload, 1, True)
                for topic, payload in configs(self.settings, self.topics, self.devices, self.headers)
            ]
        owed += self.spool.take()
        for message in owed:
            self._publish(message)
        self.live = True

    def _births(self) -> None:
        """Sparkplug's births, on a connection or a rebirth: NBIRTH, then each online
        device's DBIRTH with its last values.  Nothing was spooled: Sparkplug's data is QoS 0,
        and the births carry the values as they are now."""
        node, now = self.node, time.time()
        assert node is not None  # payload = "sparkplug_b", the only one with a node
        self.born = set()
        self._publish(Message(node.topic("NBIRTH"), node.node_birth(self.bdseq, now), 0, False))
        for name, state in self.device_states.items():
            if state == ONLINE and name in self.values:
                self.born.add(name)
                self._publish(
                    Message(
                        node.topic("DBIRTH", name), node.device_birth(name, self.values[name], now), 0, False
                    )
                )
        self.live = True

    def _rehome(self) -> None:
        """The primary host went offline (Sparkplug B): the node's NDEATH, then it leaves the
        broker and connects again, to wait for the host's STATE before it is born again."""
        self.live = False
        self.notify(f"primary host {self.settings.primary_host} offline: NDEATH, connecting again")
        node = self.node
        assert node is not None  # payload = "sparkplug_b", the only one with a node
        self._publish(Message(node.topic("NDEATH"), node.node_death(self.bdseq), 1, False))
        deadline = time.monotonic() + 2.0
        while self._unsent() and time.monotonic() < deadline:
            time.sleep(0.01)
        self.client.disconnect()
        self.client.loop_stop()
        self.client.connect_async(self.settings.host, self.settings.port, self.settings.keepalive)
        self.client.loop_start()

    def _write(self, request: SetRequest) -> None:
        """A write from the broker: refused here, or handed to its device's link."""
        writes, submit = self.writes, self.submit
        assert writes is not None and submit is not None  # made for [mqtt] writes, which is how a /set came
        try:
            point, write = writes.check(request)
        except (UsageError, RequestError) as error:  # the user's mistake, or the spec's refusal
            self._result(WriteResult(request.device, request.point, f"refused: {error}"))
            return
        submit(request.device, writes.job(request, point, write, self.report))

    def _result(self, result: WriteResult) -> None:
        outcome = result.result.partition(":")[0].partition(";")[0]
        self._count({"written": "writes_written", "refused": "writes_refused"}.get(outcome, "writes_failed"))
        self.notify(f"write {result.device} {result.point}: {result.result}")
        if self.node is not None:  # Sparkplug has no result topic: the value read back is in DDATA
            return
        topic = f"{self.topics.point(result.device, result.point)}/result"
        self._send(Message(topic, result.result.encode(), 1, False))

    def _messages(self, item) -> list[Message]:
        """A Poll's (or a DevicePoll's) messages: its device's status when it changed, and its points."""
        if self.node is not None:
            return self._sparkplug(item)
        settings = self.settings
        if isinstance(item, DevicePoll):
            name, values = item.device, item.values
        else:
            name = item.device.name
            values = self._values(item) if item.readings else None
        messages = []
        if item.state in (ONLINE, OFFLINE) and self.device_states.get(name) != item.state:
            self.device_states[name] = item.state
            if self.live:  # else the next connection's announcement says it
                messages.append(Message(self.topics.device_status(name), item.state.encode(), 1, True))
        if values:
            chosen = self.changes.select(name, item.time, values, item.group)
            if chosen and settings.per_point:
                messages += [
                    Message(
                        self.topics.point(name, point), point_payload(value), settings.qos, settings.retain
                    )
                    for point, value in chosen.items()
                ]
            elif chosen:
                payload = device_payload(item.time, settings.labels, self.units[name], chosen)
                messages.append(Message(self.topics.device[name], payload, settings.qos, settings.retain))
        return messages

    def _sparkplug(self, item) -> list[Message]:
        """A Poll's Sparkplug messages: DDEATH when its device went offline, DBIRTH when it is
        first read on this connection (again after a death), else DDATA of what changed."""
        node, name = self.node, item.device.name
        assert node is not None  # payload = "sparkplug_b", the only one with a node
        values = self._values(item) if item.readings else {}
        chosen = self.changes.select(name, item.time, values, item.group) if values else {}
        self.values.setdefault(name, {}).update(values)
        if item.state in (ONLINE, OFFLINE):
            self.device_states[name] = item.state
        if not self.live:
            return []  # the next connection's births say it all
        if item.state == OFFLINE:
            if name not in self.born:
                return []
            self.born.discard(name)
            return [Message(node.topic("DDEATH", name), node.device_death(item.time), 0, False)]
        if name not in self.born:
            if item.state != ONLINE:
                return []
            self.born.add(name)
            return [
                Message(
                    node.topic("DBIRTH", name),
                    node.device_birth(name, self.values[name], item.time),
                    0,
                    False,
                )
            ]
        if not chosen:
            return []
        return [Message(node.topic("DDATA", name), node.device_data(name, chosen, item.time), 0, False)]

    def _values(self, poll) -> dict:
        """A Poll's values by point name, those it read, a float point's whole number as a float
        (22.0, not 22): a consumer that fixes a field's type at its first value (InfluxDB,
        Telegraf) takes every later one."""
        values = {r.point.name: r.value for r in poll.readings if r.error is None}
        floating = self.floating.get(poll.device.name)
        if floating is None:  # the device's float points, found at its first poll
            floating = self.floating[poll.device.name] = [
                p.name for p in poll.device.reader.points if p.floating
            ]
        for point in floating:
            value = values.get(point)
            if isinstance(value, int) and not isinstance(value, bool):
                values[point] = float(value)
        return values

    def _send(self, message: Message) -> None:
        if self.live:
            self._publish(message)
        elif message.qos:
            self.spool.add(message)
        else:
            self._count("dropped")  # QoS 0: at most once, and the broker is away

    def _publish(self, message: Message) -> None:
        # Not under self.lock: paho calls on_publish holding its own lock, which publish takes.
        info = self.client.publish(message.topic, message.payload, message.qos, message.retain)
        # NO_CONN for QoS 1: paho keeps the message and sends it on reconnection.
        if info.rc == MQTTErrorCode.MQTT_ERR_SUCCESS or (
            info.rc == MQTTErrorCode.MQTT_ERR_NO_CONN and message.qos
        ):
            self.handed += 1  # by the publisher's thread alone (close's comes after it ended)
        else:
            self._count("dropped")
