#!/usr/bin/env python3
"""Exporter fuzz and DoS: ``mbtool exporter`` with an inventory and ``--allow-target`` patterns,
fed HTTP no Prometheus sends, over raw sockets (issue 40.1-4, 15, 16).

The exporter polls an inventory (a link to ``mbtool serve``, whose /modbus scrapes are then
refused with 409, and a ``sim://`` link) and reads the map ``meter`` from targets its patterns
allow (``tcp://127.0.0.1:*``, ``*:PORT`` of a second ``mbtool serve``, ``/dev/ttyUSB*``,
``/dev/serial/by-id/*``).  Phases:

* fuzz: random requests, each on a connection of its own whose sending side is then shut:
  well-formed scrapes of /metrics and /modbus; /modbus with hostile targets (pyserial URL
  handlers such as ``spy://...?file=CANARY``, paths that climb out of an allowed folder, other
  spellings of allowed and inventory targets, ports out of range, very long and binary text),
  hostile modules and units, parameters given twice; random scrape-timeout headers (0,
  negative, nan, 1e400, 9.3e9...); random methods; bad request lines; huge headers; bodies,
  chunked bodies and a request smuggled behind a ``Content-Length``; several requests
  pipelined on one connection; random paths and query strings;
* targets: /modbus scrapes of 2,000 different targets (ports nobody listens on), for the lock
  table;
* slowloris: 300 connections trickling their request head a byte a second for 12 s while a
  well-behaved scraper scrapes /metrics and /modbus every half second;
* storm: 1,500 connections opened at once and left silent, then a scrape.

RSS and threads of the exporter are sampled from /proc/PID/status throughout.  Faults: a 5xx
answer (a 503 only counts outside the storm); an internal error or a traceback on stderr; an
answer that did not come within the scrape's deadline (its header, clamped as the exporter
clamps it, or 10 s) plus slack, or a connection the exporter held past its own deadlines; a
/modbus 200 whose body prometheus_client cannot parse, or a 200 for a target that must be
refused; more answers on a connection than requests that may be answered (smuggling); a
well-behaved scrape unanswered during slowloris or after the storm; RSS grown past
``--rss-limit`` MB between the end of the first fuzz quarter and the end, or threads still
above the idle count by more than 4 at the end (or past 64 at any time); a file in the canary
folder created, changed or truncated, or one in the exporter's working folder.
"""

from __future__ import annotations

import contextlib
import math
import random
import re
import socket
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import common

SLACK = 3.0  # seconds an answer may come past its deadline on a loaded two-core machine
MAX_SCRAPE = 300.0  # the exporter's MAX_SCRAPE_TIMEOUT
DEFAULT_SCRAPE = 10.0
THREADS_CEILING = 64


