"""``mbtool bridge`` end to end: Modbus TCP clients (pymodbus's, mbpoll, mbtool's, raw sockets)
through the bridge to pymodbus's RTU and ASCII servers on pseudo-terminal pairs, and the
reverse (mbtool and pymodbus as masters on a pty, a TCP device behind), with the gateway's
exceptions 0A/0B, broadcasts, several clients at once, the display and bad input.

Every bridge here is a subprocess on a free loopback port (``--listen tcp://127.0.0.1:0``: its
start line on stderr says which), stopped with SIGTERM at the end of its test.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from types import SimpleNamespace

import pytest
from helpers.checks import assert_one_error_line, expect_ok, plain_pairs
from helpers.devices import start_device
from helpers.frames import crc16, mbap, read_mbap, rtu
from helpers.ptys import PTY_SERIAL_OPTS, PtyPair
from helpers.run import REPO_ROOT, first_line, mbtool_env, run_cli, run_mbtool, signals_as_from_a_shell
from helpers.served import Bridge, bridge, pymodbus_tcp, serve

pytestmark = pytest.mark.timeout(90)


@pytest.fixture(scope="module")
def rtu_bus():
    """pymodbus's RTU server for units 1 and 2 on a pty pair: the bus behind the bridge."""
    with start_device(tcp=False, framer="rtu") as device:
        yield device


@pytest.fixture(scope="module")
def shared_bus():
    """``mbtool serve -u 1,2`` on a pty pair: silent to other units' requests, as slaves on a
    shared bus are (pymodbus 3.16's server answers them exception 04), so a unit that is not
    there costs the bridge its timeout.  Its ``pty`` is the tap: what reached the bus."""
    pair = PtyPair()
    try:
        with serve("-u", "1,2", *PTY_SERIAL_OPTS, target=pair.device_path):
            yield SimpleNamespace(target=pair.mbtool_path, pty=pair)
    finally:
        pair.close()


# --- TCP clients to an RTU bus ---------------------------------------------------------------


def test_pymodbus_client_reads_and_writes_through_the_bridge(rtu_bus):
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS) as running:
        client = pymodbus_tcp(running, timeout=5.0)
        try:
            assert client.read_holding_registers(0, count=5, device_id=1).registers == [
                100,
                101,
                102,
                103,
                104,
            ]
            assert client.read_input_registers(0, count=2, device_id=2).registers == [200, 201]
            assert not client.write_registers(600, [11, 22, 33], device_id=1).isError()
            assert client.read_holding_registers(600, count=3, device_id=1).registers == [11, 22, 33]
            assert not client.write_coil(600, True, device_id=2).isError()
            assert client.read_coils(600, count=1, device_id=2).bits[0] is True
        finally:
            client.close()
        code, out, err = running.stop()
    records = [json.loads(line) for line in out.splitlines()]
    assert [r["outcome"] for r in records] == ["reply"] * 6
    assert [r["function"] for r in records] == [3, 4, 16, 3, 5, 1]
    first = records[0]
    assert first["client"].startswith("127.0.0.1:")
    assert first["forwarded"] == "01 03 00 00 00 05 85 C9"  # the request as it went on the bus
    assert first["received"].startswith("01 03 0A 00 64 00 65")
    assert first["reply"]["frame"].endswith("00 64 00 65 00 66 00 67 00 68")
    assert 0 < first["bus_ms"] <= first["total_ms"]
    assert "stopped: 6 transactions: 6 replies" in err


def test_mbpoll_reads_and_writes_through_the_bridge(rtu_bus):
    if shutil.which("mbpoll") is None:
        pytest.skip("mbpoll is not installed (Debian package mbpoll)")
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS) as running:
        # A pymodbus client polls the other unit all the while: two clients at once.
        alongside: list[object] = []

        def poll() -> None:
            client = pymodbus_tcp(running, timeout=5.0)
            try:
                alongside.extend(
                    client.read_input_registers(0, count=1, device_id=2).registers for _ in range(20)
                )
            finally:
                client.close()

        poller = threading.Thread(target=poll)
        poller.start()
        common = ["-m", "tcp", "-p", str(running.port), "-a", "1", "-0", "-1", "-o", "3"]
        done = subprocess.run(
            ["mbpoll", *common, "-r", "610", running.host, "4321", "8765"],
            capture_output=True,
            text=True,
            timeout=20,
        )
        assert done.returncode == 0, done.stdout + done.stderr
        done = subprocess.run(
            ["mbpoll", *common, "-r", "609", "-c", "4", running.host],
            capture_output=True,
            text=True,
            timeout=20,
        )
        assert done.returncode == 0, done.stdout + done.stderr
        values = dict(
            line.strip().strip("[").replace("]:", "").split()
            for line in done.stdout.splitlines()
            if line.strip().startswith("[")
        )
        assert values == {"609": "0", "610": "4321", "611": "8765", "612": "0"}
        poller.join(30)
        assert alongside == [[200]] * 20


