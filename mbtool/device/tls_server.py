"""The server behind ``serve`` and ``bridge`` on Modbus/TCP Security (``tls://HOST:PORT``).

A TCP server (``mbtool.device.tcp_server``: its clients, limits and timeouts) whose
connections are TLS 1.2 or newer, as the MODBUS/TCP Security specification (MB-TCP-Security-
v21) asks: MBAP inside, and the client's certificate required and checked against the CA
given (mutual authentication).  The handshake runs in the loop like any read, never waiting,
so a client that stalls it holds nobody up, and the first-request timeout closes it.

A client whose handshake fails (no certificate, one the CA did not sign, an expired one, a
plain Modbus TCP client) gets TLS's alert and the loop's log line saying why; the connection
is closed for writing at once and its bytes are dropped until the client hangs up, so the
alert is not lost to a reset.

Authorization (the specification's role-based rules): a client's role is the UTF8String of
its certificate's extension 1.3.6.1.4.1.50316.802.1 (``mbtool.link.x509``).  With write roles
given, a request from any other role (or none) that is not known to only read (``reads_only``,
an allow-list) is answered exception 01, Illegal Function, as the specification says, and never
reaches the device or the bus (``RoleCheck``): on ``serve`` and ``bridge`` alike.
"""

from __future__ import annotations

import selectors
import socket
import ssl
from collections.abc import Callable
from typing import cast

from mbtool.codec.device_id import MEI_TYPE
from mbtool.codec.framing import Frame, Framer, Rejected
from mbtool.codec.pdu import ExceptionCode, ExceptionResponse
from mbtool.codec.record import replace
from mbtool.codec.serial_line import DiagnosticSubFunction as Sub
from mbtool.device.serving import Answerer, ServerParts, Stats
from mbtool.device.tcp_server import RECV_SIZE, TcpServer, _Client
from mbtool.link import x509

# What a failed handshake means, by OpenSSL's reason, in the server's words.
FAILURES = {
    "PEER_DID_NOT_RETURN_A_CERTIFICATE": "the client sent no certificate (Modbus/TCP Security is mutual)",
    "NO_SHARED_CIPHER": "no cipher in common",
    "UNSUPPORTED_PROTOCOL": "the client speaks no TLS version this server does (1.2 or newer)",
    "WRONG_VERSION_NUMBER": "not TLS (a plain Modbus TCP client?)",
    "HTTP_REQUEST": "not TLS (an HTTP request)",
    "RECORD_LAYER_FAILURE": "not TLS (a plain Modbus TCP client?)",
    "PACKET_LENGTH_TOO_LONG": "not TLS (a plain Modbus TCP client?)",
}


# What a role that may not write may send: an allow-list of the requests that only read (spec
# §6), so that nothing whose effect is unknown gets through: not FC 08's reserved sub-functions
# (05-09, 13, 15 and up: what a device does with them nobody can promise), not FC 43's other MEI
# types (0D, CANopen general reference, can write), not a function code nobody knows.
READ_FUNCTIONS = frozenset({0x01, 0x02, 0x03, 0x04, 0x07, 0x0B, 0x0C, 0x11, 0x14, 0x18})
READ_DEVICE_ID = (0x2B, MEI_TYPE)  # FC 43 / 14: Read Device Identification
# FC 08: the query's echo, the diagnostic register and the counters 0B-12 (the spec's FC 08
# table, codec.serial_line: 13 is reserved there, 14 clears).
READ_DIAGNOSTICS = frozenset(
    {
        Sub.RETURN_QUERY_DATA,
        Sub.RETURN_DIAGNOSTIC_REGISTER,
        *range(Sub.BUS_MESSAGE_COUNT, Sub.BUS_CHAR_OVERRUN_COUNT + 1),
    }
)


def reads_only(pdu: bytes) -> bool:
    """Whether a request only reads, by its function code (and FC 08's sub-function, FC 43's MEI
    type): what a client whose role may not write may send."""
    if not pdu:
        return False
    code = pdu[0]
    if code in READ_FUNCTIONS:
        return True
    if code == 0x08:
        return len(pdu) >= 3 and int.from_bytes(pdu[1:3], "big") in READ_DIAGNOSTICS
    return tuple(pdu[:2]) == READ_DEVICE_ID


