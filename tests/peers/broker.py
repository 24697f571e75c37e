"""A real MQTT broker for the tests: Debian's mosquitto on a free loopback port, with the
config file the test asks for (a password file, a TLS listener), and paho-mqtt subscribers.

``mosquitto`` missing: the tests that need it skip with that reason (``.ci/run`` installs
it; ``apt-get install mosquitto`` does too)."""

from __future__ import annotations

import contextlib
import getpass
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import paho.mqtt.client as paho
import pytest
from paho.mqtt.enums import CallbackAPIVersion

MOSQUITTO = shutil.which("mosquitto") or (
    "/usr/sbin/mosquitto" if Path("/usr/sbin/mosquitto").exists() else None
)
needs_mosquitto = pytest.mark.skipif(
    MOSQUITTO is None,
    reason="mosquitto is not installed (apt-get install mosquitto): no broker to publish to",
)


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class Broker:
    """A running mosquitto: ``url``, and stop/start on the same port (an outage)."""

    def __init__(self, folder: Path, extra: str = "", port: int | None = None) -> None:
        self.folder = folder
        self.port = port or _free_port()
        self.extra = extra
        self.proc: subprocess.Popen | None = None
        self.url = f"mqtt://127.0.0.1:{self.port}"

    def start(self) -> None:
        conf = self.folder / "mosquitto.conf"
        conf.write_text(
            f"listener {self.port} 127.0.0.1\n"
            + ("allow_anonymous true\n" if "allow_anonymous" not in self.extra else "")
            + ("persistence false\n" if "persistence" not in self.extra else "")
            # As the test's own user: started as root, mosquitto would become "mosquitto",
            # who cannot read the test's files (its password file, its keys).
            + f"user {getpass.getuser()}\n"
            + self.extra
        )
        self.log = open(self.folder / "mosquitto.log", "ab")  # noqa: SIM115 - closed by stop
        self.proc = subprocess.Popen([MOSQUITTO, "-c", str(conf)], stdout=self.log, stderr=self.log)
        end = time.monotonic() + 5
        while time.monotonic() < end:
            with (
                contextlib.suppress(OSError),
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2),
            ):
                return
            if self.proc.poll() is not None:
                break
            time.sleep(0.02)
        raise AssertionError(f"mosquitto did not start: {(self.folder / 'mosquitto.log').read_text()}")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(timeout=5)
        if self.proc is not None:
            self.log.close()
        self.proc = None


@contextlib.contextmanager
def mosquitto(extra: str = ""):
    """A mosquitto started for the test and stopped after it."""
    with tempfile.TemporaryDirectory(prefix="mbtool-mosquitto-") as folder:
        broker = Broker(Path(folder), extra)
        broker.start()
        try:
            yield broker
        finally:
            broker.stop()


class Subscriber:
    """A paho-mqtt client that keeps every message of the topics it subscribed to, in order:
    (topic, payload bytes, retain)."""

    def __init__(self, port: int, topics: str | list[str] = "#", session: bool = False, **login) -> None:
        """``session``: the broker keeps the subscription and queues what comes while this
        subscriber is away (a broker stopped and started with persistence)."""
        self.messages: list[tuple[str, bytes, bool]] = []
        self.lock = threading.RLock()  # wait_for's predicate may call on()
        self.ready = threading.Event()
        self.client = paho.Client(
            CallbackAPIVersion.VERSION2, client_id=f"test-{time.monotonic_ns()}", clean_session=not session
        )
        self.client.reconnect_delay_set(0.1, 0.2)
        if login:
            self.client.username_pw_set(login["username"], login.get("password"))
        topics = [topics] if isinstance(topics, str) else topics
        self.client.on_connect = lambda c, u, f, r, p: [c.subscribe(t, qos=1) for t in topics]
        self.client.on_subscribe = lambda c, u, m, r, p: self.ready.set()
        self.client.on_message = self._message
        self.client.connect("127.0.0.1", port, 30)
        self.client.loop_start()
        assert self.ready.wait(5), "the test's subscriber did not subscribe"

    def _message(self, client, userdata, message) -> None:
        with self.lock:
            self.messages.append((message.topic, message.payload, bool(message.retain)))

    def on(self, topic: str) -> list[bytes]:
        with self.lock:
            return [payload for name, payload, _ in self.messages if name == topic]

    def wait_for(self, predicate, wait: float = 10.0) -> bool:
        end = time.monotonic() + wait
        while time.monotonic() < end:
            with self.lock:
                if predicate(list(self.messages)):
                    return True
            time.sleep(0.02)
        return False

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()
