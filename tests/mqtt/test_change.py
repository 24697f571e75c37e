"""What on_change, deadband and heartbeat publish (mbtool/mqtt/change.py), for scripted
sequences of values: exactly the expected points, at exactly the expected polls."""

from __future__ import annotations

import math

from mbtool.codec.record import replace
from mbtool.mqtt.change import ChangeFilter
from mbtool.mqtt.settings import Deadband, MqttSettings

BASE = MqttSettings("localhost", 1883, False, "test", "plant")


def _run(settings: MqttSettings, polls: list[tuple[float, dict]]) -> list[dict]:
    changes = ChangeFilter(settings)
    return [changes.select("meter", when, values) for when, values in polls]


def test_without_on_change_every_point_of_every_poll_is_published():
    polls = [(t, {"flow": 1.0, "on": True}) for t in range(3)]
    assert _run(BASE, polls) == [{"flow": 1.0, "on": True}] * 3


def test_on_change_publishes_a_point_only_when_it_moved_past_its_deadband_from_the_last_published():
    settings = replace(BASE, on_change=True, deadband=Deadband(0.5))
    polls = [
        (0, {"flow": 10.0, "mode": "auto", "on": False}),  # first: everything
        (1, {"flow": 10.4, "mode": "auto", "on": False}),  # within the band: nothing
        (2, {"flow": 10.6, "mode": "auto", "on": False}),  # 0.6 from the published 10.0: flow
        (3, {"flow": 10.9, "mode": "manual", "on": False}),  # 0.3 from 10.6: the label only
        (4, {"flow": 10.9, "mode": "manual", "on": True}),  # a bit always counts
        (5, {"flow": 11.0, "mode": "manual", "on": True}),  # 0.4 from 10.6 (a drift adds up)...
        (6, {"flow": 11.2, "mode": "manual", "on": True}),  # ...0.6: published
    ]
    assert _run(settings, polls) == [
        {"flow": 10.0, "mode": "auto", "on": False},
        {},
        {"flow": 10.6},
        {"mode": "manual"},
        {"on": True},
        {},
        {"flow": 11.2},
    ]


def test_a_percentage_deadband_is_of_the_last_published_value_and_a_point_may_have_its_own():
    settings = replace(
        BASE, on_change=True, deadband=Deadband(10, percent=True), deadbands={"power": Deadband(0)}
    )
    polls = [
        (0, {"flow": 100.0, "power": 5}),
        (1, {"flow": 109.0, "power": 5}),  # 9 % of 100: not past 10 %
        (2, {"flow": 111.0, "power": 6}),  # 11 %: flow; power's band is 0: any change
        (3, {"flow": 100.5, "power": 6}),  # 9.5 % of 111
    ]
    assert _run(settings, polls) == [{"flow": 100.0, "power": 5}, {}, {"flow": 111.0, "power": 6}, {}]


def test_the_heartbeat_publishes_every_point_again_once_due():
    settings = replace(BASE, on_change=True, heartbeat=10)
    polls = [(t, {"flow": 1.0 if t < 15 else 1.5, "level": 2}) for t in (0, 4, 9.9, 10, 15, 19.9, 20)]
    everything = {"flow": 1.0, "level": 2}
    assert _run(settings, polls) == [
        everything, {}, {}, everything, {"flow": 1.5}, {}, {"flow": 1.5, "level": 2},
    ]  # fmt: skip


def test_nan_and_invalid_values_are_changes_only_when_they_come_or_go():
    settings = replace(BASE, on_change=True, deadband=Deadband(1))
    polls = [(0, {"t": math.nan}), (1, {"t": math.nan}), (2, {"t": 20.0}), (3, {"t": None}), (4, {"t": None})]
    published = _run(settings, polls)
    assert [list(p) for p in published] == [["t"], [], ["t"], ["t"], []]
    assert math.isnan(published[0]["t"]) and published[2] == {"t": 20.0} and published[3] == {"t": None}


def test_the_heartbeat_is_each_poll_groups_own():
    """A device of poll groups (issue 44): a poll carries its group's points only, so the
    heartbeat of one group does not stand for the others' points."""
    settings = replace(BASE, on_change=True, heartbeat=10)
    changes = ChangeFilter(settings)
    polls = [(0, {"flow": 1.0}, "fast"), (0.5, {"energy": 5}, "slow"), (10, {"flow": 1.0}, "fast"),
             (10.5, {"energy": 5}, "slow"), (11, {"flow": 1.0}, "fast")]  # fmt: skip
    published = [changes.select("meter", when, values, group) for when, values, group in polls]
    assert published == [{"flow": 1.0}, {"energy": 5}, {"flow": 1.0}, {"energy": 5}, {}]