def test_mbtool_reads_through_the_bridge_to_an_ascii_bus():
    with start_device(tcp=False, framer="ascii") as device:
        with bridge("-p", device.target, "--framer", "ascii", *PTY_SERIAL_OPTS) as running:
            res = expect_ok(
                run_cli("read-holding-registers", "3", "2", "-p", running.target, "-u", "2", "-t", "5")
            )
            assert plain_pairs(res) == [(3, "103"), (4, "104")]
            records = running.records()
    assert records[0]["forwarded"].startswith(":0203000300")  # the bus spoke ASCII
    assert records[0]["outcome"] == "reply"


def test_the_clients_transaction_id_comes_back_and_requests_in_one_burst_are_all_answered(rtu_bus):
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS) as running:
        with socket.create_connection((running.host, running.port), timeout=5) as sock:
            # Three requests in one send: each is forwarded in turn, each answered with its id.
            sock.sendall(
                mbap(0xBEEF, 1, bytes.fromhex("0300000001"))
                + mbap(0x0001, 2, bytes.fromhex("0400050002"))
                + mbap(0xFFFF, 1, bytes.fromhex("0300130001"))
            )
            replies = [read_mbap(sock) for _ in range(3)]
    assert replies == [
        (0xBEEF, 1, bytes.fromhex("03020064")),
        (0x0001, 2, bytes.fromhex("040400CD00CE")),
        (0xFFFF, 1, bytes.fromhex("03020077")),
    ]


def test_several_clients_at_once_are_each_answered_their_own_values(rtu_bus):
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS, "-q") as running:
        failures: list[str] = []

        def work(number: int) -> None:
            client = pymodbus_tcp(running, timeout=10)
            try:
                for poll in range(8):
                    address = (number * 3 + poll) % 18
                    unit = 1 + number % 2
                    first = 100 if unit == 1 else 100  # both units hold 100.. (conftest)
                    registers = client.read_holding_registers(address, count=2, device_id=unit).registers
                    if registers != [first + address, first + address + 1]:
                        failures.append(f"client {number} poll {poll}: {registers}")
            except Exception as error:  # reported below, with the others
                failures.append(f"client {number}: {error!r}")
            finally:
                client.close()

        workers = [threading.Thread(target=work, args=(n,)) for n in range(5)]
        for worker in workers:
            worker.start()
        for worker in workers:
            worker.join(60)
        assert failures == []
        _, _, err = running.stop()
    assert "stopped: 40 transactions: 40 replies" in err
    assert "5 connections" in err


def test_a_client_that_floods_cannot_hold_up_another(rtu_bus):
    """Clients take turns: a burst of 30 requests from one waits behind the other's one."""
    # --pause makes each transaction take 30 ms at least, as on a slow line.
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS, "--pause", "0.03") as running:
        flood = socket.create_connection((running.host, running.port), timeout=20)
        polite = socket.create_connection((running.host, running.port), timeout=20)
        try:
            flood.sendall(b"".join(mbap(n, 1, bytes.fromhex("0300000010")) for n in range(30)))
            time.sleep(0.1)  # the flood is on its way first
            polite.sendall(mbap(0x7777, 2, bytes.fromhex("0300000001")))
            assert read_mbap(polite) == (0x7777, 2, bytes.fromhex("03020064"))
            polite_done = time.monotonic()
            replies = [read_mbap(flood) for _ in range(30)]
            flood_done = time.monotonic()
        finally:
            flood.close()
            polite.close()
        assert [tid for tid, _, _ in replies] == list(range(30))
        records = running.records()
    # The polite client's request went on the bus among the first few, not after the 30.
    order = [r["client"] for r in records]
    polite_peer = next(r["client"] for r in records if r["unit"] == 2)
    assert order.index(polite_peer) <= 5
    assert flood_done - polite_done > 0.5  # the flood was still being worked through


def rtu_units(sent: bytes) -> list[int]:
    """The unit of each FC03 request (8 bytes with its CRC) in what the tap saw on the bus."""
    frames = [sent[at : at + 8] for at in range(0, len(sent), 8)]
    assert all(len(f) == 8 and f[1] == 0x03 and crc16(f[:6]) == f[6:] for f in frames), sent.hex(" ")
    return [f[0] for f in frames]


