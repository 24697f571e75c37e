"""The exporter's HTTP side: what it parses and what a connection may hold (issues 39.18, 40.3,
40.4).  The scrapers are raw sockets, so that what goes on the wire is exactly what the test
writes: a body behind a GET, a head that never ends, more connections than descriptors.
"""

from __future__ import annotations

import contextlib
import os
import re
import resource
import shutil
import socket
import threading
import time

import pytest
from helpers.exporter import METER_MAP, exporting
from helpers.run import signals_as_from_a_shell

pytestmark = pytest.mark.timeout(120)


def address(exporter) -> tuple[str, int]:
    host, port = exporter.url.removeprefix("http://").rsplit(":", 1)
    return host, int(port)


def exchange(where: tuple[str, int], data: bytes, wait: float = 5.0) -> tuple[bytes, bool]:
    """Send ``data`` on a new connection and read what comes back: (the bytes, whether the
    exporter closed the connection within ``wait`` seconds)."""
    with socket.create_connection(where, timeout=wait) as sock:
        sock.sendall(data)
        got = b""
        end = time.monotonic() + wait
        while time.monotonic() < end:
            sock.settimeout(max(0.01, end - time.monotonic()))
            try:
                chunk = sock.recv(65536)
            except TimeoutError:
                return got, False
            except ConnectionResetError:
                return got, True
            if not chunk:
                return got, True
            got += chunk
        return got, False


def responses(raw: bytes) -> list[tuple[int, dict[str, str], bytes]]:
    """The responses in ``raw``, each (status, headers in lower case, body by Content-Length):
    not for a HEAD's, whose Content-Length is that of a body it does not send."""
    out = []
    while raw:
        head, _, rest = raw.partition(b"\r\n\r\n")
        lines = head.decode("latin-1").split("\r\n")
        status = int(lines[0].split()[1])
        headers = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:])}
        length = int(headers.get("content-length", "0"))
        body, raw = rest[:length], rest[length:]
        out.append((status, headers, body))
    return out


@pytest.fixture
def maps(tmp_path):
    folder = tmp_path / "maps"
    folder.mkdir()
    shutil.copy(METER_MAP, folder / "energy-meter.toml")
    return folder


def test_a_request_with_a_body_is_400_and_its_connection_closed(tmp_path, maps, silent_server):
    """Issue 40.3: a GET with a Content-Length body got two answers, and the /modbus read
    smuggled in its body ran: behind a reverse proxy, a request the proxy never saw."""
    smuggled = (
        f"GET /modbus?target={silent_server.tcp_target}&module=energy-meter HTTP/1.1\r\nHost: x\r\n\r\n"
    ).encode()
    chunked = b"%x\r\n%s\r\n0\r\n\r\n" % (len(smuggled), smuggled)
    with exporting("--maps", maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path) as exporter:
        for framing, body in (
            (b"Content-Length: %d\r\n" % len(smuggled), smuggled),
            (b"Transfer-Encoding: chunked\r\n", chunked),
            (b"Content-Length: %d\r\nTransfer-Encoding: chunked\r\n" % len(chunked), chunked),
        ):
            request = b"GET /metrics HTTP/1.1\r\nHost: x\r\n" + framing + b"\r\n" + body
            raw, closed = exchange(address(exporter), request)
            got = responses(raw)
            assert [status for status, _, _ in got] == [400], raw
            assert closed, raw
            (status, headers, text) = got[0]
            assert headers["content-type"].startswith("text/plain") and text.count(b"\n") == 1, raw
        # What has no body is answered as ever: Content-Length 0 is no body.
        raw, _ = exchange(
            address(exporter), b"GET / HTTP/1.1\r\nHost: x\r\nContent-Length: 0\r\nConnection: close\r\n\r\n"
        )
        assert [status for status, _, _ in responses(raw)] == [200], raw
    assert silent_server.connections == 0


