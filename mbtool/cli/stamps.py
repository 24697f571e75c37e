"""Time stamps as a log reader wants them: local time, ISO 8601, milliseconds, UTC offset."""

from __future__ import annotations

import time

# The second last stamped (its epoch second, a float; none yet: minus infinity) and its text; a
# stamp in it is that text and its millisecond's ending, so a poll looks its stamp up: one
# strftime a second, however fast the polls come.
_second = -float("inf")
_second_text = ""
# ".000+01:00" to ".999+01:00": each millisecond and the UTC offset in force, made again when
# the offset changes (daylight saving time), and on first use: a one-shot command stamps nothing.
_zone = ""
_endings: list[str] = []
_round = float.__round__  # round() looks __round__ up on its number each call


def local_time(when: float | None = None) -> str:
    """Local time, ISO 8601 with milliseconds and UTC offset: what a log reader wants.

    Built from time.localtime, which knows the offset in force (a day-long poll crosses
    daylight saving time), at a third of datetime.astimezone's cost a poll.
    """
    if when is None:
        when = time.time()
    # Within the second last stamped, this is exact (two floats of one second), and the
    # fraction when % 1.0 gives.  To the microsecond first, as datetime takes a time stamp,
    # then cut to the millisecond: a time a float holds just under its millisecond (.001 as
    # .000999...) is that millisecond, and the stamp is the one the MQTT payload and datetime
    # write for the same poll.  Times 1e6, not 1_000_000: the same product, and a float's by a
    # float is specialized by the interpreter, by an int is not.
    fraction = when - _second
    if 0.0 <= fraction < 1.0:
        try:
            return _second_text + _endings[_round(fraction * 1e6) // 1000]
        except IndexError:  # 1000: .9999996 is the next second's .000
            pass
    return _new_second(when)


def _new_second(when: float) -> str:
    """The stamp of the first poll in a second: the second's text, and the offset's endings
    when the offset is not the one before."""
    global _second, _second_text, _zone
    fraction = when % 1.0
    second, milli = when - fraction, _round(fraction * 1e6) // 1000
    if milli == 1000:
        second, milli = second + 1.0, 0
    local = time.localtime(second)
    offset = local.tm_gmtoff // 60
    zone = f"{'-' if offset < 0 else '+'}{abs(offset) // 60:02d}:{abs(offset) % 60:02d}"
    if zone != _zone:
        _zone, _endings[:] = zone, [f".{ms:03d}{zone}" for ms in range(1000)]
    _second, _second_text = second, time.strftime("%Y-%m-%dT%H:%M:%S", local)
    return _second_text + _endings[milli]
