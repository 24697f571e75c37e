"""cli.stamps: a poll's time stamp is the local time, ISO 8601, cut to the millisecond, with the
UTC offset in force at that moment (daylight saving time included)."""

from __future__ import annotations

import time
from datetime import datetime

import pytest

from mbtool.cli.stamps import local_time

# Central European time, written as a POSIX TZ string so that no tz database is needed:
# +01:00 in winter, +02:00 from the last Sunday of March to the last Sunday of October.
CET = "CET-1CEST,M3.5.0,M10.5.0/3"


@pytest.fixture
def central_europe(monkeypatch):
    monkeypatch.setenv("TZ", CET)
    time.tzset()
    yield
    monkeypatch.undo()
    time.tzset()


@pytest.mark.parametrize(
    "when, expected",
    [
        (1764140800.123456, "2025-11-26T08:06:40.123+01:00"),  # winter
        (1751328000.0, "2025-07-01T02:00:00.000+02:00"),  # summer, on the second
        (1751328000.9996, "2025-07-01T02:00:00.999+02:00"),  # cut, not rounded, to the millisecond
        (1743296399.5, "2025-03-30T01:59:59.500+01:00"),  # a moment before the clocks go forward
        (1743296400.25, "2025-03-30T03:00:00.250+02:00"),  # and after
    ],
)
def test_a_stamp_is_local_time_to_the_millisecond_with_the_offset_then_in_force(
    central_europe, when, expected
):
    assert local_time(when) == expected
    assert local_time(when) == datetime.fromtimestamp(when).astimezone().isoformat(timespec="milliseconds")


def test_every_millisecond_of_a_second_is_stamped_as_datetime_stamps_it(central_europe):
    """A float holds most exact milliseconds a hair under (.001 as .000999...): the stamp is
    that millisecond, as datetime (and so the MQTT payload of the same poll) writes it."""
    for k in range(1000):
        when = 1764140800 + k / 1000
        assert local_time(when) == datetime.fromtimestamp(when).astimezone().isoformat(
            timespec="milliseconds"
        )
    when = 1764140800.9999996  # rounds to the next second's first microsecond
    assert local_time(when) == datetime.fromtimestamp(when).astimezone().isoformat(timespec="milliseconds")
