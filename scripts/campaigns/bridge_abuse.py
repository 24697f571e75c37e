#!/usr/bin/env python3
"""Bridge abuse: ``mbtool bridge`` in front of a pseudo-terminal bus (``mbtool serve`` on the
other end, unit 1), its stdout a pipe that is never read, its RSS sampled from
/proc/PID/status, while a well-behaved Modbus TCP client reads unit 1 throughout and others
abuse it, phase after phase:

* alone: the well-behaved client by itself (its latency here is the baseline);
* bulk: four clients pipelining reads of unit 1 as fast as the bus answers, then two
  pipelining requests for a unit not forwarded, answered 0A at once: thousands of
  transactions a second for the bridge to show on a stdout nobody reads;
* slowloris: clients that connect and never send, drip a request a byte at a time, or send
  half an MBAP header and stop;
* garbage: clients sending random bytes and text that is no Modbus at all;
* malformed: MBAP headers with another protocol id or a length that lies, and PDUs whose
  length does not fit their function code (spec §3: each request's fields), each on its
  own connection; the bus is tapped to see which reached it;
* vanishing: clients that queue requests for an absent unit and go at once; then a new
  client's wait, and the tap says how many of the gone clients' requests reached the bus;
* flood: one client keeping ten requests for an absent unit in flight;
* bus gone: the device on the bus stops for a while, then comes back.

Faults: a malformed request on the bus; RSS grown by more than --rss-limit MB from the end
of "alone" to the end; the well-behaved client's median during the flood at half the
bridge's timeout or more; a new client kept waiting more than twice the timeout after the
vanished clients; no reply once the bus is back; a well-behaved request unanswered outside
"bus gone"; the bridge ending early, a traceback, or not stopping on SIGTERM.
"""

from __future__ import annotations

import contextlib
import random
import socket
import statistics
import struct
import subprocess
import threading
import time
from collections import Counter
from pathlib import Path

import common

TIMEOUT = 0.5  # the bridge's -t: seconds it waits for the bus
ABSENT = 99  # a unit nobody on the bus answers
NOT_FORWARDED = 250  # past --units' default 1-247: answered 0A at once, and shown like any other
RECOVERY = 15.0  # seconds the bridge has to answer again once the bus is back (--silent-hold is 5)
REPLY_DEADLINE = 30.0  # seconds a client waits for a reply before it counts as unanswered
READ = bytes.fromhex("03 0000 000A")  # FC 03: holding registers 0-9


def adu(tid: int, unit: int, pdu: bytes, protocol: int = 0, length: int | None = None) -> bytes:
    """An MBAP frame; ``protocol`` and ``length`` may lie."""
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1 if length is None else length, unit) + pdu


def read_reply(sock: socket.socket, deadline: float) -> tuple[int, int, bytes] | None:
    """(transaction id, unit, PDU) of the next reply; None if the connection closes or the
    deadline passes first."""

    def exactly(size: int) -> bytes | None:
        data = b""
        while len(data) < size:
            left = deadline - time.monotonic()
            if left <= 0:
                return None
            sock.settimeout(left)
            try:
                chunk = sock.recv(size - len(data))
            except (TimeoutError, OSError):
                return None
            if not chunk:
                return None
            data += chunk
        return data

    header = exactly(7)
    if header is None:
        return None
    tid, _, length, unit = struct.unpack(">HHHB", header)
    pdu = exactly(length - 1) if length > 1 else b""
    return None if pdu is None else (tid, unit, pdu)


