"""``mbtool serve -p udp://`` and ``-p rtu+udp://``: a datagram a request, its reply a datagram
back; pymodbus's UDP client against it, directly and through a loopback proxy that loses and
reorders datagrams, raw datagrams for what pymodbus never sends (issue 33).
"""

from __future__ import annotations

import socket
import struct

import pytest
from helpers.checks import assert_one_error_line, expect_ok, plain_pairs, wait_until
from helpers.frames import crc16
from helpers.run import run_cli
from helpers.served import serve
from peers.lossy_udp import LossyUdpProxy

pytestmark = pytest.mark.timeout(120)

FRAMINGS = {"udp": "socket", "rtu+udp": "rtu"}


def pymodbus_client(port: int, scheme: str, retries: int = 0, timeout: float = 2.0):
    from pymodbus import FramerType
    from pymodbus.client import ModbusUdpClient

    framer = FramerType.SOCKET if scheme == "udp" else FramerType.RTU
    client = ModbusUdpClient("127.0.0.1", port=port, framer=framer, timeout=timeout, retries=retries)
    assert client.connect()
    return client


@pytest.mark.parametrize("scheme", FRAMINGS)
def test_pymodbus_udp_client_reads_and_writes(tmp_path, scheme):
    with serve("-u", "1,2", target=f"{scheme}://127.0.0.1:0") as server:
        assert server.first_line == f"serving {scheme}://127.0.0.1:{server.port} units 1-2 framer " + (
            "tcp" if scheme == "udp" else "rtu"
        )
        client = pymodbus_client(server.port, scheme)
        try:
            assert not client.write_registers(20, [5, 6], device_id=2).isError()
            assert client.read_holding_registers(20, count=2, device_id=2).registers == [5, 6]
            assert client.read_coils(0, count=3, device_id=1).bits[:3] == [True, False, True]
        finally:
            client.close()


@pytest.mark.parametrize("scheme", FRAMINGS)
def test_pymodbus_through_a_lossy_path_recovers_with_retries_and_nothing_is_mismatched(tmp_path, scheme):
    """Requests for two units in turn, through a proxy that drops every fifth datagram each
    way and swaps or delays every seventh: pymodbus's retries recover each, and each reply is
    its own request's (unit 1 holds 0..4 at 0, unit 2 10..12 at 10)."""
    with serve("-u", "1,2", target=f"{scheme}://127.0.0.1:0") as server:
        proxy = LossyUdpProxy(server.port)
        client = pymodbus_client(proxy.port, scheme, retries=10, timeout=0.3)
        try:
            for turn in range(20):  # every fifth datagram each way dropped, every seventh swapped or late
                unit, address, count = (1, 0, 5) if turn % 2 == 0 else (2, 10, 3)
                reply = client.read_holding_registers(address, count=count, device_id=unit)
                assert not reply.isError(), (turn, reply)
                assert reply.registers == list(range(address, address + count)), (turn, reply)
        finally:
            client.close()
            proxy.close()
        assert sum(proxy.dropped.values()) > 0
        assert sum(proxy.swapped.values()) + sum(proxy.late.values()) > 0


@pytest.mark.parametrize("scheme", FRAMINGS)
def test_mbtool_reads_its_own_udp_server(tmp_path, scheme):
    with serve(target=f"{scheme}://127.0.0.1:0") as server:
        res = expect_ok(run_cli("read-holding-registers", "0", "3", "-p", server.target))
        assert plain_pairs(res) == [(0, "0"), (1, "1"), (2, "2")]


def test_a_datagram_that_is_no_frame_is_logged_and_dropped_and_the_next_is_answered(tmp_path):
    with serve(quiet=False, target="rtu+udp://127.0.0.1:0") as server:
        peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        peer.settimeout(3)
        try:
            request = bytes.fromhex("01 03 0000 0001")
            peer.sendto(request[:4], (server.host, server.port))  # half a frame: its datagram ends it
            peer.sendto(request + crc16(request), (server.host, server.port))
            reply, _ = peer.recvfrom(512)
        finally:
            peer.close()
        assert reply == bytes.fromhex("01 03 02 0000") + crc16(bytes.fromhex("01 03 02 0000"))
        assert wait_until(lambda: " RX 01 03 00 00 00 01 84 0A" in server.log(), 5), server.log()
        bad = [line for line in server.log().splitlines() if " bad " in line]
        assert len(bad) == 1 and " bad 01 03 00 00 truncated frame (4 of 8 bytes)" in bad[0], server.log()


def test_mbap_in_datagrams_answers_each_with_its_transaction_id(tmp_path):
    with serve(target="udp://127.0.0.1:0") as server:
        peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        peer.settimeout(3)
        try:
            for tid in (7, 0xBEEF):
                peer.sendto(
                    struct.pack(">HHHB", tid, 0, 6, 1) + bytes.fromhex("03 0001 0001"),
                    (server.host, server.port),
                )
            replies = {peer.recvfrom(512)[0] for _ in range(2)}
        finally:
            peer.close()
        assert replies == {
            struct.pack(">HHHB", tid, 0, 5, 1) + bytes.fromhex("03 02 0001") for tid in (7, 0xBEEF)
        }


def test_faults_of_tcp_clients_do_not_apply_to_datagrams():
    res = run_cli("serve", "-p", "udp://127.0.0.1:0", "--settle", "1")
    line = assert_one_error_line(res, 2)
    assert "are faults of TCP clients" in line
    res = run_cli("serve", "-p", "rtu+udp://127.0.0.1:0", "--framer", "tcp")
    line = assert_one_error_line(res, 2)
    assert line == (
        "mbtool: --framer tcp (MBAP) needs a tcp://, tls:// or udp:// target; rtu+udp://127.0.0.1:0 takes rtu or ascii"
    )