def test_requests_of_clients_that_have_gone_never_reach_the_bus(pty_pair):
    """Issue 29 item 3: each request of a client gone while it waited cost the full timeout."""
    with bridge("-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, "-t", "0.5", "-q") as running:
        for unit in range(10, 30):  # each its own unit: none is known to be silent yet
            with socket.create_connection((running.host, running.port), timeout=5) as gone:
                gone.sendall(mbap(unit, unit, bytes.fromhex("0300000001")))
        time.sleep(0.2)
        with socket.create_connection((running.host, running.port), timeout=30) as sock:
            started = time.monotonic()
            sock.sendall(mbap(1, 1, bytes.fromhex("0300000001")))
            assert read_mbap(sock) == (1, 1, bytes.fromhex("830B"))  # a silent line: 0B
            waited = time.monotonic() - started
        units = rtu_units(pty_pair.sent_by_mbtool())
    print(f"\nafter 20 gone clients the next waited {waited:.2f} s; on the bus: units {units}")
    assert units[-1] == 1 and len(units) <= 3, units  # at most the one on the bus as they left
    assert waited < 4 * 0.5, waited  # 20 gone clients were 10 s


def _poll_while(running, unit: int, flooding, seconds: float, warm_up: float = 0.3) -> list[float]:
    """A client's FC03 latencies, polling ``unit`` (serve's demo data) every 50 ms for
    ``seconds`` while ``flooding`` runs, from ``warm_up`` seconds after it started."""
    stop = threading.Event()
    threads = [threading.Thread(target=work, args=(stop,), daemon=True) for work in flooding]
    for thread in threads:
        thread.start()
    time.sleep(warm_up)
    latencies = []
    try:
        with socket.create_connection((running.host, running.port), timeout=30) as sock:
            end = time.monotonic() + seconds
            while time.monotonic() < end:
                started = time.monotonic()
                sock.sendall(mbap(7, unit, bytes.fromhex("0300000001")))
                assert read_mbap(sock) == (7, unit, bytes.fromhex("03020000"))
                latencies.append(time.monotonic() - started)
                time.sleep(0.05)
    finally:
        stop.set()
        for thread in threads:
            thread.join(10)
    return latencies


def _flooder(running, units, answers: list[bytes]):
    """A client that asks for each of ``units`` in turn, as fast as it is answered."""

    def work(stop: threading.Event) -> None:
        with socket.create_connection((running.host, running.port), timeout=30) as sock:
            tid = 0
            while not stop.is_set():
                sock.sendall(mbap(tid, units[tid % len(units)], bytes.fromhex("0300000001")))
                answers.append(read_mbap(sock)[2])
                tid += 1

    return work


def test_a_client_flooding_an_absent_unit_does_not_slow_the_others(shared_bus):
    """Issue 29 item 3: one client asking again and again for a unit that is not there made
    every other client wait the bridge's timeout (median 910 ms)."""
    with bridge("-p", shared_bus.target, *PTY_SERIAL_OPTS, "-t", "1", "-q") as running:
        shared_bus.pty.clear()
        answers: list[bytes] = []
        latencies = _poll_while(running, 1, [_flooder(running, [9], answers)], 4.0)
        units = rtu_units(shared_bus.pty.sent_by_mbtool())
    median = sorted(latencies)[len(latencies) // 2]
    print(f"\nwhile one client flooded unit 9: median {median * 1000:.0f} ms over {len(latencies)} reads")
    assert set(answers) == {bytes.fromhex("830B")} and len(answers) > 20
    assert units.count(9) <= 2, units  # tried once, then answered 0B at once (--silent-hold)
    assert median < 0.3, latencies


def test_silent_hold_0_tries_the_bus_every_time(pty_pair):
    with bridge("-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, "-t", "0.2", "--silent-hold", "0") as running:
        with socket.create_connection((running.host, running.port), timeout=5) as sock:
            for tid in range(3):
                sock.sendall(mbap(tid, 9, bytes.fromhex("0300000001")))
                assert read_mbap(sock) == (tid, 9, bytes.fromhex("830B"))
        assert rtu_units(pty_pair.sent_by_mbtool()) == [9, 9, 9]


def test_clients_share_the_bus_by_the_time_they_use(shared_bus):
    """Five connections that each cycle through absent units (each costs the bridge its
    timeout) cost a polling client one transaction at most, not one for each of them: the
    client that has used the least bus time goes next."""
    timeout = 0.5
    with bridge("-p", shared_bus.target, *PTY_SERIAL_OPTS, "-t", str(timeout), "-q") as running:
        answers: list[bytes] = []
        flooding = [_flooder(running, list(range(20 + 40 * n, 60 + 40 * n)), answers) for n in range(5)]
        # Once each flooder has used the bus, the newcomer is the one that has used the least.
        latencies = _poll_while(running, 1, flooding, 4.0, warm_up=6 * timeout)
    assert set(answers) == {bytes.fromhex("830B")}
    median = sorted(latencies)[len(latencies) // 2]
    worst = max(latencies)
    print(
        f"\nwhile 5 clients flooded absent units: median {median * 1000:.0f} ms, worst {worst * 1000:.0f} ms"
    )
    assert worst < 2 * timeout, latencies  # the one under way, then its turn (was 5)
    assert median < 1.5 * timeout, latencies


# --- what the gateway answers itself -------------------------------------------------------


def test_a_unit_that_does_not_answer_gets_exception_0B(pty_pair):
    # Nothing on the line: pymodbus's server answers units it does not have with exception 04.
    with bridge("-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, "-t", "0.3") as running:
        started = time.monotonic()
        res = run_mbtool("read-holding-registers", "0", "1", "-p", running.target, "-u", "9", "-t", "3")
        took = time.monotonic() - started
        records = running.records()
    assert_one_error_line(res, 4)
    assert "exception 0B Gateway Target Failed to Respond" in res.stderr
    assert took < 2.5  # the bridge's own timeout, not the client's
    assert records[0]["outcome"] == "no response"
    assert "no response from unit 9 within 0.3 s" in records[0]["why"]
    assert records[0]["received"] is None


def test_the_summary_on_exit_counts_each_units_transactions_by_outcome():
    """Per unit, what became of each request forwarded (issue 32), as every summary counts
    transactions: unit 1 answers, unit 2 refuses writes (02), unit 9 is not on the bus."""
    pair = PtyPair()
    try:
        with (
            serve("-u", "1,2", "--exception", "6:2", *PTY_SERIAL_OPTS, target=pair.device_path),
            bridge("-p", pair.mbtool_path, *PTY_SERIAL_OPTS, "-t", "0.3", "-q") as running,
        ):
            for _ in range(2):
                expect_ok(run_cli("read-holding-registers", "0", "-p", running.target, "-u", "1", "-t", "5"))
            run_cli("write-register", "0", "7", "-p", running.target, "-u", "2", "-t", "5")
            for _ in range(2):  # the second is answered 0B without the bus (--silent-hold)
                run_cli("read-holding-registers", "0", "-p", running.target, "-u", "9", "-t", "5")
            code, _, err = running.stop()
    finally:
        pair.close()
    assert code == 0, err
    units = {line.split(":", 1)[0]: line for line in err.splitlines() if line.startswith("unit ")}
    assert set(units) == {"unit 1", "unit 2", "unit 9"}, err
    assert units["unit 1"].startswith(
        "unit 1: transactions 2: answered 2, exception 0, timeout 0, corrupt 0, not ours 0, link lost 0, connection 0;"
    ), err
    assert "rtt min/avg/p95/max " in units["unit 1"]
    assert units["unit 2"].startswith("unit 2: transactions 1: answered 0, exception 1 (02:1), timeout 0,"), (
        err
    )
    assert units["unit 9"].startswith("unit 9: transactions 1: answered 0, exception 0, timeout 1,"), err
    assert units["unit 9"].endswith("rtt -"), err


def test_a_unit_not_forwarded_gets_exception_0A_and_nothing_goes_on_the_bus(rtu_bus):
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS, "--units", "2") as running:
        rtu_bus.pty.clear()
        res = run_cli("read-holding-registers", "0", "1", "-p", running.target, "-u", "1")
        assert rtu_bus.pty.sent_by_mbtool() == b""
        records = running.records()
    assert_one_error_line(res, 4)
    assert "exception 0A Gateway Path Unavailable" in res.stderr
    assert records[0]["outcome"] == "no path"
    assert records[0]["forwarded"] is None
    assert "unit 1 is not forwarded (--units)" in records[0]["why"]


def test_a_link_that_cannot_be_used_gets_exception_0A_and_is_opened_again():
    """TCP behind the bridge: the device goes away (0A), comes back (answered again)."""
    with start_device(tcp=True, framer="socket", units="1") as device:
        port = device.port
        with bridge("-p", device.target) as running:
            res = expect_ok(run_cli("read-holding-registers", "0", "1", "-p", running.target, "-t", "5"))
            assert plain_pairs(res) == [(0, "100")]
            device.proc.send_signal(signal.SIGTERM)
            device.proc.wait(10)
            res = run_cli("read-holding-registers", "0", "1", "-p", running.target, "-t", "5")
            assert_one_error_line(res, 4)
            assert "exception 0A Gateway Path Unavailable" in res.stderr
            with start_device(tcp=True, framer="socket", units="1", port=port) as again:
                assert again.port == port
                res = expect_ok(run_cli("read-holding-registers", "0", "1", "-p", running.target, "-t", "5"))
                assert plain_pairs(res) == [(0, "100")]
            records = running.records()
    assert [r["outcome"] for r in records] == ["reply", "no path", "reply"]
    assert "127.0.0.1" in records[1]["why"]


def test_a_broadcast_goes_on_the_bus_and_is_not_answered(rtu_bus):
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS, "--units", "0-2") as running:
        rtu_bus.pty.clear()
        with socket.create_connection((running.host, running.port), timeout=5) as sock:
            sock.sendall(mbap(5, 0, bytes.fromhex("06025A1234")))
            sock.settimeout(1.0)
            with pytest.raises(TimeoutError):
                sock.recv(100)
        sent = rtu_bus.pty.sent_by_mbtool()
        records = running.records()
    frame = bytes.fromhex("0006025A1234")
    assert sent == frame + crc16(frame)
    assert records[0]["outcome"] == "broadcast"
    assert records[0]["reply"] is None


# --- requests the gateway refuses itself (issue 29 item 2) -------------------------------------

# Requests a device would refuse, and the exception the bridge answers in its place: the
# codec's layout of each function code says what a whole request is (spec §3).
MALFORMED = [
    ("03 0000 0001 FFFF", "83 03"),  # FC03 with 2 bytes past its layout
    ("03 00", "83 03"),  # a PDU of 2 bytes
    ("03" + " 00" * 252, "83 03"),  # a 253-byte FC03
    ("10 0000 0002 04 0001", "90 03"),  # byte count 4, 2 bytes of data
    ("10 0000 0002 02 0001 0002", "90 03"),  # byte count 2, 4 bytes of data
    ("14 0E 06 0004 0001 0002", "94 03"),  # byte count 14, one 7-byte group
    ("03 0000 007E", "83 03"),  # 126 registers: past the spec's 125
    ("00", "80 01"),  # no function has code 00
    ("83 02", "83 01"),  # an exception response sent as a request
    ("41 0102", "C1 01"),  # a function code the codec does not know (no --raw-functions)
    ("2B 0D 01 00", "AB 01"),  # FC43 with an MEI type other than 0E
]


def test_malformed_requests_are_answered_by_the_bridge_and_never_reach_the_bus(rtu_bus):
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS) as running:
        rtu_bus.pty.clear()
        with socket.create_connection((running.host, running.port), timeout=5) as sock:
            for tid, (pdu, reply) in enumerate(MALFORMED):
                sock.sendall(mbap(tid, 1, bytes.fromhex(pdu)))
                assert read_mbap(sock) == (tid, 1, bytes.fromhex(reply)), pdu
            assert rtu_bus.pty.sent_by_mbtool() == b""  # the tap: nothing went on the bus
            # The bus is there: a whole request is forwarded and answered.
            sock.sendall(mbap(99, 1, bytes.fromhex("0300000001")))
            assert read_mbap(sock) == (99, 1, bytes.fromhex("03020064"))
        assert rtu_bus.pty.sent_by_mbtool() == rtu(bytes.fromhex("010300000001"))
        records = running.records()
    assert [r["outcome"] for r in records] == ["invalid"] * len(MALFORMED) + ["reply"]
    assert all(r["forwarded"] is None for r in records[:-1])
    assert "not forwarded" in records[0]["why"]


def test_unknown_function_codes_are_forwarded_only_with_raw_functions(pty_pair):
    # A silent line (nothing on it knows FC 41): the tap shows what was sent, 0B comes back.
    with bridge("-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, "--raw-functions", "-t", "0.3") as running:
        with socket.create_connection((running.host, running.port), timeout=5) as sock:
            sock.sendall(mbap(1, 1, bytes.fromhex("41 0102")))
            assert read_mbap(sock) == (1, 1, bytes.fromhex("C10B"))
            for tid, pdu in ((2, "00"), (3, "83 02"), (4, "03 00")):  # never forwarded
                sock.sendall(mbap(tid, 1, bytes.fromhex(pdu)))
                assert read_mbap(sock)[0] == tid
        assert pty_pair.sent_by_mbtool() == rtu(bytes.fromhex("01410102"))


def test_broadcasts_obey_units_and_only_writes_are_broadcast(rtu_bus):
    write, read = bytes.fromhex("06025A1234"), bytes.fromhex("0300000001")
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS) as running:  # --units 1-247: no 0
        rtu_bus.pty.clear()
        with socket.create_connection((running.host, running.port), timeout=5) as sock:
            sock.sendall(mbap(1, 0, write))
            assert read_mbap(sock) == (1, 0, bytes.fromhex("860A"))
        assert rtu_bus.pty.sent_by_mbtool() == b""
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS, "--units", "0-247") as running:
        rtu_bus.pty.clear()
        with socket.create_connection((running.host, running.port), timeout=5) as sock:
            sock.sendall(mbap(2, 0, read))  # a read of every unit: nobody could answer it
            assert read_mbap(sock) == (2, 0, bytes.fromhex("8301"))
            sock.sendall(mbap(3, 0, bytes.fromhex("41")))
            assert read_mbap(sock) == (3, 0, bytes.fromhex("C101"))
        assert rtu_bus.pty.sent_by_mbtool() == b""
        records = running.records()
    assert [r["outcome"] for r in records] == ["invalid", "invalid"]
    assert "only writes are broadcast" in records[0]["why"]


# --- the display -------------------------------------------------------------------------------


def test_plain_lines_show_each_transaction_decoded_with_its_times(rtu_bus):
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS, fmt="plain") as running:
        expect_ok(run_cli("read-holding-registers", "0", "2", "-p", running.target, "-t", "5"))
        code, out, err = running.stop()
    lines = [line for line in out.splitlines() if " > " in line or " < " in line]
    assert "> unit 1 FC 03 (0x03) Read Holding Registers: starting_address=0 quantity=2" in lines[0]
    assert (
        "< unit 1 FC 03 (0x03) Read Holding Registers: byte_count=4 register[0]=100 register[1]=101"
        in lines[1]
    )
    assert " | bus " in lines[1] and " ms, total " in lines[1]
    assert any(line.endswith("connected") for line in out.splitlines())
    assert code == 0
    assert "1 transaction: 1 reply" in err


