"""The misbehaving-peer matrix: every way a device (or what stands for one) can answer badly,
over every kind of link, and the exit code and one stderr line each one ends in.

This is the contract docs/exit-codes.md documents.  Each case is
a scripted peer that reads the real request mbtool sent and builds its reply from it
(the request's transaction id and unit, or deliberately not), writing it in pieces with
delays where the case says so.  The peer frames its replies with the CRC/LRC helpers of
tests/helpers/frames.py, never with mbtool's codec.

Links:

* ``tcp``: Modbus TCP (MBAP) to a thread server on 127.0.0.1 (``tcp://``);
* ``socket-rtu``: RTU framing over a raw TCP socket (``socket://``, a serial device server);
* ``pty-rtu`` and ``pty-ascii``: a pseudo-terminal pair (os.openpty); the peer thread is the
  device on the master side, mbtool opens the slave (with ``--parity N``: Linux ptys refuse
  parity).

mbtool runs as a subprocess with ``-t T --retries 1`` and must end within T × 2 plus a
margin for Python start-up (measured against a baseline run); every wait here has a deadline
and every peer thread stops.
"""

from __future__ import annotations

import binascii
import contextlib
import functools
import os
import random
import re
import select
import socket
import struct
import threading
import time
import tty
from collections.abc import Callable
from dataclasses import dataclass

import pytest
from helpers.checks import assert_one_error_line
from helpers.frames import crc16, lrc
from helpers.ptys import PTY_SERIAL_OPTS
from helpers.run import run_mbtool

pytestmark = pytest.mark.timeout(60)

RETRIES = 1
PEER_LIFETIME = 15.0  # seconds a peer thread lives at most, whatever happens
CLOSE = "close"  # a script step: close the connection (TCP) or the pty's device end

GOOD = bytes.fromhex("03 02 00 64")  # FC03 reply: 1 register = 100
GOOD_OUTPUT = "0 100\n"


@dataclass(frozen=True)
class Link:
    name: str
    framing: str  # tcp | rtu | ascii
    via: str  # tcp | pty


LINKS = {
    "tcp": Link("tcp", "tcp", "tcp"),
    "socket-rtu": Link("socket-rtu", "rtu", "tcp"),
    "pty-rtu": Link("pty-rtu", "rtu", "pty"),
    "pty-ascii": Link("pty-ascii", "ascii", "pty"),
}
ALL = tuple(LINKS)
SERIAL = ("socket-rtu", "pty-rtu", "pty-ascii")  # links without a transaction id
PTYS = ("pty-rtu", "pty-ascii")


@dataclass
class Req:
    """A request as the peer read it off the link."""

    raw: bytes
    unit: int
    pdu: bytes
    tid: int | None = None


# ----------------------------------------------------------------------------- the peer


