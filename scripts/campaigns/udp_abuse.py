#!/usr/bin/env python3
"""UDP abuse: ``mbtool serve`` and ``mbtool bridge`` on ``udp://`` and ``rtu+udp://`` fed datagrams
no Modbus client sends (issue 40.6).  Each front in turn: ``serve`` alone, and ``bridge`` in front
of a pseudo-terminal bus (``mbtool serve`` on its far end, unit 1, 115200 baud):

* packed: datagrams of up to 60 KB packed with the biggest read there is (FC 03, 125 registers),
  each followed by a lone read from the same socket: the replies to a packed datagram, their
  bytes beside its bytes (the amplification a forged sender would get), and the lone reads
  answered;
* garbage: random datagrams of 1 to 65,507 bytes, and the replies they got;
* hold-up (bridge): an attacker sending a packed datagram every 50 ms while a well-behaved
  master reads one register at a time from another address: its median and longest wait;
* flood (bridge with --udp-rate 20): an attacker sending lone reads as fast as it can from
  127.0.0.1, the master reading from 127.0.0.2: the attacker's replies a second, the master's
  median wait and its reads unanswered;
* SIGTERM (bridge) in the middle of the packed datagrams: the time to exit 0.

Faults: more than one reply to a datagram (or reply bytes past the datagram's); a lone read
unanswered; the master's median wait in "hold-up" at half the bridge's timeout or more; the
attacker answered past twice --udp-rate; the master's reads unanswered in "flood" past 5 %;
SIGTERM taking more than a second or not exit 0; a traceback.
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
from pathlib import Path

import common
from bridge_abuse import BusDevice

TIMEOUT = 0.5  # the bridge's -t
RATE = 20  # --udp-rate of the flood phase
BIGGEST_READ = bytes.fromhex("03 0000 007D")
LONE_READ = bytes.fromhex("03 0000 0001")
DATAGRAM = 60_000  # bytes of a packed datagram, about the issue's


def crc16(data: bytes) -> bytes:
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


def adu(scheme: str, tid: int, pdu: bytes) -> bytes:
    if scheme == "udp":
        return struct.pack(">HHHB", tid, 0, len(pdu) + 1, 1) + pdu
    frame = bytes([1]) + pdu
    return frame + crc16(frame)


def is_lone_reply(scheme: str, reply: bytes) -> bool:
    pdu = reply[7:] if scheme == "udp" else reply[1:-2]
    return pdu[:2] == bytes([0x03, 0x02])


def packed(scheme: str) -> bytes:
    one = adu(scheme, 1, BIGGEST_READ)
    return one * (DATAGRAM // len(one))


def udp_socket(host: str = "127.0.0.1") -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    return sock


class Front:
    """``serve`` or ``bridge`` listening on a UDP port; its stderr in a file."""

    def __init__(self, kind: str, scheme: str, folder: Path, bus: str | None, *more: object) -> None:
        self.kind = kind
        self.errors = folder / f"{kind}-{scheme}-{time.monotonic_ns()}.err"
        where = f"{scheme}://127.0.0.1:0"
        with open(self.errors, "wb") as err:
            if kind == "serve":
                self.proc = common.popen("serve", "-q", "-p", where, *more, stderr=err)
                line = common.first_stream_line(self.proc, self.proc.stdout, "serving ")
            else:
                self.proc = common.popen(
                    "bridge", "--listen", where, "-p", bus, *common.PTY_SERIAL_OPTS, "-b", "115200",
                    "-t", TIMEOUT, "-q", *more, stderr=err, stdout=subprocess.DEVNULL,
                )  # fmt: skip
                line = ""
                end = time.monotonic() + 20
                while time.monotonic() < end and "\n" not in (line := self.stderr()):
                    if self.proc.poll() is not None:
                        break
                    time.sleep(0.05)
                if not line.startswith("bridging "):
                    self.proc.kill()
                    self.proc.wait(5)
                    raise RuntimeError(f"the bridge did not start: {line.strip()!r}")
        self.port = int(line.split()[1].rpartition(":")[2])

    def stderr(self) -> str:
        return self.errors.read_text(errors="replace")

    def stop(self) -> tuple[int | None, float]:
        """SIGTERM: (exit code, None if it had to be killed; seconds it took)."""
        began = time.monotonic()
        self.proc.terminate()
        try:
            code = self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
            code = None
        took = time.monotonic() - began
        if self.proc.stdout:
            self.proc.stdout.close()
        return code, took


def amplification(front: Front, scheme: str, rounds: int, report: common.Report, name: str) -> None:
    """Packed datagrams, each followed by a lone read: replies and bytes back per datagram."""
    data = packed(scheme)
    most_replies, most_bytes, unanswered = 0, 0, 0
    with udp_socket() as sock:
        for _ in range(rounds):
            sock.sendto(data, ("127.0.0.1", front.port))
            sock.sendto(adu(scheme, 0xFFFF, LONE_READ), ("127.0.0.1", front.port))
            replies, answered = [], False
            end = time.monotonic() + 3
            while time.monotonic() < end and not answered:
                sock.settimeout(max(0.01, end - time.monotonic()))
                try:
                    reply, _ = sock.recvfrom(65536)
                except TimeoutError:
                    break
                if is_lone_reply(scheme, reply):
                    answered = True
                else:
                    replies.append(reply)
            unanswered += not answered
            most_replies = max(most_replies, len(replies))
            most_bytes = max(most_bytes, sum(map(len, replies)))
    lone = len(adu(scheme, 1, BIGGEST_READ))
    report.figure(
        f"{name}: packed datagrams of {len(data)} bytes ({len(data) // lone} reads)",
        f"{rounds}: at most {most_replies} replies, {most_bytes} bytes back "
        f"({most_bytes / len(data):.4f} x); lone reads unanswered {unanswered}",
    )
    if most_replies > 1 or most_bytes > len(data):
        report.fault(
            "more than one reply to a datagram", f"{name}: {most_replies} replies, {most_bytes} bytes"
        )
    if unanswered:
        report.fault("a lone read unanswered", f"{name}: {unanswered} of {rounds}")


def garbage(front: Front, count: int, rng: random.Random, report: common.Report, name: str) -> None:
    replies = sent = 0
    with udp_socket() as sock:
        sock.settimeout(0.01)
        for _ in range(count):
            data = rng.randbytes(rng.choice([1, 7, 12, 260, 4096, 65507]))
            sock.sendto(data, ("127.0.0.1", front.port))
            sent += len(data)
            with contextlib.suppress(TimeoutError):
                while True:
                    sock.recvfrom(65536)
                    replies += 1
    report.figure(f"{name}: garbage datagrams", f"{count} ({sent / 1e6:.1f} MB): {replies} replies")
    if replies > count:
        report.fault(
            "more than one reply to a datagram", f"{name}: {replies} replies to {count} garbage datagrams"
        )


class Master(threading.Thread):
    """Reads one register at a time from ``host``, a little apart: its waits, its reads unanswered."""

    def __init__(self, port: int, scheme: str, host: str) -> None:
        super().__init__(name="master", daemon=True)
        self.port, self.scheme, self.host = port, scheme, host
        self.waits: list[float] = []
        self.unanswered = 0
        self.stopping = threading.Event()

    def run(self) -> None:
        with udp_socket(self.host) as sock:
            tid = 0
            while not self.stopping.is_set():
                tid = tid % 0xFFFE + 1
                began = time.monotonic()
                sock.sendto(adu(self.scheme, tid, LONE_READ), ("127.0.0.1", self.port))
                answered = False
                while not answered and time.monotonic() < began + 2:
                    sock.settimeout(max(0.01, began + 2 - time.monotonic()))
                    try:
                        reply, _ = sock.recvfrom(512)
                    except TimeoutError:
                        break
                    answered = self.scheme != "udp" or reply[:2] == tid.to_bytes(2, "big")
                if answered:
                    self.waits.append(time.monotonic() - began)
                else:
                    self.unanswered += 1
                self.stopping.wait(0.02)


def attack(
    port: int, data: bytes, pause: float, until: threading.Event, host: str = "127.0.0.1"
) -> list[int]:
    """Sends ``data`` every ``pause`` seconds (0: as fast as it can) until ``until``; counts the
    datagrams sent and the replies it got (in a list, for the caller to read after)."""
    counts = [0, 0]
    with udp_socket(host) as sock:
        sock.setblocking(False)
        while not until.is_set():
            with contextlib.suppress(BlockingIOError):
                sock.sendto(data, ("127.0.0.1", port))
                counts[0] += 1
            with contextlib.suppress(BlockingIOError):
                while True:
                    sock.recvfrom(65536)
                    counts[1] += 1
            if pause:
                until.wait(pause)
            else:
                time.sleep(0.0002)  # the loopback's buffer is the limit, not this loop
    return counts


def ms(values: list[float]) -> str:
    if not values:
        return "no replies"
    return f"median {statistics.median(values) * 1000:.1f} ms, max {max(values) * 1000:.0f} ms ({len(values)} reads)"


def hold_up(front: Front, scheme: str, report: common.Report, name: str, share: float) -> None:
    """A packed datagram every 50 ms against a master's reads from another address; then
    SIGTERM with the attack going on."""
    master = Master(front.port, scheme, "127.0.0.2")
    until = threading.Event()
    attacker = threading.Thread(target=attack, args=(front.port, packed(scheme), 0.05, until), daemon=True)
    master.start()
    attacker.start()
    time.sleep(6 * share)
    code, took = front.stop()
    until.set()
    master.stopping.set()
    attacker.join(5)
    master.join(5)
    report.figure(f"{name}: hold-up, the master's wait", ms(master.waits))
    report.figure(f"{name}: SIGTERM during the attack", f"exit {code} in {took * 1000:.0f} ms")
    median = statistics.median(master.waits) if master.waits else float("inf")
    if median >= TIMEOUT / 2:
        report.fault("a packed datagram holds another master up", f"{name}: {ms(master.waits)}")
    if code != 0 or took > 1.0:
        report.fault("SIGTERM not prompt", f"{name}: exit {code} after {took:.1f} s")


def flood(
    folder: Path, pair: common.PtyPair, fronts: list[Front], report: common.Report, share: float
) -> None:
    """A flood from one address against --udp-rate, a master on another."""
    try:
        front = Front("bridge", "udp", folder, pair.mbtool_path, "--udp-rate", RATE)
    except RuntimeError as failed:  # an mbtool without --udp-rate (--mbtool of an older one)
        report.figure(f"bridge udp --udp-rate {RATE}", str(failed))
        report.fault("no --udp-rate", str(failed))
        return
    fronts.append(front)
    master = Master(front.port, "udp", "127.0.0.2")
    until = threading.Event()
    sent = []
    attacker = threading.Thread(
        target=lambda: sent.append(attack(front.port, adu("udp", 1, LONE_READ), 0, until)), daemon=True
    )
    master.start()
    attacker.start()
    seconds = 8 * share
    time.sleep(seconds)
    until.set()
    attacker.join(5)
    master.stopping.set()
    master.join(5)
    code, took = front.stop()
    datagrams, answered = sent[0] if sent else (0, 0)
    per_second = answered / seconds
    report.figure(
        f"bridge udp --udp-rate {RATE}: flood from one address",
        f"{datagrams} datagrams, {answered} answered ({per_second:.1f} a second)",
    )
    report.figure(f"bridge udp --udp-rate {RATE}: the master's wait", ms(master.waits))
    report.figure(f"bridge udp --udp-rate {RATE}: the master's reads unanswered", master.unanswered)
    summary = [line for line in front.stderr().splitlines() if line.startswith("stopped: ")]
    report.figure(f"bridge udp --udp-rate {RATE}: summary", summary[-1] if summary else "none")
    if per_second > 2 * RATE:
        report.fault("--udp-rate not kept", f"{per_second:.1f} replies a second")
    tried = len(master.waits) + master.unanswered
    if not tried or master.unanswered > 0.05 * tried:
        report.fault("the master unanswered in a flood", f"{master.unanswered} of {tried}")
    if code != 0:
        report.fault("SIGTERM not prompt", f"flood: exit {code}")
    if "Traceback (most recent call last)" in front.stderr():
        report.fault("traceback", front.stderr()[-3000:])


def main() -> None:
    args = common.arguments(
        __doc__, seconds=(float, 60.0, "the campaign's length, shared out among its phases")
    )
    rng = random.Random(args.seed)
    report = common.Report("UDP abuse", args.verbose)
    share = args.seconds / 60
    rounds = max(3, int(20 * share))
    pair = common.PtyPair()
    device = BusDevice(pair)
    fronts: list[Front] = []
    try:
        with common.scratch("udp") as scratch:
            folder = Path(scratch)
            device.start()
            for kind in ("serve", "bridge"):
                for scheme in ("udp", "rtu+udp"):
                    name = f"{kind} {scheme}"
                    try:
                        front = Front(kind, scheme, folder, pair.mbtool_path)
                    except RuntimeError as failed:
                        common.give_up(str(failed))
                    fronts.append(front)
                    amplification(front, scheme, rounds, report, name)
                    garbage(front, max(20, int(100 * share)), rng, report, name)
                    if kind == "bridge":
                        hold_up(front, scheme, report, name, share)
                    else:
                        front.stop()
                    errors = front.stderr()
                    if "Traceback (most recent call last)" in errors:
                        report.fault("traceback", errors[-3000:])

            flood(folder, pair, fronts, report, share)
    finally:
        for front in fronts:
            if front.proc.poll() is None:
                front.proc.kill()
        device.stop()
        pair.close()
    report.finish()


if __name__ == "__main__":
    main()
