"""poll's MQTT publisher (mbtool/mqtt/), started beside the plant's outputs: paho-mqtt and
the publisher imported only when a run publishes."""

from __future__ import annotations

import sys

from mbtool.registermap.load import load_map


def start_publisher(settings, plant, quiet: bool = False):
    """The publisher of ``settings`` for the inventory ``plant``, connecting (in the
    background: the broker may come later).  Each change of the broker's state is a line
    on stderr unless ``quiet`` (the live view shows it in its title)."""
    from mbtool.mqtt.publisher import MqttPublisher  # noqa: PLC0415 - paho-mqtt, 49 ms: --mqtt and [mqtt] only

    headers = {}
    if settings.discovery:  # the model and maker Home Assistant shows, from each map's [device]
        loaded = {}
        for name, path in plant.maps.items():
            if path not in loaded:
                loaded[path] = load_map(path).header
            headers[name] = loaded[path]

    def notify(line: str) -> None:
        if not quiet:
            print(f"mbtool: mqtt: {line}", file=sys.stderr, flush=True)

    publisher = MqttPublisher(settings, plant.devices, headers, notify)
    publisher.start()
    return publisher


def stats_line(stats: dict) -> str:
    """The broker's line of poll's statistics table."""
    return (
        f"mqtt {stats['broker']} {stats['state']}: {stats['published']} published, "
        f"{stats['spooled']} spooled ({stats['in_spool']} unsent), "
        f"{stats['spool_dropped'] + stats['dropped']} dropped"
    )