def test_hex_shows_every_frame_on_both_sides_with_checksums(rtu_bus):
    with bridge("-p", rtu_bus.target, *PTY_SERIAL_OPTS, "--hex", fmt="plain") as running:
        with socket.create_connection((running.host, running.port), timeout=5) as sock:
            sock.sendall(mbap(0x1234, 1, bytes.fromhex("0300010001")))
            read_mbap(sock)
        _, out, _ = running.stop()
    lines = [line.split(" ", 1)[1] for line in out.splitlines() if " RX " in line or " TX " in line]
    assert lines[0].endswith("RX 12 34 00 00 00 06 01 03 00 01 00 01  MBAP tid 4660 length 6 ok")
    assert lines[1] == "link TX 01 03 00 01 00 01 D5 CA  CRC D5 CA ok"
    crc = crc16(bytes.fromhex("0103020065")).hex(" ").upper()
    assert lines[2] == f"link RX 01 03 02 00 65 {crc}  CRC {crc} ok"
    assert "TX 12 34 00 00 00 05 01 03 02 00 65  MBAP tid 4660 length 5 ok | bus " in lines[3]


def _rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:"))


@pytest.mark.long  # 3,000 transactions of 1 KB: 8 s alone, 15-30 s on a busy machine (tests/conftest.py)
def test_a_display_nobody_reads_never_holds_the_bus_nor_grows():
    """Issue 29 item 4: with its stdout not read, the bridge kept every transaction it could not
    print (18.9 MB -> 52 MB and rising).  The bus never waits for the display: past a backlog
    lines are dropped, and counted where the display catches up."""
    argv = [
        sys.executable,
        "-m",
        "mbtool",
        "bridge",
        "--listen",
        "tcp://127.0.0.1:0",
        "-p",
        "sim://",
        "-o",
        "plain",
    ]
    proc = subprocess.Popen(
        argv,
        cwd=REPO_ROOT,
        env=mbtool_env(),
        preexec_fn=signals_as_from_a_shell,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,  # read by nobody until the end
        stderr=subprocess.PIPE,
    )
    try:
        running = Bridge(proc, first_line(proc, "bridging ", proc.stderr), os.devnull)
        # FC23 with 121 registers written and 125 read: about 1 KB of frames a transaction.
        pdu = bytes.fromhex("17 0000 007D 0000 0079 F2") + bytes(242)
        count = 3000  # unbounded, the lines kept would be ~13 MB (4.5 KB a transaction): far past 5 MB
        with socket.create_connection((running.host, running.port), timeout=10) as sock:
            for first in range(0, 100):  # the sim device's first request: allocations that stay
                sock.sendall(mbap(first, 1, pdu))
                read_mbap(sock)
            before = _rss_kb(proc.pid)
            started = time.monotonic()
            for first in range(0, count, 10):
                sock.sendall(b"".join(mbap(tid, 1, pdu) for tid in range(first, first + 10)))
                assert [read_mbap(sock)[0] for _ in range(10)] == list(range(first, first + 10))
            took = time.monotonic() - started
            after = _rss_kb(proc.pid)
        print(f"\n{count} transactions in {took:.1f} s with stdout unread: RSS {before} kB -> {after} kB")
        assert after - before < 5 * 1024, (before, after)
        # Now the display is read: it catches up and says how much it did not show.
        out = b""
        end = time.monotonic() + 20
        while b"not shown: the display fell behind" not in out and time.monotonic() < end:
            ready, _, _ = select.select([proc.stdout], [], [], 0.1)
            if ready:
                out += os.read(proc.stdout.fileno(), 65536)
        proc.send_signal(signal.SIGTERM)
        rest, err = proc.communicate(timeout=15)
        out += rest
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=5)
    text = out.decode()
    assert proc.returncode == 0, err
    shown = sum(" < unit 1 " in line for line in text.splitlines())  # the replies shown
    not_shown = [line for line in text.splitlines() if "not shown: the display fell behind" in line]
    dropped = sum(int(line.split()[1]) for line in not_shown)
    assert not_shown and dropped > count // 2, not_shown
    assert shown + dropped >= count + 100 - 5  # every transaction is shown or counted (+ events)
    assert f"{dropped} not shown (the display fell behind)" in err.decode(), err


