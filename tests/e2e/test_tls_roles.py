"""Modbus/TCP Security's write roles on ``serve`` and ``bridge`` alike (issue 40.5): a role that may
not write gets only what is known to read.  The rule is an allow-list: FC 01-04, 07, 0B, 0C, 11,
14, 18, 2B/0E, and of FC 08 the query echo (00) and the counters' reads (02, 0B-12).  Everything
else (every write, FC 08's state changes and its reserved sub-functions such as 05, 13 and 16,
FC 43's other MEI types such as 0D CANopen, function codes nobody knows) is answered exception 01
and never reaches the device or the bus.

The clients are real TLS clients (Python's ssl, mbtool's own), with certificates ``openssl``
makes (tests/peers/certs.py).  What reached the device is read from the log of the ``serve``
that is the device: ``serve`` itself, or the TCP device behind the ``bridge``.
"""

from __future__ import annotations

import contextlib
import socket
import ssl

import pytest
from helpers.checks import assert_one_error_line
from helpers.frames import mbap, read_mbap
from helpers.run import run_cli
from helpers.served import PROMPT, bridge, serve

pytestmark = pytest.mark.timeout(120)

# Requests only read: every role may send them.
READS = [
    "01 0000 0001",
    "02 0000 0001",
    "03 0000 0001",
    "04 0000 0001",
    "07",
    "08 0000 A537",
    "08 0002 0000",
    *(f"08 00{sub:02X} 0000" for sub in range(0x0B, 0x13)),  # the counters, 0B-12
    "0B",
    "0C",
    "11",
    "14 07 06 0001 0000 0001",
    "18 0000",
    "2B 0E 01 00",
]
# Everything else needs a write role.
OTHERS = [
    "05 0001 FF00",
    "06 0001 0009",
    "0F 0001 0002 01 03",
    "10 0001 0001 02 0009",
    "15 09 06 0001 0000 0001 0009",
    "16 0001 00F2 0025",
    "17 0000 0001 0001 0001 02 0009",
    "08 0001 0000",  # restart communications
    "08 0003 3A00",  # change the ASCII delimiter
    "08 0005 0000",  # reserved: what a device does with it nobody can promise
    "08 000A 0000",  # clear counters
    "08 0013 0000",  # reserved in the current spec (IOP overrun count on old Modicons)
    "08 0014 0000",  # clear overrun
    "08 0015 0003",  # Modbus Plus statistics: reserved in the current spec
    "08 0016 0000",  # reserved
    "2B 0D 00 00 00 00",  # MEI type 0D, CANopen general reference: it can write
    "41 00 01",  # a function code nobody knows
]
SILENCING = "08 0004 0000"  # force listen-only: refused too, but the operator's would silence the device


def pdu(text: str) -> bytes:
    return bytes.fromhex(text.replace(" ", ""))


@contextlib.contextmanager
def tls_client(host: str, port: int, pki, who: str):
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.load_verify_locations(pki.ca.cert)
    pair = getattr(pki, who)
    context.load_cert_chain(pair.cert, pair.key)
    raw = socket.create_connection((host, port), timeout=PROMPT * 2)
    with context.wrap_socket(raw) as sock:
        sock.settimeout(PROMPT * 2)
        yield sock


def ask_each(sock: ssl.SSLSocket, requests: list[str]) -> list[bytes]:
    """Each request's reply PDU, in turn."""
    replies = []
    for tid, text in enumerate(requests, 1):
        sock.sendall(mbap(tid, 1, pdu(text)))
        got_tid, _, reply = read_mbap(sock)
        assert got_tid == tid
        replies.append(reply)
    return replies


def received(log: str) -> list[str]:
    """The PDUs a serve's log says it received, as hex."""
    pdus = []
    for line in log.splitlines():
        words = line.split()
        if len(words) > 3 and words[2] == "RX":
            pdus.append(bytes.fromhex("".join(words[3:])[14:]).hex(" ").upper())
    return pdus


def shown(texts: list[str]) -> list[str]:
    return [pdu(text).hex(" ").upper() for text in texts]


def server_args(pki) -> list[str]:
    tls = ["--cert", str(pki.server.cert), "--key", str(pki.server.key), "--ca", str(pki.ca.cert)]
    return [*tls, "--write-roles", "operator"]


@contextlib.contextmanager
def front(kind: str, pki):
    """(the TLS port's host and port, the serve that is the device) for ``serve`` on tls://, or a
    ``bridge`` on tls:// (--raw-functions: nothing unknown is held back but by the role) in
    front of a TCP ``serve``."""
    if kind == "serve":
        with serve(*server_args(pki), target="tls://127.0.0.1:0", quiet=False) as device:
            yield (device.host, device.port), device
        return
    with serve(quiet=False) as device:
        with bridge(
            "-p", device.target, "--raw-functions", *server_args(pki), listen="tls://127.0.0.1:0", fmt="plain"
        ) as running:  # fmt: skip
            yield (running.host, running.port), device


@pytest.mark.parametrize("kind", ["serve", "bridge"])
def test_roles_that_may_not_write_get_only_reads(pki, kind):
    with front(kind, pki) as ((host, port), device):
        for who in ("viewer", "no_role"):
            before = len(device.log())
            with tls_client(host, port, pki, who) as sock:
                replies = ask_each(sock, OTHERS + [SILENCING] + READS)
            refused = replies[: len(OTHERS) + 1]
            sent = [pdu(text) for text in OTHERS + [SILENCING]]
            assert refused == [bytes([r[0] | 0x80, 0x01]) for r in sent], who
            # Only the reads reached the device, every one of them.
            assert received(device.log()[before:]) == shown(READS), who
        before = len(device.log())
        with tls_client(host, port, pki, "operator") as sock:
            ask_each(sock, OTHERS + READS)
        assert received(device.log()[before:]) == shown(OTHERS + READS)


@pytest.mark.parametrize("kind", ["serve", "bridge"])
def test_mbtool_raw_from_a_viewer_is_refused_a_reserved_diagnostic(pki, kind):
    with front(kind, pki) as ((host, port), device):
        identity = ["--cert", str(pki.viewer.cert), "--key", str(pki.viewer.key), "--ca", str(pki.ca.cert)]
        res = run_cli("raw", "01", "08", "00", "05", "00", "00", "-p", f"tls://{host}:{port}", *identity)
        line = assert_one_error_line(res, 4)
        assert "exception 01" in line, line
        assert received(device.log()) == []
