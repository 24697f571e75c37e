"""How many QoS 1 messages the publisher lets wait for their PUBACK at once
(mbtool/mqtt/publisher.py): no bound on MQTT 3.1.1, which sets none (a round of a plant's
polls is never held back for the broker's acknowledgements); a bound on MQTT 5, whose
brokers keep one."""

from __future__ import annotations

from mbtool.mqtt.publisher import INFLIGHT_MQTT5, MqttPublisher
from mbtool.mqtt.settings import Device, mqtt_settings


def _client(table: dict):
    devices = [Device("m1", "bus", 1)]
    settings = mqtt_settings(table, "plant.toml", devices, "mqtt://127.0.0.1:1", {})
    return MqttPublisher(settings, devices).client


def test_mqtt_3_1_1_holds_no_message_back_for_the_acknowledgements_of_others():
    assert _client({}).max_inflight_messages == 0


def test_mqtt_5_keeps_a_bound():
    assert _client({"version": "5"}).max_inflight_messages == INFLIGHT_MQTT5