class Stuck:
    """A stdout whose reader is away until ``back`` is set."""

    def __init__(self) -> None:
        self.back = threading.Event()
        self.text = ""

    def write(self, text: str) -> None:
        self.back.wait(10)
        self.text += text

    def flush(self) -> None:
        pass


def fall_behind(monkeypatch, transactions: int):
    """A JSON display on a stdout nobody reads, handed ``transactions`` replies: (its Show, the
    stdout)."""
    from mbtool.cli.commands import bridge as command
    from mbtool.link.forward import REPLY, Passage

    stuck = Stuck()
    monkeypatch.setattr(sys, "stdout", stuck)
    request, reply = mbap(1, 1, bytes.fromhex("0300000001")), mbap(1, 1, bytes.fromhex("03020064"))
    passage = Passage(0.0, "peer", 1, 3, request, "tcp", b"", "rtu", b"", reply, REPLY, "", 0.001, 0.002)
    show = command.Show("json", False, False)
    for _ in range(transactions):
        show.passage(passage)
    return show, stuck


def test_json_says_how_many_transactions_it_did_not_show(monkeypatch):
    """The count of the lines dropped is a JSON object of its own, in its place."""
    from mbtool.cli.commands.bridge import DISPLAY_BACKLOG

    total = DISPLAY_BACKLOG + 500
    show, stuck = fall_behind(monkeypatch, total)
    stuck.back.set()
    show.close()
    records = [json.loads(line) for line in stuck.text.splitlines()]
    counts = [r["not_shown"] for r in records if "not_shown" in r]
    assert len(counts) == 1 and counts[0] == show.not_shown >= 499
    assert len(records) - 1 + counts[0] == total
    assert records[-1] == {
        "time": records[-1]["time"],
        "not_shown": counts[0],
        "why": "the display fell behind",
    }


