"""The exporter's HTTP/1.1 server: h11 reads the requests, one thread runs every connection's
I/O through a selector, and a thread of its own answers each request (a scrape of /modbus
waits on a device, a /metrics scrape must not wait behind it).

h11 is a strict parser (RFC 9110/9112): a request whose framing it cannot trust is an error,
not a guess.  A GET or HEAD with a body (Content-Length above 0, or any Transfer-Encoding) is
refused, and nothing after it read: behind a reverse proxy, a request in a body is one the
proxy never saw (request smuggling).  Any other method is 405 with ``Allow: GET, HEAD``.
A refusal closes its connection.

What connections may hold is bounded, so that scrapers that never finish cannot starve the
one that does: a thread only while a request is answered, never for a connection that waits;
at most ``max_connections()`` of them (a new one drops the one that has waited longest for a
request); a request's head whole within HEAD_DEADLINE of its first byte, however slowly the
bytes trickle (slowloris); a kept-alive connection IDLE_CONNECTION seconds between requests;
an answer written within WRITE_DEADLINE.  When descriptors run out, accept's EMFILE drops the
longest-waiting connection, or pauses accepting: it never spins.
"""

from __future__ import annotations

import collections
import errno
import selectors
import socket
import sys
import threading
import time
from collections.abc import Callable
from http import HTTPStatus
from typing import cast
from urllib.parse import urlsplit

import h11

HEAD_DEADLINE = 10.0  # seconds a request's head may take, from its first byte (or the connect)
IDLE_CONNECTION = 60.0  # seconds a kept-alive connection may wait for its next request
WRITE_DEADLINE = 10.0  # seconds an answer may take to be written (a scraper that stopped reading)
# Bytes of an unfinished request head h11 holds (431 past them; a head that comes whole in
# one read is bounded by the read's 64 KiB): a scrape's is a few hundred.
MAX_HEAD = 16384
MAX_CONNECTIONS = 256  # connections at once, at most a quarter of the descriptors (max_connections)
ACCEPT_PAUSE = 0.1  # seconds accepting waits when descriptors ran out and no connection can go
# What accept raises when the process or the system is out of descriptors or memory: waiting
# (or freeing one) helps; trying again at once only spins.
OUT_OF_RESOURCES = {errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM}
METHODS = (b"GET", b"HEAD")

# (path, query, headers by their names in lower case) -> (HTTP status, content type, body);
# it answers whatever happens (an error of its own is a 500 of its own)
Answer = Callable[[str, str, dict[str, str]], tuple[int, str, bytes]]