class Peer:
    """The device end of a link, in a thread; answers each request with ``script(peer, req)``.

    A script returns steps: bytes to write, a float to sleep, or CLOSE.
    """

    def __init__(self, link: Link, script: Callable[[Peer, Req], list]) -> None:
        self.link = link
        self.script = script
        self.requests: list[Req] = []
        self.errors: list[str] = []
        self._stop = threading.Event()
        self._fds: list[int] = []
        if link.via == "tcp":
            self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._server.bind(("127.0.0.1", 0))
            self._server.listen(2)
            scheme = "tcp" if link.framing == "tcp" else "socket"
            self.target = f"{scheme}://127.0.0.1:{self._server.getsockname()[1]}"
        else:
            self._master, self._slave = os.openpty()
            for fd in (self._master, self._slave):
                tty.setraw(fd)
            self._fds = [self._master, self._slave]  # the slave stays open: no EIO when mbtool closes
            self.target = os.ttyname(self._slave)
        self._thread = threading.Thread(target=self._run, name=f"peer-{link.name}", daemon=True)
        self._thread.start()

    # -- mbtool's options for this link

    @property
    def options(self) -> list[str]:
        opts = ["-p", self.target]
        if self.link.via == "pty":
            opts += PTY_SERIAL_OPTS
        if self.link.framing == "ascii":
            opts += ["--framer", "ascii"]
        return opts

    # -- building replies (independent of mbtool's codec)

    def frame(
        self,
        req: Req,
        pdu: bytes,
        *,
        unit: int | None = None,
        tid: int | None = None,
        pid: int = 0,
        length: int | None = None,
    ) -> bytes:
        unit = req.unit if unit is None else unit
        body = bytes([unit]) + pdu
        if self.link.framing == "tcp":
            tid = req.tid if tid is None else tid
            return struct.pack(">HHH", tid & 0xFFFF, pid, len(body) if length is None else length) + body
        if self.link.framing == "rtu":
            return body + crc16(body)
        return b":" + (body + bytes([lrc(body)])).hex().upper().encode() + b"\r\n"

    def bad_checksum(self, frame: bytes) -> bytes:
        if self.link.framing == "rtu":
            return frame[:-1] + bytes([frame[-1] ^ 0xFF])
        assert self.link.framing == "ascii"
        text = frame[1:-2]
        wrong = (int(text[-2:], 16) + 1) & 0xFF
        return b":" + text[:-2] + f"{wrong:02X}".encode() + b"\r\n"

    # -- the thread

    def _run(self) -> None:
        deadline = time.monotonic() + PEER_LIFETIME
        try:
            if self.link.via == "tcp":
                while not self._stop.is_set() and time.monotonic() < deadline:
                    ready, _, _ = select.select([self._server], [], [], 0.05)
                    if not ready:
                        continue
                    conn, _ = self._server.accept()
                    conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                    with conn:
                        self._serve(
                            conn.fileno(),
                            conn.recv,
                            conn.sendall,
                            functools.partial(_hang_up, conn),
                            deadline,
                        )
            else:
                read = lambda n: os.read(self._master, n)  # noqa: E731
                self._serve(self._master, read, self._write_pty, self._close_master, deadline)
        except Exception as error:  # noqa: BLE001 - reported by the test
            self.errors.append(f"{type(error).__name__}: {error}")

    def _write_pty(self, data: bytes) -> None:
        while data:
            data = data[os.write(self._master, data) :]

    def _serve(self, fd: int, recv, send, hang_up, deadline: float) -> None:
        buffer = b""
        while not self._stop.is_set() and time.monotonic() < deadline:
            ready, _, _ = select.select([fd], [], [], 0.05)
            if not ready:
                continue
            try:
                data = recv(4096)
            except OSError:
                return
            if not data:
                return  # mbtool closed the connection
            buffer += data
            while (taken := self._take_request(buffer)) is not None:
                req, buffer = taken
                self.requests.append(req)
                for step in self.script(self, req):
                    if step == CLOSE:
                        hang_up()
                        return
                    if isinstance(step, float):
                        if self._stop.wait(step):
                            return
                    else:
                        try:
                            send(step)
                        except OSError:
                            return

    def _close_master(self) -> None:
        os.close(self._master)  # mbtool's end of the pty now reads EIO: the device is gone
        self._fds.remove(self._master)

    def _take_request(self, buffer: bytes) -> tuple[Req, bytes] | None:
        framing = self.link.framing
        if framing == "tcp":
            if len(buffer) < 6:
                return None
            size = 6 + int.from_bytes(buffer[4:6], "big")
            if len(buffer) < size:
                return None
            raw = buffer[:size]
            return Req(raw, raw[6], raw[7:], int.from_bytes(raw[:2], "big")), buffer[size:]
        if framing == "rtu":
            if len(buffer) < 8:  # every request of this matrix is FC03: 8 bytes
                return None
            raw = buffer[:8]
            return Req(raw, raw[0], raw[1:-2]), buffer[8:]
        end = buffer.find(b"\n")
        if end < 0:
            return None
        raw = buffer[: end + 1]
        body = binascii.unhexlify(raw[1:-2])
        return Req(raw, body[0], body[1:-1]), buffer[end + 1 :]

    def wait_requests(self, count: int, within: float = 1.0) -> int:
        end = time.monotonic() + within
        while len(self.requests) < count and time.monotonic() < end:
            time.sleep(0.01)
        return len(self.requests)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=3)
        assert not self._thread.is_alive(), "the peer thread did not stop"
        if self.link.via == "tcp":
            self._server.close()
        for fd in self._fds:
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> Peer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _hang_up(conn: socket.socket) -> None:
    with contextlib.suppress(OSError):
        conn.shutdown(socket.SHUT_RDWR)
    conn.close()