def test_a_display_that_caught_up_says_at_once_what_it_did_not_show(monkeypatch):
    """Where the traffic stops after the lines dropped, the display says how many once it has
    caught up, not with a next transaction that may never come, nor only at the end."""
    from mbtool.cli.commands.bridge import DISPLAY_BACKLOG

    total = DISPLAY_BACKLOG + 500
    show, stuck = fall_behind(monkeypatch, total)
    stuck.back.set()
    end = time.monotonic() + 5
    while '"not_shown"' not in stuck.text and time.monotonic() < end:
        time.sleep(0.01)
    records = [json.loads(line) for line in stuck.text.splitlines()]
    show.close()
    assert records[-1]["not_shown"] == show.not_shown >= 499, records[-1]
    assert len(records) - 1 + show.not_shown == total


# --- the reverse: a slave on a serial line, a TCP device behind --------------------------------


@pytest.fixture(scope="module")
def tcp_behind():
    with start_device(tcp=True, framer="socket", units="1,2") as device:
        yield device


def test_reverse_mbtool_as_master_on_the_serial_side(tcp_behind):
    pty = PtyPair()
    try:
        with bridge(
            "-p", tcp_behind.target, "--framer", "rtu", "--units", "1,2", listen=pty.device_path
        ) as running:
            serial = (*PTY_SERIAL_OPTS, "-p", pty.mbtool_path)
            res = expect_ok(run_cli("read-holding-registers", "2", "3", *serial, "-u", "2", "-t", "5"))
            assert plain_pairs(res) == [(2, "102"), (3, "103"), (4, "104")]
            expect_ok(run_cli("write-registers", "620", "5", "6", *serial, "-t", "5"))
            res = expect_ok(run_cli("read-holding-registers", "620", "2", *serial, "--hex", "-t", "5"))
            assert plain_pairs(res) == [(620, "5"), (621, "6")]
            assert "CRC" in res.stderr and " ok" in res.stderr  # RTU on the serial side
            # A unit not forwarded is another slave's: no answer at all, not an exception.
            res = run_cli("read-holding-registers", "0", "1", *serial, "-u", "3", "-t", "0.5")
            assert_one_error_line(res, 3)
            records = running.records()
    finally:
        pty.close()
    assert [r["outcome"] for r in records] == ["reply", "reply", "reply", "no path"]
    assert records[0]["client"] == pty.device_path
    assert records[0]["forwarded"].startswith("00 01 00 00 00 06 02 03 00 02 00 03")  # MBAP behind