class RoleCheck:
    """An answerer in front of another: a request that does more than read (``reads_only``),
    from a client whose role may not write, is answered exception 01 at once; everything else
    goes on to ``answerer``."""

    def __init__(
        self,
        answerer: Answerer,
        write_roles: frozenset[str],
        roles: dict[str, str | None],
        stats: Stats,
        log: Callable[[str, str, bytes, str], None],
    ) -> None:
        self.answerer = answerer
        self.write_roles = write_roles
        self.roles = roles  # peer -> its certificate's role (None: it has none)
        self.stats = stats
        self.log = log

    def answer(self, event: Frame | Rejected, framer: Framer, peer: str) -> bytes | None:
        if isinstance(event, Rejected) or reads_only(event.pdu):
            return self.answerer.answer(event, framer, peer)
        role = self.roles.get(peer)
        if role in self.write_roles:
            return self.answerer.answer(event, framer, peer)
        shown = f"role {role}" if role is not None else "no role"
        why = f"write refused: {shown} may not write (exception 01)"
        refusal = ExceptionResponse(event.pdu[0], ExceptionCode.ILLEGAL_FUNCTION)
        reply = framer.build(event.unit, refusal.encode(), event.transaction_id or 0)
        self.stats.requests += 1
        self.stats.replies += 1
        self.stats.frame("RX", peer, event.adu)
        self.stats.frame("TX", peer, reply, why)
        self.log("refuse", peer, event.adu, why)
        return reply


class TlsServer(TcpServer):
    """A TcpServer whose connections are TLS, clients' certificates required (``context``,
    mbtool.link.tls.server_context); ``write_roles``: the roles that may write (None: any)."""

    def __init__(
        self,
        parts: ServerParts,
        *,
        context: ssl.SSLContext,
        write_roles: frozenset[str] | None = None,
        **limits,
    ) -> None:
        self.roles: dict[str, str | None] = {}
        if write_roles is not None:
            answerer = RoleCheck(parts.answerer, write_roles, self.roles, parts.stats, parts.log)
            parts = replace(parts, answerer=answerer)
        super().__init__(parts, **limits)
        self.context = context

    def _wrap(self, conn: socket.socket) -> socket.socket:
        return self.context.wrap_socket(conn, server_side=True, do_handshake_on_connect=False)

    def _recv(self, client: _Client) -> bytes:
        sock = _tls(client)
        if client.tls == "refused":
            data = sock.recv(RECV_SIZE)  # plain again: what follows the alert is dropped
            if data:
                raise BlockingIOError
            return data
        if client.tls != "ready" and not self._handshake(client):
            raise BlockingIOError
        try:
            data = sock.recv(RECV_SIZE)
            # The rest of a record already decrypted: the selector would not see it.
            waiting = sock.pending()
            if waiting:
                data += sock.recv(waiting)
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            raise BlockingIOError from None
        except ssl.SSLEOFError:
            return b""
        return data

    def _send(self, client: _Client, data: bytearray) -> int:
        try:
            return client.sock.send(data)
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            raise BlockingIOError from None

    def _flush(self, client: _Client) -> None:
        if client.tls not in ("ready", "refused") and not client.closed:
            self._receive(client)  # the handshake wanted to write: it goes on
            return
        super()._flush(client)

    def _handshake(self, client: _Client) -> bool:
        """One step of the client's handshake; True once it is done."""
        client.tls = "handshake"
        try:
            _tls(client).do_handshake()
        except ssl.SSLWantReadError:
            self._want(client, 0)
            return False
        except ssl.SSLWantWriteError:
            self._want(client, 1)
            return False
        except (ssl.SSLError, OSError) as error:
            self._refuse(client, error)
            return False
        client.tls = "ready"
        self._want(client, 0)
        der = _tls(client).getpeercert(binary_form=True)

        note = ""
        try:
            role = x509.role(der) if der else None
        except ValueError as error:
            role, note = None, f" ({error}: taken as no role)"
        self.roles[client.peer] = role
        shown = f"role {role}" if role is not None else "no role"
        self._log("open", client.peer, b"", f"TLS {_tls(client).version()}, {shown}{note}")
        return True

    def _want(self, client: _Client, writing: int) -> None:
        """Wait for the socket to be readable, or writable too, for the handshake."""
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if writing else 0)
        if events != client.events:
            client.events = events
            assert self.selector is not None  # open() made it
            self.selector.modify(client.sock, events, client)

    def _refuse(self, client: _Client, error: BaseException) -> None:
        why = _failure(error)
        client.tls = "refused"
        self.stats.refused += 1
        self.stats.frame("refuse", client.peer, b"", f"TLS handshake failed: {why}")
        self._log("refuse", client.peer, b"", f"TLS handshake failed: {why}")
        try:
            client.sock.shutdown(socket.SHUT_WR)  # after the alert: the client reads it, then the end
        except OSError:
            self._close(client, f"TLS handshake failed: {why}")

    def _close(self, client: _Client, why: str) -> None:
        self.roles.pop(client.peer, None)
        super()._close(client, why)


def _failure(error: BaseException) -> str:
    if isinstance(error, ssl.SSLCertVerificationError):
        return f"the client's certificate does not verify: {error.verify_message}"
    code = getattr(error, "reason", None) or ""
    if code in FAILURES:
        return FAILURES[code]
    if code:
        return code.lower().replace("_", " ")
    return getattr(error, "strerror", None) or str(error) or type(error).__name__


def _tls(client: _Client) -> ssl.SSLSocket:
    """A client's socket as what _wrap made it."""
    return cast(ssl.SSLSocket, client.sock)
