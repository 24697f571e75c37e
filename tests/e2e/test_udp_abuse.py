"""``serve`` and ``bridge`` on ``udp://`` and ``rtu+udp://`` under datagram abuse (issue 40.6).

A datagram carries one ADU (the spec's UDP mapping): one spoofed datagram packed with thousands of
reads got thousands of replies, 21.6 times its bytes (31.9 on rtu+udp), and on ``bridge`` held
every other master up behind it, SIGTERM too.  Now the datagram's first ADU is answered and what
follows it is dropped and counted; ``--udp-rate`` caps the datagrams answered a second for one
source address.  The peers are raw UDP sockets, the only way to send what no Modbus client sends.
"""

from __future__ import annotations

import contextlib
import socket
import struct
import time

import pytest
from helpers.checks import assert_one_error_line
from helpers.frames import crc16
from helpers.run import run_cli
from helpers.served import bridge, serve

pytestmark = pytest.mark.timeout(120)

BIGGEST_READ = bytes.fromhex("03 0000 007D")  # FC 03, 125 registers: the largest reply a read gets
LONE_READ = bytes.fromhex("03 0000 0001")
PACKED = 400  # ADUs in one datagram (the had 5,000: the effect is the same, the run shorter)


def adu(scheme: str, tid: int, pdu: bytes) -> bytes:
    if scheme == "udp":
        return struct.pack(">HHHB", tid, 0, len(pdu) + 1, 1) + pdu
    frame = bytes([1]) + pdu
    return frame + crc16(frame)


def lone_reply(scheme: str, reply: bytes) -> bool:
    """Is this the reply to LONE_READ (byte count 2), not to a BIGGEST_READ (250)?"""
    pdu = reply[7:] if scheme == "udp" else reply[1:-2]
    return pdu[:2] == bytes([0x03, 0x02])


@contextlib.contextmanager
def peer(host: str = "127.0.0.1"):
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    sock.settimeout(3)
    with sock:
        yield sock


def replies_until_lone(sock: socket.socket, scheme: str, deadline: float = 3.0) -> tuple[list[bytes], bool]:
    """The datagrams that came back before the lone read's reply, and whether it came."""
    got: list[bytes] = []
    end = time.monotonic() + deadline
    while time.monotonic() < end:
        sock.settimeout(max(0.01, end - time.monotonic()))
        try:
            data, _ = sock.recvfrom(65536)
        except TimeoutError:
            break
        if lone_reply(scheme, data):
            return got, True
        got.append(data)
    return got, False


@contextlib.contextmanager
def listening(kind: str, scheme: str, *more: str):
    """(host, port, stop) of ``serve`` or ``bridge -p sim://`` on ``scheme``; stop() gives the
    summary on stderr (bridge) or the stopped line (serve)."""
    where = f"{scheme}://127.0.0.1:0"
    if kind == "serve":
        with serve(*more, target=where, quiet=False) as server:
            yield server.host, server.port, lambda: server.stop()[1]
    else:
        with bridge("-p", "sim://", "-q", *more, listen=where) as running:
            yield running.host, running.port, lambda: running.stop()[2]


@pytest.mark.parametrize("scheme", ["udp", "rtu+udp"])
@pytest.mark.parametrize("kind", ["serve", "bridge"])
def test_a_datagram_packed_with_reads_gets_one_reply_no_bigger_than_itself(kind, scheme):
    with listening(kind, scheme) as (host, port, stop), peer() as sock:
        packed = b"".join(adu(scheme, tid, BIGGEST_READ) for tid in range(1, PACKED + 1))
        sock.sendto(packed, (host, port))
        sock.sendto(adu(scheme, 0xFFFF, LONE_READ), (host, port))
        replies, answered = replies_until_lone(sock, scheme)
        assert answered, "a lone read after the packed datagram still gets its reply"
        assert len(replies) <= 1, f"{len(replies)} replies to one datagram"
        assert sum(map(len, replies)) <= len(packed)  # no amplification
        summary = stop()
    assert (
        f"1 datagram held more than one ADU: {len(packed) - len(adu(scheme, 1, BIGGEST_READ))} bytes dropped"
        in summary
    )


def test_a_datagram_that_starts_with_no_frame_gets_no_reply_whatever_follows():
    with serve(target="rtu+udp://127.0.0.1:0") as server, peer() as sock:
        garbage_then_reads = b"\x00\xff" + b"".join(adu("rtu+udp", 0, BIGGEST_READ) for _ in range(50))
        sock.sendto(garbage_then_reads, (server.host, server.port))
        sock.sendto(adu("rtu+udp", 0, LONE_READ), (server.host, server.port))
        replies, answered = replies_until_lone(sock, "rtu+udp")
    assert answered and replies == []


def test_a_packed_datagram_holds_no_other_master_up_on_bridge_and_sigterm_is_prompt():
    """The bus behind takes 20 ms a transaction (serve --delay): 200 packed reads held another
    master up 4 s before, and SIGTERM as long."""
    with serve("--delay", "0.02") as device:
        with bridge("-p", device.target, "-q", listen="udp://127.0.0.1:0") as running:
            where = (running.host, running.port)
            with peer() as attacker, peer() as master:
                packed = b"".join(adu("udp", tid, LONE_READ) for tid in range(1, 201))
                attacker.sendto(packed, where)
                time.sleep(0.05)  # the packed datagram is the bridge's before the master's
                began = time.monotonic()
                master.sendto(adu("udp", 7, LONE_READ), where)
                reply, _ = master.recvfrom(512)
                waited = time.monotonic() - began
                assert reply[:2] == b"\x00\x07"
                assert waited < 2.0, f"another master waited {waited:.1f} s"  # the 200 take 4 s
                attacker.sendto(packed, where)
                time.sleep(0.05)
                began = time.monotonic()
                code, _, _ = running.stop()
                stopping = time.monotonic() - began
    assert code == 0
    assert stopping < 2.5, f"SIGTERM took {stopping:.1f} s"  # the 200 take 4 s


@pytest.mark.parametrize("kind", ["serve", "bridge"])
def test_udp_rate_caps_the_replies_to_one_source_and_spares_the_others(kind):
    with listening(kind, "udp", "--udp-rate", "5") as (host, port, stop):
        with peer("127.0.0.1") as flooder, peer("127.0.0.2") as other:
            for tid in range(1, 51):
                flooder.sendto(adu("udp", tid, LONE_READ), (host, port))
            other.sendto(adu("udp", 0xFFFF, LONE_READ), (host, port))
            reply, _ = other.recvfrom(512)
            assert reply[:2] == b"\xff\xff"  # another source is answered
            answered = 0
            flooder.settimeout(0.5)
            with contextlib.suppress(TimeoutError):
                while True:
                    flooder.recvfrom(512)
                    answered += 1
        assert 1 <= answered <= 8, f"{answered} of 50 answered at --udp-rate 5"
        summary = stop()
    assert f"{50 - answered} datagrams over --udp-rate dropped" in summary


@pytest.mark.parametrize(
    "command",
    [
        ("serve", "-p", "tcp://127.0.0.1:0", "--udp-rate", "5"),
        ("bridge", "-p", "sim://", "--udp-rate", "5"),
    ],
)
def test_udp_rate_off_udp_is_exit_2(command):
    line = assert_one_error_line(run_cli(*command), 2)
    assert "--udp-rate is for a udp:// or rtu+udp:// server" in line, line
