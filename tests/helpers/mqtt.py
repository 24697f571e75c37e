"""A plant publishing to a real broker, as the MQTT tests (tests/e2e/test_mqtt.py,
test_sparkplug.py) start one: mosquitto, pymodbus's TCP device, ``mbtool poll`` as a process
and a paho subscriber, together, and stopped together whatever the test does."""

from __future__ import annotations

import contextlib
import signal
import subprocess
from pathlib import Path

from peers.broker import Subscriber, mosquitto

from helpers.devices import start_device, stop_device
from helpers.run import start_mbtool
from helpers.sockets import free_port

STOPPING = 10.0  # seconds poll has to end once told to (SIGTERM), then SIGKILL


def run_poll(plant: Path, *args: str, wait: float = 20) -> tuple[int, str, str]:
    """``mbtool poll PLANT ARGS`` to its end (killed at ``wait``): exit code, stdout, stderr;
    a traceback fails the test."""
    proc = start_mbtool("poll", plant, *args)
    try:
        out, err = proc.communicate(timeout=wait)
    finally:
        proc.kill()
    assert "Traceback" not in err, err
    return proc.returncode, out, err


class Published:
    """What ``plant_on_broker`` started: ``broker`` (its ``url``, ``port``), ``device`` (pymodbus's,
    its ``target``), ``poll`` (the process), ``subscriber``; once it ended, poll's ``out``, ``err``."""

    def __init__(self, stack: contextlib.ExitStack, port: int, broker, device, poll, subscriber) -> None:
        self.stack, self.port = stack, port
        self.broker, self.device, self.poll, self.subscriber = broker, device, poll, subscriber
        self.out = self.err = ""

    def kill_device(self) -> None:
        stop_device(self.device.proc)

    def device_back(self) -> None:
        """A new device on the killed one's port."""
        self.device = self.stack.enter_context(
            start_device(tcp=True, framer="socket", units="1", port=self.port)
        )


@contextlib.contextmanager
def plant_on_broker(
    tmp_path: Path, inventory: str, *poll_args: str, topics: str = "#", signal_=signal.SIGTERM
):
    """mosquitto on a free port, pymodbus's TCP device (unit 1: 40001.. hold 100, 101...),
    a subscriber to ``topics`` and ``mbtool poll`` of ``inventory`` (its text: ``{target}``
    the device's, ``{url}`` the broker's) with ``poll_args``.  At the end poll is stopped
    (``signal_``, SIGKILL after STOPPING s unless it ended already), its output kept in the
    Published, the subscriber closed, the device and broker stopped; a traceback fails the test."""
    port = free_port()
    with contextlib.ExitStack() as stack:
        device = stack.enter_context(start_device(tcp=True, framer="socket", units="1", port=port))
        broker = stack.enter_context(mosquitto())
        plant = tmp_path / "plant.toml"
        plant.write_text(inventory.replace("{target}", device.target).replace("{url}", broker.url))
        subscriber = Subscriber(broker.port, topics)
        stack.callback(subscriber.close)
        poll = start_mbtool("poll", plant, *poll_args)
        published = Published(stack, port, broker, device, poll, subscriber)
        try:
            yield published
        finally:
            if poll.poll() is None:
                poll.send_signal(signal_)
            try:
                published.out, published.err = poll.communicate(timeout=STOPPING)
            except subprocess.TimeoutExpired:
                poll.kill()
                published.out, published.err = poll.communicate(timeout=STOPPING)
        assert "Traceback" not in published.err, published.err