def test_reverse_pymodbus_serial_client_and_a_device_gone_answers_0A(tcp_behind):
    from pymodbus.client import ModbusSerialClient

    pty = PtyPair()
    try:
        with start_device(tcp=True, framer="socket", units="1") as gone:
            target = gone.target
        with bridge("-p", tcp_behind.target, listen=pty.device_path):
            client = ModbusSerialClient(pty.mbtool_path, baudrate=19200, parity="N", timeout=3, retries=0)
            assert client.connect()
            try:
                assert client.read_input_registers(1, count=2, device_id=1).registers == [201, 202]
            finally:
                client.close()
        # The TCP device stopped before the bridge started: the bridge says so and exits 6.
        res = run_mbtool("bridge", "--listen", pty.device_path, "-p", target, timeout=20)
        assert_one_error_line(res, 6)
    finally:
        pty.close()


def test_reverse_the_link_lost_after_start_answers_0A_on_the_serial_line():
    pty = PtyPair()
    try:
        with start_device(tcp=True, framer="socket", units="1") as device:
            with bridge("-p", device.target, listen=pty.device_path) as running:
                serial = (*PTY_SERIAL_OPTS, "-p", pty.mbtool_path)
                expect_ok(run_cli("read-holding-registers", "0", "1", *serial, "-t", "5"))
                device.proc.send_signal(signal.SIGTERM)
                device.proc.wait(10)
                res = run_cli("read-holding-registers", "0", "1", *serial, "-t", "5")
                assert_one_error_line(res, 4)
                assert "exception 0A Gateway Path Unavailable" in res.stderr
                assert [r["outcome"] for r in running.records()] == ["reply", "no path"]
    finally:
        pty.close()


