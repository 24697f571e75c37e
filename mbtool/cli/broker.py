"""poll's MQTT publisher (mbtool/mqtt/), started beside the plant's outputs: paho-mqtt and
the publisher imported only when a run publishes."""

from __future__ import annotations

import sys

from mbtool.plant.schedule import LinkWorker
from mbtool.registermap.load import load_map


def make_publisher(settings, plant, quiet: bool = False):
    """The publisher of ``settings`` for the inventory ``plant``, to be started
    (``start``: it connects in the background, the broker may come later).  Each change of
    the broker's state, and each write, is a line on stderr unless ``quiet`` (the live view
    shows the broker's state in its title)."""
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

    return MqttPublisher(settings, plant.devices, headers, notify)


def hand_writes(publisher, runner) -> None:
    """``writes = true``: each device's writes go to the worker of its link, which runs them
    between its polls (the link is never opened a second time)."""
    worker_of: dict[str, LinkWorker] = {}
    for worker in runner.workers:
        worker.accept_jobs()
        worker_of |= {state.spec.name: worker for state in worker.devices}
    publisher.submit = lambda device, job: worker_of[device].submit(device, job)


def stats_line(stats: dict) -> str:
    """The broker's line of poll's statistics table."""
    return (
        f"mqtt {stats['broker']} {stats['state']}: {stats['published']} published, "
        f"{stats['spooled']} spooled ({stats['in_spool']} unsent), "
        f"{stats['spool_dropped'] + stats['dropped']} dropped"
        + (
            f"; writes: {stats['writes_received']} received, {stats['writes_written']} written, "
            f"{stats['writes_refused']} refused, {stats['writes_failed']} failed"
            if "writes_received" in stats
            else ""
        )
    )