def connect(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return sock


# --- malformed requests: each with a marker (unit, function, 0x7A, n) to find it on the bus ----


def malformed_cases() -> list[tuple[str, bytes, bytes]]:
    """(what, bytes sent on a new connection, what it would start with on the bus)."""
    cases = []

    def pdu_case(what: str, pdu: bytes) -> None:
        cases.append((what, adu(len(cases) + 1, 1, pdu), bytes([1]) + pdu[:4]))

    def marked(fc: int, *rest: int) -> bytes:
        return bytes([fc, 0x7A, len(cases) + 1, *rest])

    pdu_case("FC 03 one byte short", marked(0x03, 0x00))
    pdu_case("FC 03 one byte over", marked(0x03, 0x00, 0x01, 0xFF))
    pdu_case("FC 01 one byte over", marked(0x01, 0x00, 0x08, 0x00))
    pdu_case("FC 04 two bytes over", marked(0x04, 0x00, 0x01, 0x00, 0x00))
    pdu_case("FC 05 one byte short", marked(0x05, 0xFF))
    pdu_case("FC 06 one byte short", marked(0x06, 0x00))
    pdu_case("FC 16 byte count not 2 x quantity", marked(0x10, 0x00, 0x02, 0x03, 0x00, 0x01, 0x00))
    pdu_case("FC 16 fewer data bytes than its count", marked(0x10, 0x00, 0x02, 0x04, 0x00, 0x01))
    pdu_case("FC 15 byte count not the coils' bytes", marked(0x0F, 0x00, 0x10, 0x01, 0xFF))
    pdu_case("FC 22 one byte short", marked(0x16, 0x00, 0xFF, 0x00))
    pdu_case(
        "FC 23 write byte count not 2 x quantity",
        marked(0x17, 0x00, 0x01, 0x7A, 0x40, 0x00, 0x01, 0x04, 0x00, 0x01),
    )
    pdu_case("function code with the exception bit", marked(0x83, 0x00, 0x01))
    # MBAP headers that lie: the PDU after them would read well.
    n = len(cases) + 1
    cases.append(
        (
            "MBAP protocol id 1",
            adu(n, 1, bytes([0x03, 0x7A, n, 0x00, 0x01]), protocol=1),
            bytes([1, 0x03, 0x7A, n]),
        )
    )
    n += 1
    cases.append(
        ("MBAP length 0", adu(n, 1, bytes([0x03, 0x7A, n, 0x00, 0x01]), length=0), bytes([1, 0x03, 0x7A, n]))
    )
    n += 1
    cases.append(
        (
            "MBAP length 1 (no PDU)",
            adu(n, 1, b"", length=1) + bytes([0x03, 0x7A, n, 0x00, 0x01]),
            bytes([1, 0x03, 0x7A, n]),
        )
    )
    n += 1
    # A length 1 short: the PDU read is FC 03 without its last byte.
    cases.append(
        (
            "MBAP length one short",
            adu(n, 1, bytes([0x03, 0x7A, n, 0x00, 0x01]), length=5),
            bytes([1, 0x03, 0x7A, n]),
        )
    )
    n += 1
    cases.append(
        (
            "MBAP length 300",
            adu(n, 1, bytes([0x03, 0x7A, n, 0x00, 0x01]) + bytes(300), length=300),
            bytes([1, 0x03, 0x7A, n]),
        )
    )
    return cases


# --- the processes ---------------------------------------------------------------------------


class BusDevice:
    """``mbtool serve`` for unit 1 on the device end of the pty pair; it can be stopped and
    started again (a device switched off and on)."""

    def __init__(self, pair: common.PtyPair) -> None:
        self.pair = pair
        self.proc: subprocess.Popen | None = None

    def start(self) -> None:
        self.proc = common.popen(
            "serve", "-q", "-p", self.pair.device_path, *common.PTY_SERIAL_OPTS, "-b", "115200", "-u", "1"
        )
        common.first_stream_line(self.proc, self.proc.stdout, "serving ")

    def stop(self) -> None:
        if self.proc is not None:
            common.stop(self.proc)
            self.proc.stdout.close()
            self.proc.stderr.close()
            self.proc = None


class Bridge:
    """``mbtool bridge`` on a free loopback port, its stdout a pipe nobody reads."""

    def __init__(self, pair: common.PtyPair, folder: Path) -> None:
        self.errors = folder / "bridge.err"
        with open(self.errors, "wb") as err:
            self.proc = common.popen(
                "bridge",
                "--listen",
                "tcp://127.0.0.1:0",
                "-p",
                pair.mbtool_path,
                *common.PTY_SERIAL_OPTS,
                "-b",
                "115200",
                "-t",
                TIMEOUT,
                "-o",
                "plain",
                stderr=err,
            )
        end = time.monotonic() + 20
        while time.monotonic() < end and "\n" not in self.stderr():
            if self.proc.poll() is not None:
                break
            time.sleep(0.05)
        line = self.stderr().split("\n")[0]
        if not line.startswith("bridging tcp://"):
            self.proc.kill()
            common.give_up(f"the bridge did not start: {self.stderr()!r}")
        self.port = int(line.split()[1].rpartition(":")[2])

    def stderr(self) -> str:
        return self.errors.read_text(errors="replace")

    def stop(self) -> int | None:
        """SIGTERM; its exit code, None if it did not stop within 30 s (then it is killed)."""
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
            return None
        finally:
            self.proc.stdout.close()  # only now: the pipe was never read
        return self.proc.returncode


class RssSampler(threading.Thread):
    def __init__(self, pid: int) -> None:
        super().__init__(name="rss", daemon=True)
        self.pid = pid
        self.samples: list[tuple[float, int]] = []
        self.stopping = threading.Event()

    def run(self) -> None:
        while not self.stopping.wait(0.25):
            rss = common.rss_kb(self.pid)
            if rss is None:
                return
            self.samples.append((time.monotonic(), rss))

    def now(self) -> int:
        rss = common.rss_kb(self.pid)
        return rss if rss is not None else (self.samples[-1][1] if self.samples else 0)


# --- the clients -----------------------------------------------------------------------------


class Tally:
    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.sent = Counter()  # requests sent, by who sent them
        self.answered = Counter()

    def add(self, who: str, sent: int = 0, answered: int = 0) -> None:
        with self.lock:
            self.sent[who] += sent
            self.answered[who] += answered


class WellBehaved(threading.Thread):
    """Reads unit 1 one request at a time, a little apart, tagging each latency with the phase."""

    def __init__(self, port: int, tally: Tally) -> None:
        super().__init__(name="well-behaved", daemon=True)
        self.port, self.tally = port, tally
        self.phase = "alone"
        self.latencies: dict[str, list[float]] = {}
        self.unanswered = Counter()  # by phase
        self.exceptions = Counter()  # by phase: 0B, 0A ...
        self.last_reply = 0.0  # when the last reply that was no exception came
        self.stopping = threading.Event()

    def run(self) -> None:
        sock, tid = None, 0
        while not self.stopping.is_set():
            phase = self.phase
            try:
                sock = sock or connect(self.port)
                tid = (tid + 1) & 0xFFFF
                began = time.monotonic()
                sock.sendall(adu(tid, 1, READ))
                self.tally.add("well-behaved", sent=1)
                reply = read_reply(sock, began + REPLY_DEADLINE)
                while reply is not None and reply[0] != tid:  # a reply to an earlier request
                    reply = read_reply(sock, began + REPLY_DEADLINE)
            except OSError:
                reply = None
            if reply is None:
                self.unanswered[phase] += 1
                with contextlib.suppress(OSError, AttributeError):
                    sock.close()
                sock = None
            else:
                self.tally.add("well-behaved", answered=1)
                self.latencies.setdefault(phase, []).append(time.monotonic() - began)
                if reply[2][0] & 0x80:
                    self.exceptions[f"{phase}: {reply[2][1]:02X}"] += 1
                else:
                    self.last_reply = time.monotonic()
            self.stopping.wait(0.02)
        with contextlib.suppress(OSError, AttributeError):
            sock.close()


def pipeline(
    port: int, unit: int, address: int, outstanding: int, until: threading.Event, tally: Tally, who: str
) -> None:
    """Keeps ``outstanding`` requests in flight until ``until`` is set."""
    try:
        sock = connect(port)
    except OSError:
        return
    pdu = bytes([0x03]) + address.to_bytes(2, "big") + bytes([0x00, 0x01])
    tid = 0
    with sock:
        try:
            for _ in range(outstanding):
                tid = (tid + 1) & 0xFFFF
                sock.sendall(adu(tid, unit, pdu))
                tally.add(who, sent=1)
            while not until.is_set():
                if read_reply(sock, time.monotonic() + REPLY_DEADLINE) is None:
                    return
                tally.add(who, answered=1)
                tid = (tid + 1) & 0xFFFF
                sock.sendall(adu(tid, unit, pdu))
                tally.add(who, sent=1)
        except OSError:
            return


def slowloris(port: int, until: threading.Event) -> None:
    """Ten clients that never send, ten that drip a request a byte at a time, ten that send
    half an MBAP header; reconnecting when closed."""
    request = adu(1, 1, READ)
    socks: list[tuple[str, socket.socket | None, int]] = []
    for kind in ("silent", "drip", "half") * 10:
        socks.append((kind, None, 0))
    while not until.is_set():
        for i, (kind, sock, sent) in enumerate(socks):
            try:
                if sock is None:
                    sock = connect(port)
                    sent = 0
                    if kind == "half":
                        sock.sendall(request[:3])
                elif kind == "drip":
                    sock.sendall(request[sent % len(request) : sent % len(request) + 1])
                    sent += 1
            except OSError:
                with contextlib.suppress(OSError, AttributeError):
                    sock.close()
                sock = None
            socks[i] = (kind, sock, sent)
        until.wait(0.3)
    for _, sock, _ in socks:
        with contextlib.suppress(OSError, AttributeError):
            sock.close()


def garbage(port: int, until: threading.Event, rng: random.Random) -> int:
    """Random bytes and text that is no Modbus, reconnecting when closed: the bytes sent."""
    sent = 0
    texts = [
        b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",
        b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03",
        b":010300000001FB\r\n",
    ]
    while not until.is_set():
        try:
            with connect(port) as sock:
                for _ in range(20):
                    if until.is_set():
                        break
                    data = (
                        rng.choice(texts)
                        if rng.random() < 0.2
                        else rng.randbytes(rng.choice([7, 260, 4096, 65536]))
                    )
                    sock.sendall(data)
                    sent += len(data)
                    until.wait(0.01)
        except OSError:
            until.wait(0.05)
    return sent


def send_malformed(port: int, cases, tally: Tally) -> None:
    """Each case on its own connection: sent, a reply (or the end) awaited, closed."""
    for _, data, _ in cases:
        try:
            with connect(port) as sock:
                sock.sendall(data)
                tally.add("malformed", sent=1)
                if read_reply(sock, time.monotonic() + 3 * TIMEOUT) is not None:
                    tally.add("malformed", answered=1)
        except OSError:
            pass


def vanish(port: int, clients: int, each: int, tally: Tally) -> list[bytes]:
    """Clients that queue requests for the absent unit and close at once: the markers of
    their requests, to look for on the bus."""
    markers = []
    for c in range(clients):
        with contextlib.suppress(OSError), connect(port) as sock:
            burst = b""
            for r in range(each):
                n = c * each + r
                burst += adu(n + 1, ABSENT, bytes([0x03, 0x7B, n, 0x00, 0x01]))
                markers.append(bytes([ABSENT, 0x03, 0x7B, n]))
            sock.sendall(burst)
            tally.add("vanishing", sent=each)
    return markers


def one_request(port: int) -> float | None:
    """The wait of a new client's first read of unit 1; None if no reply came."""
    try:
        with connect(port) as sock:
            began = time.monotonic()
            sock.sendall(adu(1, 1, READ))
            reply = read_reply(sock, began + REPLY_DEADLINE * 2)
            return None if reply is None else time.monotonic() - began
    except OSError:
        return None


def median_ms(values: list[float]) -> str:
    return f"{statistics.median(values) * 1000:.1f} ms ({len(values)} requests)" if values else "no replies"


def main() -> None:
    args = common.arguments(
        __doc__,
        seconds=(float, 60.0, "the campaign's length, shared out among its phases"),
        rss_limit=(float, 10.0, "MB the bridge's RSS may grow from the end of 'alone' to the end"),
    )
    rng = random.Random(args.seed)
    report = common.Report("bridge abuse", args.verbose)
    share = args.seconds / 60
    tally = Tally()
    pair = common.PtyPair()
    device = BusDevice(pair)
    with common.scratch("bridge") as folder:
        device.start()
        bridge = Bridge(pair, Path(folder))
        rss = RssSampler(bridge.proc.pid)
        rss.start()
        good = WellBehaved(bridge.port, tally)
        good.start()
        try:
            time.sleep(5 * share)
            rss_start = rss.now()

            # Reads of unit 1 over the bus; then requests for a unit not forwarded, answered at
            # once: the most transactions a second the bridge has to show.
            for phase, unit, outstanding, clients, seconds in (
                ("bulk", 1, 8, 4, 8),
                ("bulk, not forwarded", NOT_FORWARDED, 16, 2, 10),
            ):
                good.phase = phase
                until = threading.Event()
                workers = [
                    threading.Thread(
                        target=pipeline,
                        args=(bridge.port, unit, 0, outstanding, until, tally, phase),
                        daemon=True,
                    )
                    for _ in range(clients)
                ]
                for worker in workers:
                    worker.start()
                time.sleep(seconds * share)
                until.set()
                for worker in workers:
                    worker.join(REPLY_DEADLINE + 5)
            rss_after_bulk = rss.now()

            good.phase = "slowloris"
            until = threading.Event()
            worker = threading.Thread(target=slowloris, args=(bridge.port, until), daemon=True)
            worker.start()
            time.sleep(6 * share)
            until.set()
            worker.join(10)

            good.phase = "garbage"
            until = threading.Event()
            flooded = []
            workers = [
                threading.Thread(target=lambda: flooded.append(garbage(bridge.port, until, rng)), daemon=True)
                for _ in range(3)
            ]
            for worker in workers:
                worker.start()
            time.sleep(6 * share)
            until.set()
            for worker in workers:
                worker.join(10)

            good.phase = "malformed"
            cases = malformed_cases()
            pair.clear()
            send_malformed(bridge.port, cases, tally)
            on_bus = pair.sent_by_mbtool(settle=2 * TIMEOUT)
            reached = [what for what, _, marker in cases if marker in on_bus]

            good.phase = "vanishing"
            pair.clear()
            markers = vanish(bridge.port, 5, 4, tally)
            wait_after = one_request(bridge.port)
            time.sleep(len(markers) * TIMEOUT + 1)  # every gone request's time on the bus, at worst
            on_bus = pair.sent_by_mbtool()
            gone_reached = sum(marker in on_bus for marker in markers)

            good.phase = "flood"
            until = threading.Event()
            worker = threading.Thread(
                target=pipeline, args=(bridge.port, ABSENT, 0x7C00, 10, until, tally, "flood"), daemon=True
            )
            worker.start()
            time.sleep(10 * share)
            until.set()
            worker.join(REPLY_DEADLINE + 5)

            good.phase = "bus gone"
            device.stop()
            time.sleep(3 * share)
            device.start()
            good.phase = "bus back"
            back = time.monotonic()
            while good.last_reply < back and time.monotonic() < back + RECOVERY:
                time.sleep(0.05)
            recovery = good.last_reply - back if good.last_reply >= back else None
            time.sleep(1)
        finally:
            good.stopping.set()
            good.join(REPLY_DEADLINE + 5)
            rss_end = rss.now()
            alive = bridge.proc.poll() is None
            rss.stopping.set()
            code = bridge.stop()
            device.stop()
            pair.close()
        errors = bridge.stderr()
    peak = max((kb for _, kb in rss.samples), default=0)
    lat = good.latencies
    lost = sum(n for phase, n in good.unanswered.items() if phase not in ("bus gone", "bus back"))
    flood_median = statistics.median(lat["flood"]) if lat.get("flood") else float("inf")

    report.figure(
        "requests sent",
        f"{sum(tally.sent.values())} ({', '.join(f'{k} {n}' for k, n in tally.sent.items())})",
    )
    report.figure("requests answered", sum(tally.answered.values()))
    report.figure("garbage sent", f"{sum(flooded) / 1e6:.1f} MB")
    report.figure("RSS start (end of 'alone')", f"{rss_start / 1024:.1f} MB")
    report.figure("RSS after bulk", f"{rss_after_bulk / 1024:.1f} MB")
    report.figure("RSS peak", f"{peak / 1024:.1f} MB")
    report.figure(
        "RSS end",
        f"{rss_end / 1024:.1f} MB (grew {(rss_end - rss_start) / 1024:.1f} MB; limit {args.rss_limit})",
    )
    report.figure("malformed requests that reached the bus (must be 0)", f"{len(reached)} of {len(cases)}")
    report.figure("gone clients' requests that reached the bus", f"{gone_reached} of {len(markers)}")
    report.figure(
        "a new client's wait after them",
        "no reply" if wait_after is None else f"{wait_after * 1000:.0f} ms (limit {2 * TIMEOUT * 1000:.0f})",
    )
    for phase in ("alone", "bulk", "bulk, not forwarded", "slowloris", "garbage", "flood"):
        report.figure(f"well-behaved median latency, {phase}", median_ms(lat.get(phase, [])))
    report.figure("well-behaved requests unanswered outside 'bus gone' (must be 0)", lost)
    report.figure("well-behaved exception replies", dict(good.exceptions) or "none")
    report.figure(
        "the first reply once the bus was back",
        f"after {recovery:.1f} s" if recovery is not None else f"none within {RECOVERY:g} s",
    )
    report.figure("bridge", f"{'running' if alive else 'ENDED EARLY'} until stopped; SIGTERM -> exit {code}")

    if reached:
        report.fault("malformed request on the bus", ", ".join(reached))
    if (rss_end - rss_start) / 1024 > args.rss_limit:
        report.fault("memory grew", f"RSS {rss_start} kB -> {rss_end} kB (peak {peak} kB)")
    if flood_median >= TIMEOUT / 2:
        report.fault("a flooder slows the others", f"median {flood_median * 1000:.0f} ms during the flood")
    if wait_after is None or wait_after > 2 * TIMEOUT:
        report.fault("gone clients' requests kept a new client waiting", f"{wait_after}")
    if recovery is None:
        report.fault("no reply once the bus was back", f"{dict(good.exceptions)} {dict(good.unanswered)}")
    if lost:
        report.fault("well-behaved request unanswered", f"{dict(good.unanswered)}")
    if not alive:
        report.fault("bridge ended early", errors[-2000:])
    if "Traceback (most recent call last)" in errors:
        report.fault("traceback", errors[-3000:])
    if code is None:
        report.fault("bridge did not stop on SIGTERM", errors[-1000:])
    report.finish()


if __name__ == "__main__":
    main()
