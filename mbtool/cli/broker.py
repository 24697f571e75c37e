"""The MQTT publisher (mbtool/mqtt/), started beside a run's outputs: poll's plant, and
read --interval's polls, each handed on where the command hands it to its output (never
inside the polling itself); paho-mqtt and the publisher imported only when a run publishes."""

from __future__ import annotations

import sys
import time

from mbtool.errors import PartialRead
from mbtool.mqtt.settings import read_settings
from mbtool.mqtt.topics import OFFLINE, ONLINE, DevicePoll
from mbtool.plant.schedule import LinkWorker
from mbtool.registermap.load import load_map


def make_publisher(settings, devices: list, maps: dict | None = None, quiet: bool = False):
    """The publisher of ``settings`` for ``devices`` (an inventory's, whose ``maps`` give
    discovery its devices' makers and models; or read's one device), to be started (``start``: it connects in the background, the broker may come later).  Each
    change of the broker's state, and each write, is a line on stderr unless ``quiet`` (the
    live view shows the broker's state in its title)."""
    from mbtool.mqtt.publisher import MqttPublisher  # noqa: PLC0415 - paho-mqtt, 49 ms: --mqtt and [mqtt] only

    headers = {}
    if settings.discovery:  # the model and maker Home Assistant shows, from each map's [device]
        loaded = {}
        for name, path in (maps or {}).items():
            if path not in loaded:
                loaded[path] = load_map(path).header
            headers[name] = loaded[path]

    def notify(line: str) -> None:
        if not quiet:
            print(f"mbtool: mqtt: {line}", file=sys.stderr, flush=True)

    return MqttPublisher(settings, devices, headers, notify)


class PublishedPolls:
    """read --interval --mqtt URL: each poll shown by the run's output (``output``: its
    Output, or ChangesOnly) and published, its values one message a poll (every poll: --changes
    is stdout's), the device online while its polls are answered and offline after one fails."""

    def __init__(self, output, url: str, name: str, unit: int) -> None:
        """``name``: --name, else ``unit<N>``; the settings are checked before anything opens."""
        settings, device = read_settings(url, name or f"unit{unit}", unit)
        self.output = output
        self.name = device.name
        self.publisher = make_publisher(settings, [device])
        self.publisher.start()

    def result(self, when: str, result, stamp: float | None = None) -> None:
        """A map's points, by name."""
        self.output.result(when, result, stamp)
        self._publish({row.name: row.value for row in result.rows}, stamp)

    def _publish(self, values: dict, stamp: float | None) -> None:
        self.publisher.report(DevicePoll(self.name, stamp or time.time(), values, ONLINE))

    def values(self, when: str, read, values: list, registers, stamp: float | None = None) -> None:
        """A poll of a read of one request: by the references given (read 40001 2), else by address."""
        self.output.values(when, read, values, registers, stamp)
        names = read.refs or [str(address) for address in read.addresses]
        self._publish(dict(zip(names, values, strict=True)), stamp)

    def failure(self, when: str, number: int, error: BaseException) -> None:
        self.output.failure(when, number, error)
        if not isinstance(error, PartialRead):  # a part read is a device that answers
            self.publisher.report(DevicePoll(self.name, time.time(), None, OFFLINE))

    def close(self) -> None:
        self.output.close()
        self.publisher.close()
        print(stats_line(self.publisher.stats()), file=sys.stderr, flush=True)


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
