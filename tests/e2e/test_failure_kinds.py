"""One classification for one failure, everywhere (issue 39.9): each way a link fails is the same
kind in the exporter's ``modbus_error_info{kind}``, in ``poll --stats json`` and ``read --interval
--stats json`` (the transaction's outcome), in ``ping``'s line, and the same exit code in ``read``,
``ping`` and ``poll``: ``connection`` (exit 6) when the link cannot be opened or reached,
``link_lost`` (exit 3) when the peer hangs up in the middle of a reply.

Each failure is a real one: a TCP port nobody listens on, a UDP port the host answers "port
unreachable" for, a TLS handshake with a plain Modbus TCP server, a serial device that is not
there, and a server that sends half a reply and closes.
"""

from __future__ import annotations

import contextlib
import json
import re
import shutil
import socket
import threading
from pathlib import Path
from urllib.parse import quote

import pytest
from helpers.exporter import METER_MAP, exporting
from helpers.run import run_cli
from helpers.served import serve
from helpers.sockets import free_udp_port
from prometheus_client.parser import text_string_to_metric_families

pytestmark = pytest.mark.timeout(90)

# Each failure: its kind and the exit code that kind is, everywhere.
KINDS = {"connection": 6, "link_lost": 3}
FAILURES = {
    "refused TCP": "connection",
    "unreachable UDP": "connection",
    "TLS handshake failure": "connection",
    "missing serial port": "connection",
    "peer closed mid-reply": "link_lost",
}
MISSING_SERIAL_PORT = "/dev/ttyMBTOOLNONE0"


class HalfReply:
    """A Modbus TCP server that answers every request with the first 5 bytes of a reply (its
    transaction id, protocol id and the first length byte) and closes the connection."""

    def __init__(self) -> None:
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.port = self.sock.getsockname()[1]
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            with conn:
                conn.settimeout(2)
                with contextlib.suppress(OSError):
                    request = conn.recv(260)
                    conn.sendall(request[:4] + b"\x00")

    def close(self) -> None:
        self.stop.set()
        self.thread.join(2)
        self.sock.close()


@pytest.fixture(scope="module")
def targets():
    """The target of each failure."""
    assert not Path(MISSING_SERIAL_PORT).exists()
    refused = socket.socket()
    refused.bind(("127.0.0.1", 0))  # bound, not listening: connecting is refused
    half = HalfReply()
    try:
        with serve() as plain:
            yield {
                "refused TCP": f"tcp://127.0.0.1:{refused.getsockname()[1]}",
                "unreachable UDP": f"udp://127.0.0.1:{free_udp_port()}",
                "TLS handshake failure": f"tls://127.0.0.1:{plain.port}",
                "missing serial port": MISSING_SERIAL_PORT,
                "peer closed mid-reply": f"tcp://127.0.0.1:{half.port}",
            }
    finally:
        half.close()
        refused.close()


TABLE = pytest.mark.parametrize("failure", list(FAILURES))


@TABLE
def test_read_exits_with_the_code_of_the_kind(targets, failure):
    res = run_cli("read-holding-registers", "0", "1", "-p", targets[failure], "-t", "0.5")
    assert res.returncode == KINDS[FAILURES[failure]], res
    assert len(res.stderr.strip().splitlines()) == 1, res


@TABLE
def test_read_interval_counts_the_transaction_as_the_kind(targets, failure):
    res = run_cli(
        "read-holding-registers", "0", "1", "-p", targets[failure], "-t", "0.5",
        "--interval", "0", "--polls", "1", "--stats", "json",
    )  # fmt: skip
    assert res.returncode == KINDS[FAILURES[failure]], res
    figures = json.loads([line for line in res.stderr.splitlines() if line.startswith("{")][0])
    assert figures["transactions"] == 1 and figures[FAILURES[failure]] == 1, figures


@TABLE
def test_poll_stats_count_the_transaction_as_the_kind(targets, failure, tmp_path):
    inventory = tmp_path / "plant.toml"
    inventory.write_text(
        f'[links.a]\ntarget = "{targets[failure]}"\ntimeout = 0.5\n'
        '[devices.d]\nlink = "a"\nunit = 1\nread = ["40001 1"]\n'
    )
    res = run_cli("poll", inventory, "--once", "-o", "json", "--stats", "json")
    assert res.returncode == KINDS[FAILURES[failure]], res
    stats = json.loads([line for line in res.stderr.splitlines() if line.startswith("{")][0])
    for counted in (stats["devices"]["d"], stats["links"]["a"]):
        assert counted["transactions"] == 1 and counted[FAILURES[failure]] == 1, counted


@TABLE
def test_ping_says_the_kind_and_exits_with_its_code(targets, failure):
    res = run_cli("ping", "-p", targets[failure], "-c", "1", "-t", "0.5")
    assert res.returncode == KINDS[FAILURES[failure]], res
    lines = re.findall(r"^unit 1: seq=1 (.*)$", res.stdout, re.M)
    if lines:  # the link opened, and the request failed: the line names the kind
        assert lines[0].startswith(FAILURES[failure].replace("_", " ") + ": "), res
        assert re.search(rf"\b{FAILURES[failure].replace('_', ' ')} 1\b", res.stderr), res
    else:  # the first link could not be opened: that ends ping, as any command
        assert KINDS[FAILURES[failure]] == 6 and len(res.stderr.strip().splitlines()) == 1, res


def test_the_exporter_gives_each_failure_its_kind(targets, tmp_path):
    maps = tmp_path / "maps"
    maps.mkdir()
    shutil.copy(METER_MAP, maps / "energy-meter.toml")
    deadline = {"X-Prometheus-Scrape-Timeout-Seconds": "2"}
    # "*" allows network links only; a serial device needs a pattern that starts with its path.
    allowed = ("--allow-target", "*", "--allow-target", "/dev/ttyMBTOOL*")
    with exporting("--maps", maps, *allowed, "-t", "0.5", tmp_path=tmp_path) as exporter:
        for failure, kind in FAILURES.items():
            status, _, text = exporter.get(
                f"/modbus?target={quote(targets[failure], safe='')}&module=energy-meter", deadline
            )
            assert status == 200, text
            (info,) = [
                sample.labels
                for family in text_string_to_metric_families(text)
                for sample in family.samples
                if sample.name == "modbus_error_info"
            ]
            assert info["kind"] == kind, (failure, info)
