"""A device poll's JSON message (mbtool/mqtt/topics.py), as a subscriber's json.loads reads it."""

from __future__ import annotations

import json
import math

from mbtool.mqtt.topics import device_payload


def test_a_device_message_carries_the_fleet_labels_and_its_points_as_read():
    message = json.loads(
        device_payload(0.25, {"site": "north", "instance": "edge7"}, 3, {"flow": 21.5, "on": True})
    )
    assert message == {
        "time": "1970-01-01T00:00:00.250Z",
        "site": "north",
        "instance": "edge7",
        "unit": 3,
        "points": {"flow": 21.5, "on": True},
    }


def _not_json(word: str):
    raise AssertionError(f"{word} is no JSON (RFC 8259): Python's json writes it, other parsers refuse it")


def test_nan_and_the_infinities_are_null_which_json_has_words_for():
    values = {"a": math.nan, "b": math.inf, "c": -math.inf, "d": 1.5}
    message = json.loads(device_payload(0.0, {}, 1, values), parse_constant=_not_json)
    assert message["points"] == {"a": None, "b": None, "c": None, "d": 1.5}
    assert math.isnan(values["a"])  # the poll's own values are left as they were
