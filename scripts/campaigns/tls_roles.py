#!/usr/bin/env python3
"""TLS role matrix: ``mbtool serve -p tls://`` and ``mbtool bridge --listen tls:// --raw-functions``
(in front of a TCP ``mbtool serve``), both with ``--write-roles operator``, sent every function
code 01-7F, every FC 08 sub-function 0000-00FF and FFFF, and every FC 43 MEI type 00-FF by
clients whose certificates carry the role viewer, no role, and operator (issue 40.5).

The campaign's own oracle says what only reads (the spec's read functions, FC 01-04, 07, 0B, 0C,
11, 14, 18, 43/0E, and FC 08's sub-functions 00, 02 and 0B-12); what reached the device is read
from the log of the ``serve`` that is the device.  Figures: requests sent, answered, reaching the
device, by front and role.

Faults: a request that does more than read reaching the device from viewer or no role; a read
from them that did not; a request from operator that did not; a request unanswered; a traceback.
"""

from __future__ import annotations

import contextlib
import signal
import socket
import ssl
import subprocess
import time
from pathlib import Path

import common
from helpers.frames import mbap, read_mbap
from peers.certs import make_pki

READ_FUNCTIONS = {0x01, 0x02, 0x03, 0x04, 0x07, 0x0B, 0x0C, 0x11, 0x14, 0x18}
READ_DIAGNOSTICS = {0x00, 0x02, *range(0x0B, 0x13)}
# A body each known function's layout takes (the bridge answers a malformed request itself).
BODIES = {
    0x01: "0000 0001",
    0x02: "0000 0001",
    0x03: "0000 0001",
    0x04: "0000 0001",
    0x05: "0001 FF00",
    0x06: "0001 0009",
    0x07: "",
    0x0B: "",
    0x0C: "",
    0x0F: "0001 0002 01 03",
    0x10: "0001 0001 02 0009",
    0x11: "",
    0x14: "07 06 0001 0000 0001",
    0x15: "09 06 0001 0000 0001 0009",
    0x16: "0001 00F2 0025",
    0x17: "0000 0001 0001 0001 02 0009",
    0x18: "0000",
}
LISTEN_ONLY = bytes.fromhex("08 0004 0000")  # the operator's would silence the device: not sent by it


def only_reads(pdu: bytes) -> bool:
    if pdu[0] == 0x08:
        return int.from_bytes(pdu[1:3], "big") in READ_DIAGNOSTICS
    if pdu[0] == 0x2B:
        return pdu[1] == 0x0E
    return pdu[0] in READ_FUNCTIONS


def requests() -> list[bytes]:
    pdus = [bytes([fc]) + bytes.fromhex(BODIES.get(fc, "0000 0001")) for fc in range(0x01, 0x80)]
    pdus = [p for p in pdus if p[0] not in (0x08, 0x2B)]
    pdus += [bytes([0x08]) + sub.to_bytes(2, "big") + b"\x00\x00" for sub in [*range(0x100), 0xFFFF]]
    pdus += [bytes([0x2B, mei, 0x01, 0x00]) for mei in range(0x100)]
    return pdus


class Logged:
    """An mbtool server whose stdout goes to a file: ``serve`` (its log) or ``bridge``."""

    def __init__(self, folder: Path, name: str, *args: object) -> None:
        self.out = folder / f"{name}.out"
        self.err = folder / f"{name}.err"
        with open(self.out, "wb") as out, open(self.err, "wb") as err:
            self.proc = common.popen(*args, stdout=out, stderr=err)
        starts = "serving " if args[0] == "serve" else "bridging "
        stream = self.out if args[0] == "serve" else self.err
        end = time.monotonic() + 20
        line = ""
        while time.monotonic() < end and self.proc.poll() is None:
            text = stream.read_text(errors="replace")
            if "\n" in text:
                line = text.partition("\n")[0]
                break
            time.sleep(0.05)
        if not line.startswith(starts):
            self.proc.kill()
            common.give_up(f"{args[0]} did not start: {self.err.read_text(errors='replace')!r}")
        self.where = line.split()[1]
        self.host, _, port = self.where.split("://")[1].rpartition(":")
        self.port = int(port)

    def log(self) -> str:
        return self.out.read_text(errors="replace")

    def stop(self) -> int | None:
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(5)
            return None