def thread_count(pid: int) -> int | None:
    try:
        with open(f"/proc/{pid}/status") as status:
            for line in status:
                if line.startswith("Threads:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


class Sampler(threading.Thread):
    """RSS (KiB) and threads of the exporter every 50 ms: the peaks, and a figure on demand."""

    def __init__(self, pid: int) -> None:
        super().__init__(name="sampler", daemon=True)
        self.pid = pid
        self.peak_rss = 0
        self.peak_threads = 0
        self.stopping = threading.Event()

    def run(self) -> None:
        while not self.stopping.wait(0.05):
            rss, threads = common.rss_kb(self.pid), thread_count(self.pid)
            if rss is None or threads is None:
                return
            self.peak_rss = max(self.peak_rss, rss)
            self.peak_threads = max(self.peak_threads, threads)

    def now(self) -> tuple[int, int]:
        return common.rss_kb(self.pid) or 0, thread_count(self.pid) or 0


def effective_timeout(header: str | None) -> float:
    """What the exporter's deadline is for this header (its scrape_deadline, before the margin)."""
    try:
        seconds = float(header) if header is not None and header.strip() else DEFAULT_SCRAPE
    except ValueError:
        seconds = DEFAULT_SCRAPE
    if not 0 < seconds < math.inf:
        seconds = DEFAULT_SCRAPE
    return min(seconds, MAX_SCRAPE)


class Exchange:
    """Raw bytes to the exporter on a connection of their own, the sending side shut, and the
    answers read to the end: (status, headers, body) each."""

    def __init__(self, port: int, data: bytes, deadline: float, heads: list[bytes] | None = None) -> None:
        self.answers: list[tuple[int, bytes, bytes]] = []
        self.head_bodies = 0  # refusals of a HEAD that carry a body
        self.hung = False
        self.error = ""
        self.took = 0.0
        began = time.monotonic()
        with socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            with contextlib.suppress(OSError):
                sock.sendall(data)
                sock.shutdown(socket.SHUT_WR)
            received = b""
            end = began + deadline
            while True:
                left = end - time.monotonic()
                if left <= 0:
                    self.hung = True
                    break
                sock.settimeout(left)
                try:
                    chunk = sock.recv(65536)
                except TimeoutError:
                    self.hung = True
                    break
                except OSError:
                    break  # reset: the exporter closed with bytes unread, as it may
                if not chunk:
                    break
                received += chunk
        self.took = time.monotonic() - began
        self.parse(received, heads or [])

    @classmethod
    def of(cls, data: bytes, methods: list[bytes]) -> Exchange:
        """The answers in ``data`` as if the exporter had sent them (the judge alone)."""
        done = cls.__new__(cls)
        done.answers, done.head_bodies, done.hung, done.error, done.took = [], 0, False, "", 0.0
        done.parse(data, methods)
        return done

    def parse(self, data: bytes, methods: list[bytes]) -> None:
        at = 0
        while at < len(data):
            end = data.find(b"\r\n\r\n", at)
            if end < 0:
                self.error = f"an answer cut in its head: {data[at : at + 200]!r}"
                return
            head = data[at:end]
            found = re.match(rb"HTTP/1\.[01] (\d{3})", head)
            if not found:
                self.error = f"not an HTTP answer: {head[:200]!r}"
                return
            length = re.search(rb"(?im)^content-length:\s*(\d+)", head)
            size = int(length[1]) if length else 0
            index = len(self.answers)
            if index < len(methods) and methods[index] == b"HEAD":
                # a HEAD's answer has no body; a refusal (Connection: close) carries its line
                # all the same, which a client reading to the close takes as what it is
                closing = re.search(rb"(?im)^connection:\s*close", head)
                if closing and end + 4 + size == len(data):
                    self.head_bodies += 1
                else:
                    size = 0
            body = data[end + 4 : end + 4 + size]
            if len(body) < size:
                self.error = f"an answer cut in its body ({len(body)} of {size} bytes)"
            self.answers.append((int(found[1]), head, body))
            at = end + 4 + size


class Campaign:
    def __init__(self, args, report: common.Report, folder: Path) -> None:
        self.args, self.report, self.folder = args, report, folder
        self.rng = random.Random(args.seed)
        self.statuses: Counter[int] = Counter()
        self.requests = 0
        self.head_bodies = 0
        self.canary = folder / "canary"
        self.canary.mkdir()
        (self.canary / "victim.txt").write_text("canary: nothing may touch this file\n")
        self.workdir = folder / "cwd"
        self.workdir.mkdir()
        (folder / "maps").mkdir()
        (folder / "maps" / "meter.toml").write_bytes(
            (common.ROOT / "examples" / "energy-meter.toml").read_bytes()
        )

    # --- the exporter ------------------------------------------------------------------------

    def start(self, plant_target: str, free_target: str) -> None:
        self.plant_target, self.free_target = plant_target, free_target
        self.free_port = int(free_target.rpartition(":")[2])
        inventory = self.folder / "plant.toml"
        inventory.write_text(
            "[poll]\ninterval = 0.2\nmax_backoff = 2\n"
            f'[links.plant]\ntarget = "{plant_target}"\ntimeout = 0.3\n'
            '[links.sim]\ntarget = "sim://"\n'
            '[devices.pump]\nlink = "plant"\nunit = 1\nread = ["40001 4"]\n'
            '[devices.dead]\nlink = "plant"\nunit = 9\nread = ["40001 1"]\n'
            '[devices.twin]\nlink = "sim"\nunit = 1\nread = ["30001 2"]\n'
        )
        self.errors = self.folder / "exporter.err"
        with open(self.errors, "wb") as err:
            self.proc = subprocess.Popen(
                common.argv(
                    "exporter",
                    inventory,
                    "--listen",
                    "127.0.0.1:0",
                    "--maps",
                    self.folder / "maps",
                    "--timeout",
                    "0.3",
                    "--allow-target",
                    "tcp://127.0.0.1:*",
                    "--allow-target",
                    f"*:{self.free_port}",
                    "--allow-target",
                    "/dev/ttyUSB*",
                    "--allow-target",
                    "/dev/serial/by-id/*",
                ),  # fmt: skip
                cwd=self.workdir,
                env=common.env(),
                preexec_fn=common.signals_as_from_a_shell,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=err,
            )
        line = common.first_stream_line(self.proc, self.proc.stdout, "")
        found = re.search(r"127\.0\.0\.1:(\d+)", line)
        if not found:
            common.give_up(f"the exporter said {line!r}, no port")
        self.port = int(found[1])
        self.sampler = Sampler(self.proc.pid)
        self.sampler.start()

    def stop(self) -> None:
        self.sampler.stopping.set()
        code = common.stop(self.proc)
        self.report.figure("exporter's exit on SIGTERM", code)
        if code != 0:
            self.report.fault("exit on SIGTERM not 0", f"exit {code}")
        errors = self.errors.read_text(errors="replace")
        for line in errors.splitlines():
            if "Traceback (most recent call last)" in line or "internal error" in line:
                self.report.fault("traceback or internal error on stderr", errors[-3000:])
                break
        unexpected = [
            line
            for line in errors.splitlines()
            if not re.search(r"\b(dead|pump|twin|plant|sim)\b.*(offline|online|no response|next try)", line)
            and not re.search(r"warning: .*sdm630.toml: point \w+_total: its metric", line)  # the library's
        ]
        self.report.figure("stderr lines (other than the plant's events)", len(unexpected))
        if unexpected:
            self.report.figure("first of them", unexpected[0][:200])

    def figure_now(self, label: str) -> tuple[int, int]:
        rss, threads = self.sampler.now()
        self.report.figure(f"RSS, threads {label}", f"{rss / 1024:.1f} MB, {threads}")
        return rss, threads

    # --- one exchange, judged ---------------------------------------------------------------

    def exchange(
        self,
        data: bytes,
        timeouts: list[str | None],
        methods: list[bytes] | None = None,
        at_most: int | None = None,
        refuse: bool = False,
        storm: bool = False,
    ) -> Exchange:
        """``data`` holds len(timeouts) requests (their scrape-timeout headers); ``at_most``: the
        answers there may be (smuggling); ``refuse``: a /modbus 200 is a fault."""
        deadline = sum(effective_timeout(t) for t in timeouts) + SLACK
        self.requests += max(1, len(timeouts))
        try:
            done = Exchange(self.port, data, deadline, methods)
        except OSError as failed:
            self.report.fault("connection refused or failed", f"{failed}: {data[:300]!r}")
            return None
        shown = f"{data[:400]!r} ({len(data)} bytes), {done.took:.2f} s"
        if done.hung:
            self.report.fault("no answer within the deadline", f"{deadline:.1f} s: {shown}")
        if done.error:
            self.report.fault("a cut or unparsable answer", f"{done.error}: {shown}")
        if len(done.answers) > (at_most if at_most is not None else max(1, len(timeouts))):
            self.report.fault("more answers than requests (smuggling)", f"{len(done.answers)}: {shown}")
        self.head_bodies += done.head_bodies
        for status, _, body in done.answers:
            self.statuses[status] += 1
            if status >= 500 and not (storm and status == 503):
                self.report.fault("a 5xx answer", f"{status} {body[:300]!r}: {shown}")
            if refuse and status == 200:
                self.report.fault("a hostile target read", f"{body[:300]!r}: {shown}")
            if status == 200 and b"modbus_up" in body:
                self.parse(body, shown)
        return done

    def parse(self, body: bytes, shown: str) -> None:
        from prometheus_client.parser import text_string_to_metric_families  # noqa: PLC0415

        try:
            list(text_string_to_metric_families(body.decode()))
        except Exception as error:  # noqa: BLE001 - whatever the parser says is the fault
            self.report.fault("an exposition prometheus_client cannot parse", f"{error}: {shown}")

    # --- the requests ------------------------------------------------------------------------

    def hostile_targets(self) -> list[str]:
        victim = self.canary / "victim.txt"
        new = self.canary / "created.txt"
        port = self.free_port
        return [
            f"spy://127.0.0.1:{port}?file={victim}",
            f"spy://127.0.0.1:{port}?file={victim}&all=:{port}",  # ends as '*:PORT' wants
            f"spy://127.0.0.1:{port}?file={new}&x=:{port}",
            f"spy://localhost:{port}?file={new}",
            f"spy:///dev/ttyUSB0?file={victim}",
            f"SPY://127.0.0.1:{port}?file={victim}",
            f"loop://?x=1&file={victim}",
            "loop://",
            "hwgrep://((",
            "hwgrep://.*",
            f"alt://{victim}?class=Serial",
            "cp2110://0001:0002",
            f"/dev/serial/by-id/../../{victim}",
            f"/dev/serial/by-id/../../../..{victim}",
            f"/dev/ttyUSB0/../../..{victim}",
            "/dev/serial/by-id/../../etc/hostname",
            str(victim),
            f"file://{victim}",
            "/dev/ttyUSB../../etc/passwd",
            "/dev/zero",
            "/dev/watchdog",
            "sim://",
            f"rfc2217://127.0.0.1:{port}",
            f"rfc2217://127.0.0.1:{port}?logging=debug",
        ]

    def other_targets(self) -> list[str]:
        port = self.free_port
        plant_port = self.plant_target.rpartition(":")[2]
        return [
            self.free_target,
            f"tcp://127.0.0.01:{port}",
            f"tcp://127.1:{port}",
            f"tcp://0x7f.0.0.1:{port}",
            f"tcp://2130706433:{port}",
            f"tcp://[::ffff:127.0.0.1]:{port}",
            f"TCP://127.0.0.1:{port}",
            f"socket://127.0.0.1:{port}",
            f"udp://127.0.0.1:{port}",
            f"tls://127.0.0.1:{port}",
            f"rtu+udp://127.0.0.1:{port}",
            f"tcp://localhost:{port}",
            f"tcp://[::1]:{port}",
            f"tcp://127.0.0.1:{port}/",
            f"tcp://127.0.0.1:{port}/../",
            self.plant_target,
            f"tcp://127.1:{plant_port}",
            f"socket://127.0.0.1:{plant_port}",
            f"tcp://127.0.0.1:{self.rng.randrange(1, 65536)}",
            "tcp://127.0.0.1:0",
            "tcp://127.0.0.1:65536",
            "tcp://127.0.0.1:99999999999999999999",
            "tcp://127.0.0.1:-1",
            "tcp://127.0.0.1",
            "tcp://",
            "tcp://[::1",
            "",
            "%00",
            "tcp://127.0.0.1:%00",
            "tcp://127.0.0.1:502\r\nX-Injected: 1",
            "tcp://" + "a" * self.rng.choice([64, 300, 5000]) + ":502",
            "tcp://" + "1." * 2000 + "1:502",
            "tcp://\u2603.example:502",
            "tcp://192.0.2.1:502",
            "foo://bar",
            "udp://0.0.0.0:0",
        ]

    def timeout_header(self) -> str | None:
        return self.rng.choice(
            [None, "0.5", "1", "0.8", "0.3", "0.05", "0", "-1", "nan", "inf", "-inf", "1e400",
             "9.3e9", "9.3e12", "abc", "", " 1 ", "1e-300", "0x10", "\u0661", "0.5, 0.5"]
        )  # fmt: skip

    def modbus_query(self, target: str) -> str:
        from urllib.parse import quote  # noqa: PLC0415

        module = self.rng.choice(
            ["meter"] * 6
            + ["../meter", "/etc/passwd", "meter/..", "nope", "", "sdm630", "METER", "meter.toml"]
        )
        unit = self.rng.choice(["1"] * 6 + ["0", "255", "256", "-1", "abc", "1e3", "", "9"])
        parts = [f"target={quote(target, safe=':/')}", f"module={quote(module)}", f"unit={quote(unit)}"]
        if self.rng.random() < 0.1:
            parts.append(self.rng.choice(parts))  # a parameter twice
        if self.rng.random() < 0.1:
            parts.append(f"{self.rng.choice(['x', 'target[]', '', '%ff'])}={self.rng.randbytes(4).hex()}")
        self.rng.shuffle(parts)
        return "&".join(parts)

    def request(self, method: str, path: str, timeout: str | None, extra: str = "") -> bytes:
        head = f"{method} {path} HTTP/1.1\r\nHost: 127.0.0.1\r\n"
        if timeout is not None:
            head += f"X-Prometheus-Scrape-Timeout-Seconds: {timeout}\r\n"
        return (head + extra + "\r\n").encode("utf-8", "surrogateescape")

    def one(self) -> None:
        """One random request (or a few pipelined) of one of the kinds, judged."""
        rng = self.rng
        kind = rng.choices(
            ["metrics", "modbus", "hostile", "method", "line", "headers", "body", "pipeline", "path"],
            weights=[8, 14, 14, 5, 8, 5, 6, 6, 8],
        )[0]
        timeout = self.timeout_header()
        if kind == "metrics":
            method = rng.choice(["GET", "HEAD"])
            self.exchange(self.request(method, "/metrics", timeout), [timeout], methods=[method.encode()])
        elif kind == "modbus":
            target = rng.choice(self.other_targets())
            self.exchange(self.request("GET", f"/modbus?{self.modbus_query(target)}", timeout), [timeout])
        elif kind == "hostile":
            target = rng.choice(self.hostile_targets())
            self.exchange(
                self.request("GET", f"/modbus?{self.modbus_query(target)}", timeout), [timeout], refuse=True
            )
        elif kind == "method":
            method = rng.choice(
                ["POST", "PUT", "DELETE", "OPTIONS", "TRACE", "CONNECT", "PATCH", "get", "GETT", "BREW",
                 "G\x00T", "M" * 5000, rng.randbytes(6).hex()]
            )  # fmt: skip
            self.exchange(self.request(method, rng.choice(["/metrics", "/modbus", "*", "/"]), None), [None])
        elif kind == "line":
            line = rng.choice(
                [b"GET\r\n\r\n", b"GET / HTTP/9.9\r\nHost: x\r\n\r\n", b"GET /\r\n\r\n", b"\r\n\r\n",
                 b"GET / HTTP/1.1\r\n\r\n", b"GET /metrics HTTP/1.0\r\n\r\n",
                 b"GET /" + b"a" * 100_000 + b" HTTP/1.1\r\nHost: x\r\n\r\n",
                 b"GET /metrics HTTP/1.1\nHost: x\n\n", b"GET  /metrics  HTTP/1.1\r\nHost: x\r\n\r\n",
                 b"GET /metrics HTTP/1.1\r\nHost: x\r\n folded: yes\r\n\r\n",
                 b"GET /metrics HTTP/1.1\r\nHost x\r\n\r\n",
                 b"GET /metrics HTTP/1.1\r\nHost: x\r\nHost: y\r\n\r\n",
                 b"GET http://127.0.0.1/metrics HTTP/1.1\r\nHost: x\r\n\r\n",
                 b"GET /metrics HTTP/1.1\r\nHost: \xff\xfe\r\n\r\n",
                 b"\x16\x03\x01\x00\xa5\x01\x00\x00\xa1\x03\x03" + rng.randbytes(64),
                 rng.randbytes(rng.choice([1, 16, 512, 20_000])),
                 rng.randbytes(64) + b"\r\n\r\n"]
            )  # fmt: skip
            self.exchange(line, [None])
        elif kind == "headers":
            if rng.random() < 0.5:
                extra = f"X-Big: {'a' * rng.choice([8_000, 17_000, 200_000])}\r\n"
            else:
                extra = "".join(f"X-{i}: {i}\r\n" for i in range(rng.choice([100, 1000, 5000])))
            self.exchange(self.request("GET", "/metrics", timeout, extra), [timeout])
        elif kind == "body":
            query = self.modbus_query(self.free_target)
            smuggled = self.request("GET", f"/modbus?{query}", "0.5")
            body = rng.choice([b"hello", smuggled, b"x" * 1_000_000])
            how = rng.choice(["length", "chunked", "both", "zero", "negative", "twice"])
            method = rng.choice(["GET", "POST", "HEAD"])
            if how == "length":
                extra = f"Content-Length: {len(body)}\r\n"
            elif how == "chunked":
                extra, body = "Transfer-Encoding: chunked\r\n", b"%x\r\n%s\r\n0\r\n\r\n" % (len(body), body)
            elif how == "both":
                extra = f"Content-Length: {len(body)}\r\nTransfer-Encoding: chunked\r\n"
            elif how == "zero":
                extra, body = "Content-Length: 0\r\n", smuggled
            elif how == "negative":
                extra = "Content-Length: -1\r\n"
            else:
                extra = f"Content-Length: {len(body)}\r\nContent-Length: {len(body) + 1}\r\n"
            data = self.request(method, "/metrics", None, extra) + body
            # a body is refused with the connection closed: one answer at most, the smuggled
            # request never answered; a Content-Length of 0 is no body, and what follows is
            # the next request (two answers)
            self.exchange(
                data,
                [None, "0.5"] if how == "zero" else [None],
                methods=[method.encode(), b"GET"],
                at_most=2 if how == "zero" else 1,
            )
        elif kind == "pipeline":
            count = rng.randrange(2, 21)
            timeouts = [rng.choice(["0.5", "1", None]) for _ in range(count)]
            parts = []
            for t in timeouts:
                path = rng.choice(
                    ["/metrics", "/", f"/modbus?{self.modbus_query(self.free_target)}", "/nope"]
                )
                parts.append(self.request("GET", path, t if path.startswith("/modbus") else "1"))
            self.exchange(b"".join(parts), [t if t else "1" for t in timeouts])
        else:
            path = rng.choice(
                ["/metrics?x=1", "//metrics", "/metrics/", "/modbus/../metrics", "/%2e%2e/metrics", "*",
                 "/modbus", "/modbus?", "/modbus?&&&", "/modbus?target", "/modbus?%ff%fe=%00",
                 "/" + rng.randbytes(30).hex(), "/\u2603", "/metrics#frag", "/modbus?target=" + "%" * 500]
            )  # fmt: skip
            self.exchange(self.request("GET", path, timeout), [timeout])

    # --- the phases --------------------------------------------------------------------------

    def fuzz(self, count: int, workers: int = 6) -> None:
        """``count`` random requests from ``workers`` threads; RSS measured after the first quarter."""
        lock = threading.Lock()
        left = [count]
        quarter = threading.Event()

        def work() -> None:
            while True:
                with lock:
                    if left[0] <= 0:
                        return
                    left[0] -= 1
                    if left[0] <= count * 3 // 4:
                        quarter.set()
                self.one()

        began = time.monotonic()
        threads = [threading.Thread(target=work, daemon=True) for _ in range(workers)]
        for thread in threads:
            thread.start()
        quarter.wait()
        self.warm_rss, _ = self.figure_now("after a quarter of the fuzz")
        for thread in threads:
            thread.join()
        self.report.figure(
            "fuzz", f"{count} requests from {workers} clients in {time.monotonic() - began:.1f} s"
        )

    def many_targets(self, count: int) -> None:
        """Scrapes of ``count`` targets nobody listens on, each once: the lock table's size."""
        began = time.monotonic()
        ports = self.rng.sample(range(20000, 60000), count)
        before, _ = self.sampler.now()
        for port in ports:
            spelling = self.rng.choice(["tcp://127.0.0.1:{}", "tcp://127.1:{}", "tcp://0x7f.0.0.1:{}"])
            query = f"target={spelling.format(port)}&module=meter"
            self.exchange(self.request("GET", f"/modbus?{query}", "1"), ["1"])
        after, _ = self.sampler.now()
        self.report.figure(
            "targets", f"{count} different targets in {time.monotonic() - began:.1f} s: "
            f"RSS {before / 1024:.1f} -> {after / 1024:.1f} MB",
        )  # fmt: skip

    def scrape_ok(self, what: str) -> bool:
        path = "/metrics" if what == "metrics" else f"/modbus?target={self.free_target}&module=meter&unit=1"
        done = self.exchange(self.request("GET", path, "2"), ["2"])
        return done is not None and not done.hung and [s for s, _, _ in done.answers] == [200]

    def slowloris(self, count: int, seconds: float) -> None:
        socks = []
        for _ in range(count):
            try:
                sock = socket.create_connection(("127.0.0.1", self.port), timeout=5)
                sock.sendall(b"GET /metrics HTTP/1.1\r\n")
                socks.append(sock)
            except OSError:
                break
        answered = asked = 0
        worst = 0.0
        began = time.monotonic()
        while time.monotonic() < began + seconds:
            for sock in socks:
                with contextlib.suppress(OSError):
                    sock.send(b"X")
            for what in ("metrics", "modbus"):
                start = time.monotonic()
                asked += 1
                answered += self.scrape_ok(what)
                worst = max(worst, time.monotonic() - start)
            time.sleep(0.5)
        closed = 0
        for sock in socks:
            sock.setblocking(False)
            try:
                closed += sock.recv(4096) == b""
            except BlockingIOError:
                pass
            except OSError:
                closed += 1
            sock.close()
        _, threads = self.sampler.now()
        self.report.figure(
            "slowloris",
            f"{len(socks)} connections for {seconds:.0f} s: {closed} closed by the exporter; "
            f"scrapes answered {answered} of {asked}, slowest {worst:.2f} s; threads {threads}",
        )
        if answered < asked:
            self.report.fault("a scrape unanswered under slowloris", f"{asked - answered} of {asked}")

    def storm(self, count: int) -> None:
        socks = []
        for _ in range(count):
            try:
                socks.append(socket.create_connection(("127.0.0.1", self.port), timeout=5))
            except OSError:
                break
        time.sleep(0.5)
        start = time.monotonic()
        ok = self.scrape_ok("metrics") and self.scrape_ok("modbus")
        took = time.monotonic() - start
        dropped = 0
        for sock in socks:
            sock.setblocking(False)
            try:
                dropped += sock.recv(4096) == b""
            except BlockingIOError:
                pass
            except OSError:
                dropped += 1
        _, threads = self.sampler.now()
        for sock in socks:
            sock.close()
        self.report.figure(
            "storm",
            f"{len(socks)} silent connections: {dropped} dropped by the exporter; "
            f"scrapes after them {'answered' if ok else 'NOT answered'} in {took:.2f} s; threads {threads}",
        )
        if not ok:
            self.report.fault("a scrape unanswered after the storm", f"{len(socks)} connections")

    def canaries(self, before: dict[str, tuple[int, int, bytes]]) -> None:
        after = snapshot(self.canary)
        if after != before:
            self.report.fault("a file touched outside the allowed targets", f"{before} -> {after}")
        if any(self.workdir.iterdir()):
            self.report.fault("a file created in the exporter's folder", str(list(self.workdir.iterdir())))


def snapshot(folder: Path) -> dict[str, tuple[int, int, bytes]]:
    return {p.name: (p.stat().st_mtime_ns, p.stat().st_size, p.read_bytes()) for p in folder.iterdir()}


def main() -> None:
    args = common.arguments(
        __doc__,
        requests=(int, 12000, "random requests of the fuzz phase"),
        targets=(int, 2000, "different targets scraped once each"),
        rss_limit=(float, 15.0, "MB the exporter's RSS may grow after the first quarter of the fuzz"),
    )
    report = common.Report("exporter fuzz and DoS", args.verbose)
    with (
        common.scratch("exporter") as scratch,
        common.serve("-u", "1-2") as plant,
        common.serve("-u", "1-2", "--data", common.ROOT / "examples" / "energy-meter-data.toml") as free,
    ):
        if not plant.target or not free.target:
            common.give_up("mbtool serve did not say where it listens")
        campaign = Campaign(args, report, Path(scratch))
        before = snapshot(campaign.canary)
        campaign.start(plant.target, free.target)
        try:
            time.sleep(1)
            _, idle_threads = campaign.figure_now("at start")
            campaign.fuzz(args.requests)
            campaign.many_targets(args.targets)
            campaign.slowloris(300, 12)
            campaign.storm(1500)
            time.sleep(1)
            rss, threads = campaign.figure_now("at the end")
            report.figure(
                "RSS, threads peak",
                f"{campaign.sampler.peak_rss / 1024:.1f} MB, {campaign.sampler.peak_threads}",
            )
            report.figure("answers by status", dict(sorted(campaign.statuses.items())))
            report.figure("requests", campaign.requests)
            report.figure("refusals of a HEAD with a body after the head", campaign.head_bodies)
            grown = (rss - campaign.warm_rss) / 1024
            if grown > args.rss_limit:
                report.fault("RSS grew without bound", f"{grown:.1f} MB after the first quarter")
            if threads > idle_threads + 4 or campaign.sampler.peak_threads > THREADS_CEILING:
                report.fault(
                    "threads grew",
                    f"{idle_threads} idle, {threads} at the end, {campaign.sampler.peak_threads} at peak",
                )
        finally:
            campaign.stop()
        campaign.canaries(before)
    report.finish()


if __name__ == "__main__":
    main()
