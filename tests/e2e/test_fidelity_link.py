"""mbtool as a master against independent peers (issue 12, link side):

* unit 0 over Modbus TCP is an address like any other (libmodbus's server answers it;
  pymodbus 3.16's server answers it with exception 04), while with RTU or ASCII framing
  it stays a broadcast that only writes may use (12.1);
* a reply to an earlier attempt that arrives late, while mbtool waits for a retry's,
  answers the request (12.2): here pymodbus's server behind a proxy that delays every reply.
"""

from __future__ import annotations

import socket
import subprocess
import threading
import time

import pytest
from helpers.checks import assert_one_error_line
from helpers.devices import HOLDING, build_libmodbus
from helpers.run import TESTS_DIR, run_cli, run_mbtool
from helpers.sockets import free_port

pytestmark = pytest.mark.timeout(60)

LIBMODBUS_SERVER = (TESTS_DIR / "peers" / "libmodbus_server.c").read_text()


@pytest.fixture(scope="module")
def libmodbus_server(tmp_path_factory):
    program = build_libmodbus(tmp_path_factory, "server", LIBMODBUS_SERVER)
    port = free_port()
    proc = subprocess.Popen([str(program), str(port)], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "READY"
        yield f"tcp://127.0.0.1:{port}"
    finally:
        proc.kill()
        proc.wait(timeout=5)


@pytest.mark.parametrize("unit", ["0", "255"])
def test_unit_0_over_modbus_tcp_reads_and_writes_libmodbus(libmodbus_server, unit):
    res = run_cli("write-register", "5", "4321", "-u", unit, "-p", libmodbus_server)
    assert res.returncode == 0, str(res)
    assert "broadcast" not in res.stderr
    res = run_cli("read-holding-registers", "4", "3", "-u", unit, "-p", libmodbus_server)
    assert res.returncode == 0, str(res)
    assert res.stdout.split() == ["4", "1004", "5", "4321", "6", "1006"]


def test_unit_0_over_modbus_tcp_is_sent_to_pymodbus(tcp_device):
    """pymodbus 3.16's server has no unit 0 and says so with exception 04 (libmodbus answers):
    mbtool sends the request and reports the device's answer, as for any unit."""
    res = run_cli("read-holding-registers", "0", "2", "-u", "0", "-p", tcp_device.target)
    line = assert_one_error_line(res, 4)
    assert line == "mbtool: exception 04 Server Device Failure to FC 03 (0x03)"


def test_unit_0_with_serial_framing_stays_a_broadcast(socket_rtu_device):
    res = run_cli("read-holding-registers", "0", "-u", "0", "-p", socket_rtu_device.target)
    line = assert_one_error_line(res, 2)
    assert "unit 0 is broadcast in RTU framing, which only writes may use" in line
    res = run_cli("write-register", "3", "77", "-u", "0", "-p", socket_rtu_device.target)
    assert res.returncode == 0 and "broadcast: no device confirms" in res.stderr, str(res)


def test_unit_0_over_tcp_with_rtu_framing_stays_a_broadcast():
    res = run_cli("read-holding-registers", "0", "-u", "0", "-p", "tcp://127.0.0.1:1", "--framer", "rtu")
    assert "unit 0 is broadcast in RTU framing" in assert_one_error_line(res, 2)


class DelayProxy:
    """Forwards requests at once and every reply ``delay`` seconds after it came: a device
    (or a gateway and a slow bus) slower than mbtool's timeout."""

    def __init__(self, port: int, delay: float) -> None:
        self.delay = delay
        self.upstream = port
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.target = f"tcp://127.0.0.1:{self.listener.getsockname()[1]}"
        self.replies: list[float] = []
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self.listener.accept()
            except OSError:
                return
            server = socket.create_connection(("127.0.0.1", self.upstream))
            threading.Thread(target=self._pipe, args=(client, server, 0.0), daemon=True).start()
            threading.Thread(target=self._pipe, args=(server, client, self.delay), daemon=True).start()

    def _pipe(self, source: socket.socket, sink: socket.socket, delay: float) -> None:
        try:
            while data := source.recv(4096):
                if delay:
                    self.replies.append(time.monotonic())
                    threading.Timer(delay, self._send, (sink, data)).start()
                else:
                    sink.sendall(data)
        except OSError:
            pass

    @staticmethod
    def _send(sink: socket.socket, data: bytes) -> None:
        try:
            sink.sendall(data)
        except OSError:
            pass

    def close(self) -> None:
        self.listener.close()


def test_a_late_reply_to_an_earlier_attempt_answers_the_request(tcp_device):
    """Attempt 1 times out at 0.3 s, attempt 2 goes out, attempt 1's reply comes at 0.45 s:
    it answers the same request, so the read succeeds (pymodbus's reply, transaction id 1)."""
    proxy = DelayProxy(tcp_device.port, delay=0.45)
    try:
        res = run_cli(
            "read-holding-registers", "0", "2", "-p", proxy.target, "-t", "0.3", "--retries", "1", "--hex"
        )
    finally:
        proxy.close()
    assert res.returncode == 0, str(res)
    assert res.stdout.split() == ["0", str(HOLDING[0]), "1", str(HOLDING[1])]
    tx = [line for line in res.stderr.splitlines() if line.startswith("TX")]
    assert len(tx) == 2 and "tid 1 " in tx[0] and "tid 2 " in tx[1], res.stderr
    assert any(line.startswith("RX") and "tid 1 " in line for line in res.stderr.splitlines()), res.stderr


def test_a_reply_to_another_request_is_still_discarded(tcp_device):
    """Only the ids of this request's own attempts count: the first poll's reply, late,
    arrives while the second poll waits, and is discarded, not taken for the second's."""
    proxy = DelayProxy(tcp_device.port, delay=0.45)
    try:
        res = run_cli(
            "read-holding-registers",
            "0",
            "-p",
            proxy.target,
            "-t",
            "0.3",
            "--polls",
            "2",
            "--interval",
            "0.35",
        )
    finally:
        proxy.close()
    assert res.returncode == 5, str(res)
    assert "poll 2: reply has transaction id 1, expected 2, discarded" in res.stderr, str(res)
    assert "replies 0" in res.stderr, str(res)


# --- FC08 sub 04: silence is the answer asked for, an exception is a refusal (12.3) -------------


def test_force_listen_only_waits_for_a_refusal(libmodbus_server):
    """libmodbus's server has no FC08 and answers exception 01: exit 4, as everywhere."""
    res = run_cli("diag", "force-listen-only", "-p", libmodbus_server, "-t", "0.5")
    line = assert_one_error_line(res, 4)
    assert line == "mbtool: exception 01 Illegal Function to FC 08 (0x08)"


def test_force_listen_only_silence_is_the_expected_outcome(silent_server):
    res = run_mbtool("diag", "force-listen-only", "-p", silent_server.tcp_target, "-t", "0.4")
    assert res.returncode == 0, str(res)
    assert "none within 0.4 s, as expected: the device is now in listen-only mode" in res.stdout, str(res)
    assert res.elapsed >= 0.4


def test_a_device_that_answers_force_listen_only_is_reported(tcp_device):
    """pymodbus 3.16 answers 08 0004 and stays online: shown, with a warning, not an error."""
    res = run_cli("diag", "force-listen-only", "-p", tcp_device.target, "-t", "0.4")
    assert res.returncode == 0, str(res)
    assert "answered: 08 00 04" in res.stdout, str(res)
    assert res.stderr == (
        "mbtool: warning: the device answered force-listen-only, which the spec leaves unanswered:"
        " it may not be in listen-only mode\n"
    )


# --- --echo: what is not the echo is the reply; no echo on tcp:// (12.14) ----------------------


def test_echo_on_a_link_without_echo_shows_the_reply(socket_rtu_device):
    res = run_cli("read-holding-registers", "0", "-p", socket_rtu_device.target, "--echo", "--hex")
    assert res.returncode == 0, str(res)
    assert res.stdout.split() == ["0", str(HOLDING[0])]
    assert [line[:2] for line in res.stderr.splitlines()] == ["TX", "RX"], res.stderr


def test_echo_on_tcp_is_a_usage_error_and_nothing_is_sent(silent_server):
    res = run_cli("read-holding-registers", "0", "-p", silent_server.tcp_target, "--echo")
    line = assert_one_error_line(res, 2)
    assert line == "mbtool: --echo strips a half-duplex serial adapter's echo; a tcp:// link has none"
    assert silent_server.received_bytes() == b""


# --- float32 in every output format (12.11) ---------------------------------------------------


def test_float32_prints_as_written_in_every_format(tcp_device):
    import json

    target = ("-p", tcp_device.target)
    res = run_cli("write-registers", "500", "123.456", "-1.1", "--type", "float32", *target)
    assert res.returncode == 0, str(res)
    read = ("read-holding-registers", "500", "2", "--type", "float32", *target)
    assert run_cli(*read, "-o", "plain").stdout == "500 123.456\n502 -1.1\n"
    assert run_cli(*read, "-o", "csv").stdout.splitlines()[1:] == ["500,123.456", "502,-1.1"]
    text = run_cli(*read, "-o", "json").stdout
    assert json.loads(text)["values"] == [123.456, -1.1]
    assert '"values": [123.456, -1.1]' in text
    table = run_cli(*read, "-o", "table").stdout
    assert "123.456 " in table + " " and "123.4560012" not in table
    polled = run_cli(*read, "-o", "csv", "--polls", "1").stdout
    assert "500,123.456" in polled and "502,-1.1" in polled


# --- report-id says what the bytes say (12.8) ---------------------------------------------------


def test_report_id_never_calls_a_run_indicator_on_and_warns_otherwise(tcp_device):
    """pymodbus 3.16 sends its identity text first and FF last: the byte where the run
    indicator belongs is 'y' (79), which is neither ON nor OFF, and is shown so."""
    res = run_cli("report-id", "-p", tcp_device.target)
    assert res.returncode == 0, str(res)
    rows = dict(line.split(" ", 1) for line in res.stdout.splitlines())
    assert rows["run_indicator"] == "unknown (byte 79)"
    assert "the last byte is FF: the device may send the run indicator last" in rows["warning"]


def test_report_id_from_a_proper_device_is_on_without_warnings():
    res = run_cli("report-id", "-p", "sim://")
    assert res.returncode == 0 and "run_indicator ON\n" in res.stdout and "warning" not in res.stdout