def test_head_is_get_without_its_body_and_other_methods_are_405(tmp_path, maps):
    """Issue 39.18: HEAD and POST were 501 with an HTML page."""
    with exporting("--maps", maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path) as exporter:
        where = address(exporter)
        # A HEAD and then a GET on one connection: the HEAD's answer has the GET's headers and
        # no body, or the GET's answer would not start where it must.
        raw, _ = exchange(
            where, b"HEAD / HTTP/1.1\r\nHost: x\r\n\r\nGET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n"
        )
        head_end = raw.index(b"\r\n\r\n") + 4
        head = responses(raw[:head_end])[0]
        get = responses(raw[head_end:])[0]
        assert head[0] == get[0] == 200, raw
        assert head[1]["content-length"] == get[1]["content-length"] == str(len(get[2])), raw
        assert head[1]["content-type"] == get[1]["content-type"], raw
        assert get[2].startswith(b"mbtool exporter\n"), raw
        raw, _ = exchange(where, b"HEAD /metrics HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        assert raw.startswith(b"HTTP/1.1 200 ") and raw.endswith(b"\r\n\r\n"), raw
        for method in (b"POST", b"PUT", b"DELETE", b"OPTIONS", b"PATCH"):
            raw, closed = exchange(
                where, method + b" /metrics HTTP/1.1\r\nHost: x\r\nContent-Length: 3\r\n\r\nx=1"
            )
            ((status, headers, text),) = responses(raw)
            assert status == 405 and headers["allow"] == "GET, HEAD", raw
            assert headers["content-type"].startswith("text/plain"), raw
            assert text == method + b" is not served: GET or HEAD\n", raw
            assert closed, raw


def test_a_head_refused_gets_its_answer_without_a_body(tmp_path, maps):
    """A HEAD is answered without a body, refusals too (the exporter fuzz campaign): a HEAD
    with a body got the 400's line after the head, which a client takes for the start of the
    next answer."""
    with exporting("--maps", maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path) as exporter:
        raw, closed = exchange(
            address(exporter), b"HEAD /metrics HTTP/1.1\r\nHost: x\r\nContent-Length: 3\r\n\r\nx=1"
        )
    assert raw.startswith(b"HTTP/1.1 400 ") and raw.endswith(b"\r\n\r\n"), raw
    assert b"Content-Length: " in raw and closed, raw


def test_a_head_h11_rejects_gets_its_answer_without_a_body(tmp_path, maps):
    """RFC 9110 9.3.2: a HEAD's answer has no body.  A HEAD whose head h11 could not parse (no
    Host, a malformed header line; after a kept-alive GET, too) got its 400's line after the
    head, which a client takes for the start of the next answer."""
    get = b"GET / HTTP/1.1\r\nHost: x\r\n\r\n"
    with exporting("--maps", maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path) as exporter:
        for before, bad in (
            (b"", b"HEAD /metrics HTTP/1.1\r\n\r\n"),  # HTTP/1.1 without Host
            (b"", b"HEAD /metrics HTTP/1.1\r\nHost: x\r\nno colon\r\n\r\n"),
            (get, b"HEAD /metrics HTTP/1.1\r\nHost: x\r\nHost: y\r\n\r\n"),  # two Hosts
        ):
            raw, closed = exchange(address(exporter), before + bad)
            # The 400's head is the last thing sent (the GET's answer, whole, before it).
            assert [status for status, _, _ in responses(raw)] == [200] * bool(before) + [400], raw
            assert raw.endswith(b"\r\n\r\n") and closed, raw
        # A GET h11 rejects still gets its line.
        raw, closed = exchange(address(exporter), b"GET /metrics HTTP/1.1\r\n\r\n")
        ((status, _, text),) = responses(raw)
        assert status == 400 and text.startswith(b"bad request: ") and closed, raw


def test_a_head_refused_for_want_of_a_thread_gets_its_answer_without_a_body(monkeypatch):
    """The 503 of a request no thread could be had for: to a HEAD, its head alone."""
    from mbtool.cli.http_server import HttpServer

    server = HttpServer(
        "127.0.0.1", 0, socket.AF_INET, lambda path, query, headers: (200, "text/plain", b"x\n")
    )
    loop = threading.Thread(target=server.serve_forever, args=(0.05,), daemon=True)
    loop.start()
    try:
        server.running.wait(5)

        def no_thread(self):
            raise RuntimeError("can't start new thread")

        monkeypatch.setattr(threading.Thread, "start", no_thread)
        where = server.server_address[:2]
        raw, closed = exchange(where, b"HEAD /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
        assert raw.startswith(b"HTTP/1.1 503 ") and raw.endswith(b"\r\n\r\n") and closed, raw
        raw, closed = exchange(where, b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
        ((status, _, text),) = responses(raw)
        assert status == 503 and text == b"no thread to answer with: try again\n" and closed, raw
    finally:
        monkeypatch.undo()
        server.shutdown()
        server.server_close()
        loop.join(5)


def _threads_and_descriptors(pid: int) -> tuple[int, int]:
    status = open(f"/proc/{pid}/status").read()
    return int(re.search(r"^Threads:\s+(\d+)", status, re.M)[1]), len(os.listdir(f"/proc/{pid}/fd"))


def _cpu_seconds(pid: int) -> float:
    fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_500_slow_connections_cost_no_thread_and_a_scrape_is_still_answered(tmp_path, maps):
    """Issue 40.4: a connection sending a byte a minute was held for ever, with a thread each
    (400 held connections: 346 threads)."""
    with exporting("--maps", maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path) as exporter:
        where = address(exporter)
        slow = []
        try:
            for _ in range(500):
                sock = socket.create_connection(where, timeout=5)
                sock.sendall(b"GET /metrics HTTP/1.1\r\nHost: x\r\nX-Slow: ")  # and never the rest
                slow.append(sock)
            began = time.monotonic()
            status, _, text = exporter.get("/metrics", timeout=5)
            took = time.monotonic() - began
            assert status == 200 and "process_cpu_seconds_total" in text
            assert took < 2.0, f"a scrape took {took:.2f} s beside 500 slow connections"
            threads, descriptors = _threads_and_descriptors(exporter.proc.pid)
            assert threads <= 8, f"{threads} threads for 500 slow connections"
            assert descriptors <= 300, f"{descriptors} descriptors held"
        finally:
            for sock in slow:
                sock.close()


def test_when_descriptors_run_short_a_scrape_is_answered_and_no_core_spins(tmp_path, maps):
    """Issue 40.4: when file descriptors ran out, no scrape was answered and the exporter spun
    a full core on accept's EMFILE.  The exporter here has 64 descriptors; 200 connections
    come and stay."""

    def few_descriptors() -> None:
        signals_as_from_a_shell()
        resource.setrlimit(resource.RLIMIT_NOFILE, (64, 64))

    with exporting(
        "--maps", maps, "--allow-target", "tcp://127.0.0.1:*", tmp_path=tmp_path, preexec_fn=few_descriptors
    ) as exporter:
        where = address(exporter)
        held = []
        try:
            for _ in range(200):
                held.append(socket.create_connection(where, timeout=5))
            time.sleep(0.3)
            before = _cpu_seconds(exporter.proc.pid)
            time.sleep(1.0)
            spent = _cpu_seconds(exporter.proc.pid) - before
            assert spent < 0.3, f"the exporter spent {spent:.2f} s of CPU in 1 s, holding connections"
            status, _, text = exporter.get("/metrics", timeout=5)
            assert status == 200 and "process_open_fds" in text
        finally:
            for sock in held:
                sock.close()


@contextlib.contextmanager
def serving_here(monkeypatch, **timing):
    """The exporter's HTTP server in this process (its index page only), with its deadlines
    as ``timing`` says: the address it listens on."""
    from mbtool.cli import http_server
    from mbtool.cli.commands.exporter import Exporter, open_server

    for name, seconds in timing.items():
        monkeypatch.setattr(http_server, name, seconds)
    server = open_server("127.0.0.1", 0, socket.AF_INET, Exporter(None, None))
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield server.server_address[:2]
    finally:
        server.shutdown()
        thread.join(10)
        server.server_close()
        assert not thread.is_alive()


def test_a_request_head_must_come_whole_within_its_deadline(monkeypatch):
    """Issue 40.4 (slowloris): a head trickled in a byte at a time is cut off at its deadline,
    however often bytes come; a whole one, sent at once, is answered."""
    with serving_here(monkeypatch, HEAD_DEADLINE=0.5) as where:
        with socket.create_connection(where, timeout=5) as sock:
            began = time.monotonic()
            closed = False
            for byte in b"GET / HTTP/1.1\r\nHost: x\r\nX-Slow: " + b"y" * 100:
                try:
                    sock.sendall(bytes([byte]))
                except (BrokenPipeError, ConnectionResetError):
                    closed = True
                    break
                time.sleep(0.05)
                if time.monotonic() - began > 3:
                    break
            if not closed:
                sock.settimeout(1)
                with contextlib.suppress(ConnectionResetError):
                    closed = sock.recv(100) == b""
            took = time.monotonic() - began
        assert closed and took < 2.0, f"a trickled head was held {took:.2f} s past a 0.5 s deadline"
        raw, _ = exchange(where, b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
        assert raw.startswith(b"HTTP/1.1 200 "), raw


def test_connections_past_the_cap_each_drop_the_longest_waiting_and_the_loop_goes_on(monkeypatch):
    """More connections than the cap, each sending at once: every new one drops the one that
    has waited longest (a drop in the same round as that one's bytes must not stop the loop),
    and a whole request still gets its answer."""
    from mbtool.cli import http_server

    monkeypatch.setattr(http_server, "max_connections", lambda: 4)
    with serving_here(monkeypatch) as where:
        held = []
        try:
            for _ in range(300):
                sock = socket.create_connection(where, timeout=5)
                sock.sendall(b"GET / HTTP/1.1\r\n")
                held.append(sock)
            raw, _ = exchange(where, b"GET / HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n")
            assert raw.startswith(b"HTTP/1.1 200 "), raw
            open_ones = 0
            for sock in held:
                sock.settimeout(0.5)
                try:
                    open_ones += sock.recv(1) != b""
                except TimeoutError:
                    open_ones += 1
                except ConnectionResetError:
                    pass
            assert open_ones <= 4
        finally:
            for sock in held:
                sock.close()