def received(log: str) -> list[bytes]:
    """The PDUs a serve's log says it received."""
    pdus = []
    for line in log.splitlines():
        words = line.split()
        if len(words) > 3 and words[2] == "RX":
            pdus.append(bytes.fromhex("".join(words[3:]))[7:])
    return pdus


@contextlib.contextmanager
def client(host: str, port: int, pki, who: str):
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.load_verify_locations(pki.ca.cert)
    pair = getattr(pki, who)
    context.load_cert_chain(pair.cert, pair.key)
    with (
        socket.create_connection((host, port), timeout=10) as raw,
        context.wrap_socket(raw) as sock,
    ):
        sock.settimeout(10)
        yield sock


def main() -> None:
    args = common.arguments(__doc__)
    report = common.Report("TLS role matrix", args.verbose)
    sent_total = 0
    with common.scratch("tls") as scratch:
        folder = Path(scratch)
        pki = make_pki(folder)
        tls = [
            "--cert",
            pki.server.cert,
            "--key",
            pki.server.key,
            "--ca",
            pki.ca.cert,
            "--write-roles",
            "operator",
        ]
        device = Logged(folder, "device", "serve", "-p", "tcp://127.0.0.1:0")
        serve = Logged(folder, "serve", "serve", "-p", "tls://127.0.0.1:0", *tls)
        bridge = Logged(
            folder, "bridge", "bridge", "--listen", "tls://127.0.0.1:0", "-p", device.where,
            "--raw-functions", "-q", "-t", "2", *tls,
        )  # fmt: skip
        servers = [device, serve, bridge]
        try:
            for front, name, logged in ((serve, "serve", serve), (bridge, "bridge", device)):
                for who in ("viewer", "no_role", "operator"):
                    pdus = [p for p in requests() if not (who == "operator" and p == LISTEN_ONLY)]
                    before = len(logged.log())
                    answered = 0
                    with client(front.host, front.port, pki, who) as sock:
                        for tid, pdu in enumerate(pdus, 1):
                            sock.sendall(mbap(tid & 0xFFFF, 1, pdu))
                            try:
                                got, _, _ = read_mbap(sock)
                            except (OSError, AssertionError):
                                report.fault("unanswered", f"{name} {who}: {pdu.hex(' ')}")
                                break
                            answered += got == tid & 0xFFFF
                    time.sleep(0.2)  # the device's log of the last request
                    reached = received(logged.log()[before:])
                    sent_total += len(pdus)
                    reads = [p for p in pdus if only_reads(p)]
                    report.figure(
                        f"{name}, {who}",
                        f"{len(pdus)} sent, {answered} answered, {len(reached)} reached the device "
                        f"({len(reads)} of them reads)",
                    )
                    if who == "operator":
                        if reached != pdus:
                            missing = [p.hex(" ") for p in pdus if p not in reached][:5]
                            report.fault("an operator's request held back", f"{name}: {missing}")
                    else:
                        leaked = [p for p in reached if not only_reads(p)]
                        for pdu in leaked:
                            report.fault(
                                "a role that may not write got more than a read through",
                                f"{name} {who}: {pdu.hex(' ')}",
                            )
                        if [p for p in reached if only_reads(p)] != reads:
                            report.fault("a read held back", f"{name} {who}")
        finally:
            codes = [server.stop() for server in (bridge, serve, device)]
        for server in servers:
            errors = server.err.read_text(errors="replace")
            if "Traceback (most recent call last)" in errors:
                report.fault("traceback", errors[-3000:])
    report.figure("requests in all", sent_total)
    report.figure("SIGTERM", f"exit codes {codes}")
    report.finish()


if __name__ == "__main__":
    main()