def max_connections() -> int:
    """Connections held at once: MAX_CONNECTIONS, or a quarter of the descriptors the process
    may open, so that the rest stay for the links a scrape opens and the files it reads."""
    try:
        import resource  # noqa: PLC0415 - POSIX only

        soft = resource.getrlimit(resource.RLIMIT_NOFILE)[0]
    except (ImportError, OSError, ValueError):
        return MAX_CONNECTIONS
    if soft == resource.RLIM_INFINITY:
        return MAX_CONNECTIONS
    return max(4, min(MAX_CONNECTIONS, soft // 4))


def refusal_text(status: int, line: str, extra: tuple[str, ...] = (), head_only: bool = False) -> bytes:
    """A refusal's whole answer: one text line, and the connection closed after it (written
    as it is, whatever h11's state after a request it could not parse); to a HEAD, its head
    alone, as every answer to a HEAD."""
    body = f"{line}\n".encode()
    head = [
        f"HTTP/1.1 {status} {HTTPStatus(status).phrase}",
        "Content-Type: text/plain; charset=utf-8",
        f"Content-Length: {len(body)}",
        *extra,
        "Connection: close",
    ]
    return ("\r\n".join(head) + "\r\n\r\n").encode() + (b"" if head_only else body)


class Connection:
    """One scraper's connection: its parser, and how long it may wait for its next request."""

    def __init__(self, sock: socket.socket, now: float) -> None:
        self.sock = sock
        self.http = h11.Connection(h11.SERVER, max_incomplete_event_size=MAX_HEAD)
        self.waiting_since = now  # for a request: the longest waiting goes first when one must
        self.deadline = now + HEAD_DEADLINE  # a new connection's first request comes at once
        self.started = False  # bytes of the next request have come
        self.request: h11.Request | None = None
        self.answering = False  # a thread has it: not the loop's to read, drop or expire
        self.done = False  # the thread is through with it and it is to be closed


class HttpServer:
    """``serve_forever`` until ``shutdown`` (from another thread), then ``server_close``."""

    def __init__(self, host: str, port: int, family: socket.AddressFamily, answer: Answer) -> None:
        self.answer = answer
        self.listener = socket.socket(family, socket.SOCK_STREAM)
        try:
            if sys.platform != "win32":  # a restart must not wait for TIME_WAIT to pass
                self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.listener.bind((host, port))
            self.listener.listen(128)
        except OSError:
            self.listener.close()
            raise
        self.listener.setblocking(False)
        self.server_address = self.listener.getsockname()
        self.cap = max_connections()
        self.selector = selectors.DefaultSelector()
        self.wake_reader, self.wake_writer = socket.socketpair()
        self.wake_reader.setblocking(False)
        self.wake_writer.setblocking(False)
        self.selector.register(self.wake_reader, selectors.EVENT_READ)
        self.selector.register(self.listener, selectors.EVENT_READ)
        self.listening = True
        self.accept_at = 0.0  # monotonic: accepting paused until then
        self.connections: dict[socket.socket, Connection] = {}
        self.returned: collections.deque[Connection] = collections.deque()  # from the answering threads
        self.stopping = False
        self.running = threading.Event()  # serve_forever is under way
        self.stopped = threading.Event()  # and has ended

    # --- the loop: every connection's reads, in one thread ------------------------------------

    def serve_forever(self, poll_interval: float = 0.5) -> None:
        self.running.set()
        try:
            self._loop(poll_interval)
        finally:
            self.running.clear()
            self.stopped.set()

    def _loop(self, poll_interval: float) -> None:
        while not self.stopping:
            now = time.monotonic()
            if not self.listening and now >= self.accept_at:
                self.selector.register(self.listener, selectors.EVENT_READ)
                self.listening = True
            waits = [c.deadline for c in self.connections.values() if not c.answering]
            if not self.listening:
                waits.append(self.accept_at)
            wait = min([now + poll_interval, *waits]) - now
            for key, _ in self.selector.select(max(0.0, wait)):
                if key.fileobj is self.listener:
                    self._accept()
                elif key.fileobj is self.wake_reader:
                    self._take_back()
                else:
                    connection = self.connections.get(
                        cast(socket.socket, key.fileobj)
                    )  # registered: a socket
                    if connection is not None:  # else dropped by an accept of this same round
                        self._read(connection)
            self._expire(time.monotonic())
        for connection in list(self.connections.values()):
            if not connection.answering:
                self._close(connection)

    def shutdown(self) -> None:
        """Stop serve_forever and wait for it (as socketserver's does): server_close must not
        close what its loop still uses."""
        self.stopping = True
        self._wake()
        if self.running.is_set():
            self.stopped.wait(5)

    def server_close(self) -> None:
        for connection in list(self.connections.values()):
            self._close(connection)
        self.selector.close()
        for sock in (self.listener, self.wake_reader, self.wake_writer):
            sock.close()

    def _accept(self) -> None:
        for _ in range(64):  # a burst, then the others' turn
            try:
                sock, _ = self.listener.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as error:
                if error.errno in OUT_OF_RESOURCES:
                    if self._drop_longest_waiting():
                        continue  # a descriptor is free again
                    self._pause_accepting()
                    return
                if error.errno in (errno.ECONNABORTED, errno.EPROTO, errno.EPERM):
                    continue  # that one connection's trouble (gone before it was accepted)
                print(
                    f"mbtool: cannot accept a connection: {error.strerror or error}",
                    file=sys.stderr,
                    flush=True,
                )
                self._pause_accepting()
                return
            if len(self.connections) >= self.cap and not self._drop_longest_waiting():
                sock.close()  # every connection is being answered: this one waits its turn elsewhere
                continue
            sock.setblocking(False)
            if sock.family in (socket.AF_INET, socket.AF_INET6):
                # The answer leaves in one write: no waiting for the scraper's delayed ACK.
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.connections[sock] = Connection(sock, time.monotonic())
            self.selector.register(sock, selectors.EVENT_READ)

    def _pause_accepting(self) -> None:
        if self.listening:
            self.selector.unregister(self.listener)
            self.listening = False
        self.accept_at = time.monotonic() + ACCEPT_PAUSE

    def _drop_longest_waiting(self) -> bool:
        """Close the connection that has waited longest for a request; False if all are
        being answered."""
        waiting = [c for c in self.connections.values() if not c.answering]
        if not waiting:
            return False
        self._close(min(waiting, key=lambda c: c.waiting_since))
        return True

    def _expire(self, now: float) -> None:
        for connection in [c for c in self.connections.values() if not c.answering and c.deadline <= now]:
            self._close(connection)

    def _read(self, connection: Connection) -> None:
        try:
            data = connection.sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            self._close(connection)
            return
        if data and not connection.started:
            connection.started = True
            connection.deadline = min(connection.deadline, time.monotonic() + HEAD_DEADLINE)
        connection.http.receive_data(data)  # b"": the scraper closed its side
        self._next_request(connection)

    def _next_request(self, connection: Connection) -> None:
        """Read the events h11 has: a whole request goes to a thread to be answered."""
        http = connection.http
        while True:
            # A head h11 rejects is gone from its buffer with its method: whether it was a
            # HEAD's, whose refusal has no body either, is known only before.
            head_only = http.their_state is h11.IDLE and http.trailing_data[0].startswith(b"HEAD ")
            try:
                event = http.next_event()
            except h11.RemoteProtocolError as error:
                self._refuse(
                    connection, error.error_status_hint, f"bad request: {error}", head_only=head_only
                )
                return
            if event is h11.NEED_DATA:
                return
            if isinstance(event, h11.ConnectionClosed) or event is h11.PAUSED:
                self._close(connection)
                return
            if isinstance(event, h11.Request):
                refusal = _refusal(event)
                if refusal is not None:
                    self._refuse(connection, *refusal, head_only=event.method == b"HEAD")
                    return
                connection.request = event
            elif isinstance(event, h11.EndOfMessage):
                self._answer_in_a_thread(connection)
                return

    def _refuse(
        self,
        connection: Connection,
        status: int,
        line: str,
        extra: tuple[str, ...] = (),
        head_only: bool = False,
    ) -> None:
        """One line, and the connection closed: what follows cannot be trusted to be a request."""
        try:
            connection.sock.send(refusal_text(status, line, extra, head_only))
        except OSError:
            pass  # it is closed below either way
        self._close(connection)

    def _close(self, connection: Connection) -> None:
        sock = connection.sock
        if self.connections.pop(sock, None) is not None and not connection.answering:
            self.selector.unregister(sock)
        sock.close()

    # --- answers: a thread each ---------------------------------------------------------------

    def _answer_in_a_thread(self, connection: Connection) -> None:
        thread = threading.Thread(target=self._answer, args=(connection,), name="http answer", daemon=True)
        self.selector.unregister(connection.sock)
        connection.answering = True
        try:
            thread.start()
        except RuntimeError:  # no thread to be had (memory, a limit): the scraper tries again
            connection.answering = False
            self.connections.pop(connection.sock, None)
            head_only = connection.request is not None and connection.request.method == b"HEAD"
            self._refuse(connection, 503, "no thread to answer with: try again", head_only=head_only)

    def _answer(self, connection: Connection) -> None:
        request, http = connection.request, connection.http
        assert request is not None  # answered once its request is whole
        try:
            status, kind, body = self._answered(request)  # which never raises but for a bug
            data = http.send(
                h11.Response(
                    status_code=status,
                    headers=[("Content-Type", kind), ("Content-Length", str(len(body)))],
                    reason=HTTPStatus(status).phrase,
                )
            )
            if request.method != b"HEAD":  # a HEAD's answer: the GET's headers, without its body
                data += http.send(h11.Data(data=body))
            data += http.send(h11.EndOfMessage())
            connection.sock.settimeout(WRITE_DEADLINE)  # sendall's whole time (Python 3.5 on)
            connection.sock.sendall(data)
            if http.our_state is h11.MUST_CLOSE:
                connection.done = True
            else:
                http.start_next_cycle()
                connection.sock.setblocking(False)
        except (OSError, h11.LocalProtocolError):  # the scraper went away, or stopped reading
            connection.done = True
        except Exception as error:  # a bug: one line, never a traceback, and the connection closed
            print(
                f"mbtool: internal error answering: {type(error).__name__}: {error}",
                file=sys.stderr,
                flush=True,
            )
            connection.done = True
        finally:  # the loop takes it back whatever happened, or it would count against the cap
            now = time.monotonic()
            connection.request, connection.started = None, False
            connection.waiting_since, connection.deadline = now, now + IDLE_CONNECTION
            connection.done = connection.done or http.their_state is h11.ERROR
            self.returned.append(connection)
            self._wake()

    def _answered(self, request: h11.Request) -> tuple[int, str, bytes]:
        url = urlsplit(request.target.decode("latin-1"))
        headers = {name.decode("latin-1"): value.decode("latin-1") for name, value in request.headers}
        return self.answer(url.path, url.query, headers)

    def _take_back(self) -> None:
        """Connections whose answer is written: read on (h11 may hold the next request
        already), or closed."""
        try:
            while self.wake_reader.recv(4096):
                pass
        except (BlockingIOError, InterruptedError):
            pass
        while self.returned:
            connection = self.returned.popleft()
            connection.answering = False
            if connection.done or self.stopping:
                self.connections.pop(connection.sock, None)
                connection.sock.close()
                continue
            self.selector.register(connection.sock, selectors.EVENT_READ)
            self._next_request(connection)

    def _wake(self) -> None:
        try:
            self.wake_writer.send(b"\0")
        except OSError:
            pass  # full (the loop is waking anyway) or closed (it has stopped)


def _refusal(request: h11.Request) -> tuple[int, str, tuple[str, ...]] | None:
    """(status, line, headers) of a request the exporter does not answer; None if it does."""
    method = request.method.decode("latin-1")
    if request.method not in METHODS:
        return 405, f"{method} is not served: GET or HEAD", ("Allow: GET, HEAD",)
    for name, value in request.headers:
        if name == b"transfer-encoding" or (name == b"content-length" and value.strip() != b"0"):
            return 400, f"a {method} has no body: {name.decode()} refused, and the connection closed", ()
    return None