# ----------------------------------------------------------------------------- the scripts


def drip(data: bytes, gap: float = 0.01) -> list:
    steps: list = []
    for byte in data:
        steps += [bytes([byte]), gap]
    return steps


def silence(peer, req):
    return []


def good(peer, req):
    return [peer.frame(req, GOOD)]


def wrong_tid(peer, req):
    return [peer.frame(req, GOOD, tid=req.tid + 1)]


def stale_then_right(peer, req):
    # The late reply to an earlier request (two registers), then the reply to this one.
    stale_pdu = bytes.fromhex("03 04 00 0A 00 0B")
    stale = peer.frame(req, stale_pdu, tid=req.tid - 1) if req.tid is not None else peer.frame(req, stale_pdu)
    return [stale, 0.05, peer.frame(req, GOOD)]


def other_unit(peer, req):
    return [peer.frame(req, GOOD, unit=7)]


def other_function(peer, req):
    return [peer.frame(req, bytes.fromhex("04 02 00 64"))]


def byte_count(peer, req):
    return [peer.frame(req, bytes.fromhex("03 04 00 64 00 65"))]  # 2 registers for 1 asked


def truncated(peer, req):
    return [peer.frame(req, GOOD)[:-2]]  # the rest never comes; the link stays open


def dripped(peer, req):
    return drip(peer.frame(req, GOOD))


def garbage_before(peer, req):
    return [b"\xff\xfe\x00\x13" + peer.frame(req, GOOD)]


# 64 KiB of noise (a gateway's buffer flushed, a line with a fault) then the reply, written
# at once: every link reads it in large pieces and resyncs at the codec's speed (issue 13.2).
NOISE = random.Random(13).randbytes(64 * 1024)


def flood_before(peer, req):
    return [NOISE + peer.frame(req, GOOD)]


def late_for_the_first_attempt(peer, req):
    """A device slower than the timeout: the first attempt's reply comes while mbtool waits
    for the second's; the second is never answered (issue 12.2)."""
    return [0.45, peer.frame(req, GOOD)] if len(peer.requests) == 1 else []


def busy_then_good(peer, req):
    """Exception 06 Server Device Busy, then the reply: the spec says to retry later (12.17)."""
    return [peer.frame(req, bytes.fromhex("83 06"))] if len(peer.requests) == 1 else [peer.frame(req, GOOD)]


def garbage_inside(peer, req):
    frame = peer.frame(req, GOOD)
    cut = {"tcp": 8, "rtu": 3, "ascii": 5}[peer.link.framing]
    return [frame[:cut] + b"\xaa\x55" + frame[cut:]]


def garbage_after(peer, req):
    return [peer.frame(req, GOOD) + b"\xff\xfe\x00\x13"]


def bad_checksum(peer, req):
    return [peer.bad_checksum(peer.frame(req, GOOD))]


def ascii_non_hex(peer, req):
    frame = peer.frame(req, GOOD)
    return [frame[:7] + b"GZ" + frame[9:]]  # the byte count's two characters are not hex


def ascii_odd_length(peer, req):
    frame = peer.frame(req, GOOD)
    return [frame[:7] + frame[8:]]  # one hex character dropped


def mbap_protocol_id(peer, req):
    return [peer.frame(req, GOOD, pid=1)]


def mbap_length(value: int):
    def script(peer, req):
        return [peer.frame(req, GOOD, length=value)]

    script.__name__ = f"mbap_length_{value}"
    return script


def closed_before_reply(peer, req):
    return [CLOSE]


