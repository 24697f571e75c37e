"""``mbtool bridge`` with TLS and UDP on either side (issue 33): a Modbus/TCP Security front on a
serial bus or a plain TCP device, with its clients' roles and the write-role rule; a plain
Modbus TCP side in front of a TLS device; datagrams in and out.  The peers are pymodbus's
clients and servers; the buses are pymodbus's RTU server on a pseudo-terminal pair, whose
tap shows what reached the bus.
"""

from __future__ import annotations

import ssl

import pytest
from helpers.checks import assert_one_error_line, expect_ok, plain_pairs
from helpers.devices import HOLDING, start_device
from helpers.run import run_cli
from helpers.served import bridge

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module")
def rtu_bus():
    with start_device(tcp=False, framer="rtu", units="1,2") as device:
        yield device


def tls_args(pki, *more: str) -> list[str]:
    return ["--cert", str(pki.server.cert), "--key", str(pki.server.key), "--ca", str(pki.ca.cert), *more]


def identity(pki, who: str) -> list[str]:
    pair = getattr(pki, who)
    return ["--cert", str(pair.cert), "--key", str(pair.key), "--ca", str(pki.ca.cert)]


def pymodbus_tls_client(running, pki, who: str):
    from pymodbus.client import ModbusTlsClient

    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False  # pymodbus's sync client wraps without a server name
    context.load_verify_locations(pki.ca.cert)
    pair = getattr(pki, who)
    context.load_cert_chain(pair.cert, pair.key)
    client = ModbusTlsClient(running.host, port=running.port, sslctx=context, timeout=5, retries=0)
    assert client.connect()
    return client


def test_pymodbus_tls_client_through_the_bridge_to_an_rtu_bus(rtu_bus, pki):
    with bridge("-p", rtu_bus.target, "--parity", "N", *tls_args(pki), listen="tls://127.0.0.1:0") as running:
        assert running.first_line.startswith("bridging tls://127.0.0.1:")
        client = pymodbus_tls_client(running, pki, "operator")
        try:
            assert client.read_holding_registers(0, count=4, device_id=2).registers == HOLDING[:4]
            assert not client.write_register(50, 1234, device_id=1).isError()
            assert client.read_holding_registers(50, count=1, device_id=1).registers == [1234]
        finally:
            client.close()
        records = running.records()
    assert [r["outcome"] for r in records] == ["reply", "reply", "reply"]


def test_writes_from_a_role_that_may_not_write_get_01_and_never_reach_the_bus(rtu_bus, pki):
    with bridge(
        "-p", rtu_bus.target, "--parity", "N", *tls_args(pki, "--write-roles", "operator"),
        listen="tls://127.0.0.1:0", fmt="plain",
    ) as running:  # fmt: skip
        rtu_bus.pty.clear()
        client = pymodbus_tls_client(running, pki, "viewer")
        try:
            reply = client.write_register(60, 1, device_id=1)
            assert reply.isError() and reply.exception_code == 1
            assert rtu_bus.pty.sent_by_mbtool() == b""  # nothing went on the bus
            assert client.read_holding_registers(0, count=1, device_id=1).registers == HOLDING[:1]
        finally:
            client.close()
        _, out, _ = running.stop()
    assert "write refused: role viewer may not write (exception 01)" in out


def test_a_tls_front_on_a_plain_tcp_device(tcp_device, pki):
    with bridge("-p", tcp_device.target, *tls_args(pki), listen="tls://127.0.0.1:0") as running:
        res = expect_ok(
            run_cli(
                "read-holding-registers",
                "0",
                "3",
                "-u",
                "2",
                "-p",
                running.listening,
                *identity(pki, "viewer"),
            )
        )
        assert plain_pairs(res) == [(i, str(v)) for i, v in enumerate(HOLDING[:3])]
        res = run_cli("read-holding-registers", "0", "-p", running.listening, "--ca", str(pki.ca.cert))
        assert_one_error_line(res, 6)  # no client certificate: refused before any request


def test_a_plain_tcp_front_on_a_tls_device(pki):
    server = pki.server
    with start_device(
        tcp=True, framer="socket", units="1",
        tls=("--cert", str(server.cert), "--key", str(server.key), "--ca", str(pki.ca.cert)),
    ) as device:  # fmt: skip
        with bridge("-p", device.target, *identity(pki, "operator")) as running:
            res = expect_ok(run_cli("read-holding-registers", "0", "3", "-p", running.target))
            assert plain_pairs(res) == [(i, str(v)) for i, v in enumerate(HOLDING[:3])]


@pytest.mark.parametrize("scheme", ["udp", "rtu+udp"])
def test_pymodbus_udp_client_through_the_bridge_to_an_rtu_bus(rtu_bus, scheme):
    from pymodbus import FramerType
    from pymodbus.client import ModbusUdpClient

    with bridge("-p", rtu_bus.target, "--parity", "N", listen=f"{scheme}://127.0.0.1:0") as running:
        assert running.first_line.startswith(f"bridging {scheme}://127.0.0.1:")
        framer = FramerType.SOCKET if scheme == "udp" else FramerType.RTU
        client = ModbusUdpClient(running.host, port=running.port, framer=framer, timeout=5, retries=0)
        assert client.connect()
        try:
            assert client.read_holding_registers(0, count=4, device_id=1).registers == HOLDING[:4]
        finally:
            client.close()
        _, _, err = running.stop()
    assert "connections" not in err.splitlines()[-1]


@pytest.mark.parametrize("framer", ["socket", "rtu"])
def test_a_tcp_front_on_a_udp_device(framer):
    with start_device(tcp=False, udp=True, framer=framer, units="1") as device:
        with bridge("-p", device.target) as running:
            res = expect_ok(run_cli("read-holding-registers", "0", "3", "-p", running.target))
            assert plain_pairs(res) == [(i, str(v)) for i, v in enumerate(HOLDING[:3])]


def test_tls_options_on_a_bridge_without_tls_are_exit_2(rtu_bus, pki):
    res = run_cli("bridge", "-p", rtu_bus.target, "--ca", str(pki.ca.cert))
    line = assert_one_error_line(res, 2)
    assert line == "mbtool: --ca is for tls:// (Modbus/TCP Security), and neither side is tls://"
    res = run_cli("bridge", "-p", rtu_bus.target, "--write-roles", "operator")
    line = assert_one_error_line(res, 2)
    assert line.startswith("mbtool: --write-roles is for a tls:// server")
