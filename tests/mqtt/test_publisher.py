"""The publisher's own ways (mbtool/mqtt/publisher.py) that no broker shows: how many QoS 1
messages it lets wait for their PUBACK at once, and that its thread sleeps while there is
nothing to publish (in a process of many threads, each wake costs)."""

from __future__ import annotations

import queue
import time

from mbtool.mqtt.publisher import INFLIGHT_MQTT5, STOP, MqttPublisher
from mbtool.mqtt.settings import Device, mqtt_settings


def _publisher(table: dict) -> MqttPublisher:
    devices = [Device("m1", "bus", 1)]
    settings = mqtt_settings(table, "plant.toml", devices, "mqtt://127.0.0.1:1", {})
    return MqttPublisher(settings, devices)


def test_mqtt_3_1_1_holds_no_message_back_for_the_acknowledgements_of_others():
    assert _publisher({}).client.max_inflight_messages == 0


def test_mqtt_5_keeps_a_bound():
    assert _publisher({"version": "5"}).client.max_inflight_messages == INFLIGHT_MQTT5


class CountedQueue(queue.SimpleQueue):
    """The publisher's queue, its waits counted."""

    def __init__(self) -> None:
        self.waits = 0

    def get(self, block=True, timeout=None):
        self.waits += 1
        return super().get(block, timeout)


def test_an_idle_publisher_s_thread_sleeps_until_there_is_work():
    publisher = _publisher({})
    publisher.queue = counted = CountedQueue()
    publisher.thread.start()  # its thread alone: no broker, nothing reported
    time.sleep(0.6)
    publisher.queue.put(STOP)
    publisher.thread.join(5)
    assert not publisher.thread.is_alive()
    assert counted.waits <= 2, f"woke {counted.waits} times in 0.6 s with nothing to do"