def test_reverse_a_malformed_request_on_the_serial_line_is_answered_there(tcp_behind):
    pty = PtyPair()
    try:
        with bridge("-p", tcp_behind.target, "--units", "1,2", listen=pty.device_path) as running:
            fd = os.open(pty.mbtool_path, os.O_RDWR | os.O_NOCTTY)
            try:
                os.write(fd, rtu(bytes.fromhex("01 10 0000 0002 04 0001")))  # 2 bytes short
                reply = b""
                end = time.monotonic() + 5
                while len(reply) < 5 and time.monotonic() < end:
                    ready, _, _ = select.select([fd], [], [], 0.1)
                    if ready:
                        reply += os.read(fd, 100)
            finally:
                os.close(fd)
            records = running.records()
    finally:
        pty.close()
    assert reply == rtu(bytes.fromhex("01 90 03"))
    assert [r["outcome"] for r in records] == ["invalid"]
    assert records[0]["forwarded"] is None


# --- bad input ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "args, says",
    [
        (["--listen", "tcp://127.0.0.1:0"], "Missing option '-p'"),
        (["-p", "sim://", "--listen", "sim://"], "in-process device"),
        (["-p", "tcp://127.0.0.1:5", "--framer", "rtu"], "both sides are tcp://"),
        (["-p", "sim://", "--units", "300"], "300"),
        (["-p", "/dev/ttyS0", "--listen", "/dev/ttyS0"], "a bridge joins two links"),
        (["-p", "sim://", "--listen", "tcp://127.0.0.1:99999"], "99999"),
        (["-p", "sim://", "--bytesize", "7"], "8 data bits"),
        (["-p", "tcp://127.0.0.1:5", "--rs485"], "neither side is one"),
    ],
)
def test_bad_arguments_are_one_line_and_exit_2(args, says):
    res = run_cli("bridge", *args)
    line = assert_one_error_line(res, 2)
    assert says in line


def test_a_serial_port_that_does_not_exist_is_exit_6_before_listening():
    res = run_cli("bridge", "-p", "/dev/ttyNOSUCH0", "--listen", "tcp://127.0.0.1:0")
    line = assert_one_error_line(res, 6)
    assert "/dev/ttyNOSUCH0" in line
