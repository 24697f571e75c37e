"""Time stamps as a log reader wants them: local time, ISO 8601, milliseconds, UTC offset."""

from __future__ import annotations

import time

# The last second stamped: its epoch second, its text and its UTC offset; one strftime a
# second, however fast the polls come.
_second: float | None = None
_second_text = ""
_zone = ""
_MILLISECONDS: list[str] = []  # ".000" to ".999": a poll looks its milliseconds up, not formats them


def local_time(when: float | None = None) -> str:
    """Local time, ISO 8601 with milliseconds and UTC offset: what a log reader wants.

    Built from time.localtime, which knows the offset in force (a day-long poll crosses
    daylight saving time), at a third of datetime.astimezone's cost a poll.
    """
    global _second, _second_text, _zone
    if when is None:
        when = time.time()
    # To the microsecond first, as datetime takes a time stamp, then cut to the millisecond: a
    # time a float holds just under its millisecond (.001 as .000999...) is that millisecond,
    # and the stamp is the one the MQTT payload and datetime write for the same poll.
    fraction = when % 1.0
    second = when - fraction  # whole seconds, kept a float: no conversion a stamp
    micro = round(fraction * 1_000_000)
    if micro == 1_000_000:  # .9999996 is the next second's .000
        second, micro = second + 1.0, 0
    if second != _second:
        local = time.localtime(second)
        offset = local.tm_gmtoff // 60
        sign = "-" if offset < 0 else "+"
        _second, _second_text = second, time.strftime("%Y-%m-%dT%H:%M:%S", local)
        _zone = f"{sign}{abs(offset) // 60:02d}:{abs(offset) % 60:02d}"
        if not _MILLISECONDS:  # made on first use: a one-shot command stamps nothing
            _MILLISECONDS.extend(f".{ms:03d}" for ms in range(1000))
    return f"{_second_text}{_MILLISECONDS[micro // 1000]}{_zone}"