def closed_mid_frame(peer, req):
    frame = peer.frame(req, GOOD)
    return [frame[: len(frame) // 2], 0.05, CLOSE]


def undefined_exception(peer, req):
    return [peer.frame(req, bytes([0x83, 0x19]))]


def echo_then_reply(peer, req):
    # The echo comes back at once; the device answers after its turnaround.
    return [req.raw, 0.15, peer.frame(req, GOOD)]


def echo_only(peer, req):
    return [req.raw]


# ----------------------------------------------------------------------------- the matrix


@dataclass(frozen=True)
class Case:
    name: str
    script: Callable
    links: tuple[str, ...]
    code: int
    # a regex the error line must match; a dict picks one by framing (tcp, rtu, ascii)
    message: str | dict[str, str] = ""
    options: tuple[str, ...] = ()
    timeout: float = 0.3
    requests: int | None = None  # how many requests mbtool sends; default: by exit code
    known_bug: dict[str, str] | None = None  # framing -> what mbtool gets wrong (strict xfail)

    def expected_message(self, link: Link) -> str:
        return self.message.get(link.framing, "") if isinstance(self.message, dict) else self.message

    def expected_requests(self) -> int:
        if self.requests is not None:
            return self.requests
        # a reply or an exception ends it at once; anything else is retried
        return 1 if self.code in (0, 4) else RETRIES + 1


CHECKSUM = {"rtu": r"CRC error", "ascii": r"LRC error"}
TRUNCATED = {
    "tcp": r"truncated MBAP frame \(9 bytes\)",
    "rtu": r"truncated frame \(5 of 7 bytes\)",
    "ascii": r"not ended by CR LF",
}

CASES = [
    Case("silence", silence, ALL, 3, r"no response from unit 1 within 0\.3 s"),
    Case("good reply (control)", good, ALL, 0),
    Case("wrong transaction id", wrong_tid, ("tcp",), 5, r"transaction id \d+, expected \d+"),
    Case("stale reply then the right one", stale_then_right, ALL, 0),
    Case("reply from another unit", other_unit, ALL, 5, r"reply from unit 7, expected unit 1"),
    Case(
        "another function code", other_function, ALL, 5, r"reply has FC 04 \(0x04\), expected FC 03 \(0x03\)"
    ),
    Case("byte count disagrees with quantity", byte_count, ALL, 5, r"byte count 4 does not fit 1 registers"),
    Case(
        "truncated reply",
        truncated,
        ALL,
        5,
        TRUNCATED,
    ),
    Case("reply dripped byte by byte", dripped, ALL, 0, timeout=1.0),
    Case("the first attempt's reply, late", late_for_the_first_attempt, ALL, 0, requests=2),
    Case("busy, then the reply", busy_then_good, ALL, 0, requests=2),
    Case(
        "busy, without retries",
        busy_then_good,
        ALL,
        4,
        r"exception 06 Server Device Busy",
        options=("--retries", "0"),
        requests=1,
    ),
    Case("garbage before the frame", garbage_before, ALL, 0),
    Case(
        "garbage inside the frame",
        garbage_inside,
        ALL,
        5,
        # MBAP: the garbage lands in the byte count, which then promises 170 bytes
        {"tcp": r"registers reply: PDU is 4 bytes, expected 172", "rtu": r"CRC error", "ascii": r"non-hex"},
    ),
    Case("garbage after the frame", garbage_after, ALL, 0),
    Case("64 KiB of garbage before the frame", flood_before, ALL, 0, timeout=1.0),
    Case("bad CRC or LRC", bad_checksum, SERIAL, 5, CHECKSUM),
    Case("non-hex ASCII", ascii_non_hex, ("pty-ascii",), 5, r"non-hex characters"),
    Case("odd-length ASCII", ascii_odd_length, ("pty-ascii",), 5, r"odd number of hex characters \(11\)"),
    Case("MBAP protocol id 1", mbap_protocol_id, ("tcp",), 5, r"MBAP protocol id 1, expected 0"),
    Case("MBAP length 0", mbap_length(0), ("tcp",), 5, r"MBAP length 0 is outside 2\.\.254"),
    Case("MBAP length 1", mbap_length(1), ("tcp",), 5, r"MBAP length 1 is outside 2\.\.254"),
    Case("MBAP length 65535", mbap_length(65535), ("tcp",), 5, r"MBAP length 65535 is outside 2\.\.254"),
    # The link is gone: no retry (it could only fail to write), exit 3 like silence, and the
    # line names what arrived before the hang-up.
    Case(
        "closed before replying",
        closed_before_reply,
        ALL,
        3,
        r"closed the connection|socket disconnected|device disconnected|went away while sending",
        requests=1,
    ),
    Case(
        "closed mid-frame",
        closed_mid_frame,
        ALL,
        3,
        {
            "tcp": r"closed the connection; what it sent before: truncated MBAP frame \(5 bytes\)",
            "rtu": r"what it sent before: truncated frame \(3 bytes\)",
            "ascii": r"what it sent before: ASCII frame not ended by CR LF",
        },
        requests=1,
    ),
    Case(
        "exception with an undefined code",
        undefined_exception,
        ALL,
        4,
        r"exception 19 Undefined Exception Code to FC 03 \(0x03\)",
    ),
    Case("half-duplex echo with --echo", echo_then_reply, PTYS + ("socket-rtu",), 0, options=("--echo",)),
    Case("half-duplex echo without --echo", echo_then_reply, PTYS + ("socket-rtu",), 0),
    Case(
        "only the echo, without --echo",
        echo_only,
        PTYS,
        5,
        r"the only reply was a copy of the request \(an echoing adapter\? try --echo\)",
    ),
    Case("only the echo, with --echo", echo_only, PTYS, 3, r"no response from unit 1", options=("--echo",)),
    # --echo on a link that does not echo: the reply is the reply, not a bad echo (issue 12.14)
    Case("no echo, with --echo", good, PTYS + ("socket-rtu",), 0, options=("--echo",)),
    # a TCP server or gateway that echoes the request says so, as a serial line does (13.10)
    Case(
        "only a copy of the request, over TCP",
        echo_only,
        ("tcp",),
        5,
        r"the only reply was a copy of the request \(the server, or a gateway on the way, echoes requests\)",
    ),
]


def _param(case: Case, link: str):
    bug = (case.known_bug or {}).get(LINKS[link].framing)
    marks = [pytest.mark.xfail(strict=True, reason=bug)] if bug else []
    return pytest.param(case, link, id=f"{case.name}-{link}", marks=marks)


PARAMS = [_param(case, link) for case in CASES for link in case.links]


@pytest.fixture(scope="module")
def margin(start_up) -> float:
    """Seconds above timeout × (retries + 1) a run may take: Python start-up, measured, with room."""
    return max(1.5, 1.0 + 3 * start_up)


@pytest.mark.parametrize("case, link_name", PARAMS)
def test_misbehaving_peer(case: Case, link_name: str, margin: float) -> None:
    link = LINKS[link_name]
    with Peer(link, case.script) as peer:
        res = run_mbtool(
            "read-holding-registers",
            "0",
            *peer.options,
            "-t",
            str(case.timeout),
            "--retries",
            str(RETRIES),
            *case.options,
        )
        sent = peer.wait_requests(case.expected_requests())
    assert not peer.errors, peer.errors
    if case.code == 0:
        assert res.returncode == 0, str(res)
        assert res.stdout == GOOD_OUTPUT and res.stderr == "", str(res)
    else:
        line = assert_one_error_line(res, case.code)
        assert re.search(case.expected_message(link), line), f"the error line does not say why\n{res}"
        assert res.stdout == "", str(res)
    assert sent == case.expected_requests(), f"mbtool sent {sent} requests\n{res}"
    bound = case.timeout * (RETRIES + 1) + margin
    assert res.elapsed <= bound, f"took {res.elapsed:.2f} s, more than {bound:.2f} s\n{res}"


# ----------------------------------------------------------------------------- the port going away


def test_a_serial_port_that_goes_away_while_draining_is_a_hang_up_not_a_crash():
    """pyserial's flush lets termios.error through (tcdrain on a pty whose other end closed):
    the 'closed before replying' case over a pty ended in exit 1 whenever the peer was quick."""
    import termios

    from mbtool.link.transport import ConnectionClosed, ConnectionFailed, SerialTransport

    class GoneAfterWrite:
        def __init__(self, fail_write: bool) -> None:
            self.fail_write = fail_write

        def write(self, data):
            if self.fail_write:
                raise OSError(5, "Input/output error")
            return len(data)

        def flush(self):
            raise termios.error(5, "Input/output error")

    import serial

    for fail_write, expected in ((False, ConnectionClosed), (True, ConnectionFailed)):
        transport = SerialTransport.__new__(SerialTransport)
        transport.description = "/dev/ttyX"
        transport.port = GoneAfterWrite(fail_write)
        transport._serial_error = serial.SerialException
        transport._rts_switching = None
        with pytest.raises(expected, match="Input/output error"):
            transport.write(b"\x01\x03")
