"""Under systemd (issue 44): poll and the exporter say READY=1 and keep the watchdog fed
(WATCHDOG=1) on the socket NOTIFY_SOCKET names, a datagram each, as sd_notify(3) does; and
contrib/mbtool-poll.service passes systemd-analyze verify."""

from __future__ import annotations

import shutil
import socket
import subprocess
import time
from pathlib import Path

import pytest
from helpers.checks import wait_until
from helpers.exporter import exporting
from helpers.run import REPO_ROOT, run_mbtool, start_mbtool

PLANT = '[links.a]\ntarget = "sim://"\n[devices.d]\nlink = "a"\nread = ["40001"]\ninterval = 0.2\n'


@pytest.fixture
def notify_socket(tmp_path):
    """A fake systemd: a datagram socket, as NOTIFY_SOCKET names one."""
    path = tmp_path / "notify"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(0.05)
    yield sock, str(path)
    sock.close()


def received(sock) -> list[str]:
    messages = []
    while True:
        try:
            messages.append(sock.recv(4096).decode())
        except TimeoutError:
            return messages


def test_poll_says_ready_feeds_the_watchdog_and_says_it_stops(tmp_path, notify_socket):
    sock, path = notify_socket
    (tmp_path / "plant.toml").write_text(PLANT)
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "400000"}
    res = run_mbtool("poll", tmp_path / "plant.toml", "--duration", "1.5", "-o", "json", env=env)
    assert res.returncode == 0, res
    messages = received(sock)
    assert messages and messages[0].startswith("READY=1"), messages
    # Half the watchdog's 0.4 s: some 7 pings in 1.5 s; at least 4 under a loaded machine.
    assert messages.count("WATCHDOG=1") >= 4, messages
    assert messages[-1].startswith("STOPPING=1"), messages


def test_a_plant_waiting_for_its_next_poll_feeds_the_watchdog(tmp_path, notify_socket):
    """A device polled once a minute: between its polls the scheduler waits on schedule, which
    is moving, not stuck."""
    sock, path = notify_socket
    (tmp_path / "plant.toml").write_text(PLANT.replace("interval = 0.2", "interval = 60"))
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "400000"}
    assert run_mbtool("poll", tmp_path / "plant.toml", "--duration", "1.5", env=env).returncode == 0
    assert received(sock).count("WATCHDOG=1") >= 4


def test_a_plant_whose_output_is_stuck_does_not_feed_the_watchdog(tmp_path, notify_socket):
    """Issue 44: the watchdog says the plant moves, not only that the process lives.  With its
    output stuck (stdout a pipe nobody reads, full), its records wait, no WATCHDOG=1 follows,
    and systemd would restart it."""
    sock, path = notify_socket
    wide = PLANT.replace('["40001"]', '["40001 100"]').replace("interval = 0.2", "interval = 0.01")
    (tmp_path / "plant.toml").write_text(wide)
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"}
    proc = start_mbtool("poll", tmp_path / "plant.toml", "-o", "json", env=env, stderr=subprocess.DEVNULL)
    try:
        messages: list[str] = []
        assert wait_until(lambda: bool(messages.extend(received(sock)) or messages), 10), messages
        assert messages[0].startswith("READY=1"), messages
        time.sleep(2.0)  # a poll's line is some 2 KB: the pipe's 64 KiB fill in a fraction of this
        received(sock)  # what came while it filled
        time.sleep(1.0)  # five of the watchdog's periods with the output stuck
        late = received(sock)
        assert proc.poll() is None and "WATCHDOG=1" not in late, late
    finally:
        proc.kill()
        proc.wait(5)


def test_a_watchdog_for_another_process_is_not_fed(tmp_path, notify_socket):
    sock, path = notify_socket
    (tmp_path / "plant.toml").write_text(PLANT)
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000", "WATCHDOG_PID": "1"}
    assert run_mbtool("poll", tmp_path / "plant.toml", "--duration", "0.6", env=env).returncode == 0
    messages = received(sock)
    assert messages[0].startswith("READY=1") and "WATCHDOG=1" not in messages, messages


def test_without_notify_socket_nothing_is_sent_and_a_dead_socket_is_no_failure(tmp_path):
    (tmp_path / "plant.toml").write_text(PLANT)
    env = {"NOTIFY_SOCKET": str(tmp_path / "nobody"), "WATCHDOG_USEC": "100000"}
    res = run_mbtool("poll", tmp_path / "plant.toml", "--duration", "0.5", env=env)
    assert res.returncode == 0 and "Traceback" not in res.stderr, res


def test_the_exporter_says_ready_once_it_listens(tmp_path, notify_socket):
    sock, path = notify_socket
    (tmp_path / "plant.toml").write_text(PLANT)
    with exporting(str(tmp_path / "plant.toml"), tmp_path=tmp_path, env={"NOTIFY_SOCKET": path}):
        messages: list[str] = []
        assert wait_until(lambda: bool(messages.extend(received(sock)) or messages), 5), messages
    assert messages[0].startswith("READY=1"), messages


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="Debian's systemd is not installed")
def test_the_unit_passes_systemd_analyze_verify(tmp_path):
    """The unit as shipped, its ExecStart's program put where this test's mbtool is (verify
    checks that the program exists) and nothing else changed."""
    unit = (REPO_ROOT / "contrib" / "mbtool-poll.service").read_text()
    program = shutil.which("mbtool") or str(Path(__import__("sys").executable).parent / "mbtool")
    assert "ExecStart=/usr/bin/mbtool " in unit
    (tmp_path / "mbtool-poll.service").write_text(
        unit.replace("ExecStart=/usr/bin/mbtool ", f"ExecStart={program} ")
    )
    res = subprocess.run(
        ["systemd-analyze", "verify", "--man=no", str(tmp_path / "mbtool-poll.service")],
        capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    if res.returncode != 0 and "Failed to" in res.stderr and "bus" in res.stderr.lower():
        pytest.skip(f"systemd-analyze cannot run here: {res.stderr.strip()}")
    assert res.returncode == 0 and res.stderr.strip() == "", res.stderr
