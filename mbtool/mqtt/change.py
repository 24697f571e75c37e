"""Which points of a poll are published: every one, or (``on_change``) those that moved by
more than their deadband since they were last published, and every one again once the
heartbeat is due.  A point is compared with the value it last had on the broker, not with
its previous reading, so a slow drift is published once it adds up past the deadband."""

from __future__ import annotations

import math

from mbtool.mqtt.settings import MqttSettings

MISSING = object()


class ChangeFilter:
    """The values last published, a device at a time."""

    def __init__(self, settings: MqttSettings) -> None:
        self.settings = settings
        self.published: dict[str, dict[str, object]] = {}  # device -> point -> value
        # (device, poll group) -> when its every point was last published: a poll of a device
        # of groups (poll's, issue 44) carries one group's points, whose heartbeat is their own
        self.whole_at: dict[tuple[str, str], float] = {}

    def select(
        self, device: str, when: float, values: dict[str, object], group: str = ""
    ) -> dict[str, object]:
        """The points of ``values`` (a poll's, of ``group``, read at ``when``) to publish now."""
        settings = self.settings
        if not settings.on_change:  # every point, every poll: nothing to remember
            return values
        last = self.published.setdefault(device, {})
        beat = self.whole_at.get((device, group))
        if beat is None or (settings.heartbeat and when - beat >= settings.heartbeat):
            self.whole_at[device, group] = when
            last.update(values)
            return dict(values)
        chosen = {
            name: value
            for name, value in values.items()
            if self._changed(last.get(name, MISSING), value, name)
        }
        last.update(chosen)
        return chosen

    def _changed(self, before, now, point: str) -> bool:
        if before is MISSING:
            return True
        if _number(before) and _number(now):
            if math.isnan(before) or math.isnan(now):
                return math.isnan(before) != math.isnan(now)
            if math.isinf(before) or math.isinf(now):
                return before != now
            return self.settings.deadband_of(point).moved(before, now)
        return before != now or type(before) is not type(now)


def _number(value) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)
