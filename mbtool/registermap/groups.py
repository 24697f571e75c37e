"""Poll groups: a device's points read each at their own pace (issue 44).

::

    once = ["serial_number", "firmware"]   # read at start and after each reconnect

    [groups.fast]                # in a map, or a device of an inventory ([devices.NAME.groups.fast])
    interval = 1                 # seconds
    points = ["power", "breaker"]

    [groups.slow]
    interval = 300
    points = ["energy_import", "energy_export"]

The points no group names are the device's default group, read at the device's interval.  A
point is in one group at most (``once`` counts as one): read at two paces, its value would be
shown twice as often as one of them asks and merged with neither.  Each group is planned
apart, so one request never serves two groups and a fast group's read stays short.
Everything is checked when the map or the inventory is loaded: ``fail(key, why)`` makes the
error that names where.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Collection

from mbtool.codec.record import record

DEFAULT, ONCE = "default", "once"  # the group of the points named in none; the points read once
GROUP_KEYS = {"interval": "seconds between its polls, such as 1", "points": "the names of its points"}
GROUP_NAME = re.compile(r"[a-zA-Z_][a-zA-Z0-9_-]*")


@record
class GroupPlan:
    """A group as its file gives it: its name, its interval (math.inf: once) and its points."""

    name: str
    interval: float
    points: tuple[str, ...]


def read_groups(
    groups: object, once: object, known: Collection[str], fail: Callable[[str, str], Exception]
) -> list[GroupPlan]:
    """The groups a map or a device gives (``groups``: its ``groups`` table, ``once``: its list,
    either None when not given), checked against the point names ``known``."""
    plans = []
    taken: dict[str, str] = {}  # point -> the group that has it
    if groups is not None:
        if not isinstance(groups, dict):
            raise fail("groups", "expected tables of groups, such as [groups.fast] with interval and points")
        for name, table in groups.items():
            key = f"groups.{name}"
            if not GROUP_NAME.fullmatch(name) or name in (DEFAULT, ONCE):
                raise fail(key, f"a group's name is letters, digits, _ and -, not {DEFAULT} or {ONCE}")
            if not isinstance(table, dict):
                raise fail(key, "expected a table with interval and points")
            for item in table:
                if item not in GROUP_KEYS:
                    raise fail(f"{key}.{item}", f"unknown key (known: {', '.join(GROUP_KEYS)})")
            interval = table.get("interval")
            if (
                isinstance(interval, bool)
                or not isinstance(interval, int | float)
                or not 0 < interval <= 86400
            ):
                raise fail(f"{key}.interval", "expected seconds above 0, at most a day (86400)")
            names = _names(table.get("points"), f"{key}.points", known, taken, name, fail)
            plans.append(GroupPlan(name, float(interval), names))
    if once is not None:
        plans.append(GroupPlan(ONCE, math.inf, _names(once, ONCE, known, taken, ONCE, fail)))
    return plans


def _names(names: object, key: str, known: Collection[str], taken: dict[str, str], group: str, fail) -> tuple:
    if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
        raise fail(key, 'expected a list of point names, such as ["power"]')
    for name in names:
        if name not in known:
            raise fail(key, f"no point named {name} (the points: {', '.join(known)})")
        if name in taken:
            where = "it" if taken[name] == group else f"group {taken[name]}"
            raise fail(key, f"point {name} is in {where} already: a point is read at one pace")
        taken[name] = group
    return tuple(names)
