"""mbtool as a Modbus UDP client (``udp://``: MBAP, ``rtu+udp://``: RTU frames) against
pymodbus's UDP server, directly and through a loopback proxy that loses and reorders
datagrams; raw UDP peers for what pymodbus never sends (issue 33).
"""

from __future__ import annotations

import json
import select
import socket
import struct
import threading
from collections.abc import Callable

import pytest
from helpers.checks import assert_one_error_line, expect_ok, parse_hex_lines, plain_pairs
from helpers.devices import HOLDING, start_device
from helpers.frames import crc16
from helpers.run import run_cli, run_mbtool
from helpers.sockets import free_udp_port
from peers.lossy_udp import LossyUdpProxy

pytestmark = pytest.mark.timeout(120)


@pytest.fixture(scope="module", params=["socket", "rtu"])
def udp_device(request):
    """pymodbus's UDP server for units 1 and 2: MBAP (udp://) or RTU frames (rtu+udp://)."""
    with start_device(tcp=False, udp=True, framer=request.param, units="1,2") as device:
        yield device


def test_reads_and_writes_one_adu_a_datagram(udp_device):
    scheme = "udp" if udp_device.framer == "socket" else "rtu+udp"
    assert udp_device.target.startswith(f"{scheme}://127.0.0.1:")
    res = expect_ok(run_cli("read-holding-registers", "0", "5", "-p", udp_device.target, "--hex"))
    assert plain_pairs(res) == [(i, str(v)) for i, v in enumerate(HOLDING[:5])]
    frames = parse_hex_lines(res.stderr)
    assert [f.direction for f in frames] == ["TX", "RX"]
    if scheme == "rtu+udp":  # RTU frames, CRC and all
        assert frames[0].data == bytes.fromhex("01 03 0000 0005") + crc16(bytes.fromhex("01 03 0000 0005"))
        assert frames[1].verdict.endswith("ok") and frames[1].verdict.startswith("CRC")
    else:
        assert frames[0].data[2:] == bytes.fromhex("0000 0006 01 03 0000 0005")
    expect_ok(run_cli("write-registers", "40", "7", "8", "-u", "2", "-p", udp_device.target))
    res = expect_ok(run_cli("read-holding-registers", "40", "2", "-u", "2", "-p", udp_device.target))
    assert plain_pairs(res) == [(40, "7"), (41, "8")]


INVENTORY = """\
[links.lossy]
target = "{target}"
timeout = 0.15  # a lost datagram costs this; loopback answers in milliseconds
retries = 10

[devices.a]
link = "lossy"
unit = 1
read = ["40001 5"]
interval = 0.01

[devices.b]
link = "lossy"
unit = 2
read = ["40011 3"]
interval = 0.01
"""


def test_retries_recover_what_a_lossy_path_drops_and_nothing_is_mismatched(udp_device, tmp_path):
    """Two devices polled in turn over one link, through a proxy that drops and reorders
    datagrams: every poll gets its own device's values, lost datagrams are resent, and a
    reply that comes late (its request sent again meanwhile) is never taken for another's."""
    scheme = udp_device.target.split("://")[0]
    proxy = LossyUdpProxy(udp_device.port)
    try:
        (tmp_path / "plant.toml").write_text(INVENTORY.format(target=f"{scheme}://{proxy.target}"))
        res = run_mbtool(
            "poll",
            str(tmp_path / "plant.toml"),
            "--rounds",
            "40",
            "-o",
            "json",
            "--stats",
            "json",
            timeout=100,
        )
    finally:
        proxy.close()
    assert res.returncode == 0, str(res)
    # the polls; a link that cannot keep up at 0.01 s says so once, an "overrun" event (issue 44)
    records = [r for r in map(json.loads, res.stdout.splitlines()) if r.get("event") != "overrun"]
    expected = {"a": HOLDING[0:5], "b": HOLDING[10:13]}
    assert len(records) == 80
    for record in records:
        assert [point["value"] for point in record["points"]] == expected[record["device"]], record
    stats = json.loads(res.stderr.splitlines()[-2])["links"]["lossy"]
    assert stats["transactions"] == stats["answered"] == 80
    assert stats["retries_recovered"] > 0
    assert sum(proxy.dropped.values()) > 0 and sum(proxy.swapped.values()) + sum(proxy.late.values()) > 0


class UdpResponder:
    """A UDP peer that answers each request datagram with the datagrams ``answer`` gives."""

    def __init__(self, answer: Callable[[bytes], list[bytes]]) -> None:
        self.answer = answer
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.port = self.sock.getsockname()[1]
        self.requests: list[bytes] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if not select.select([self.sock], [], [], 0.02)[0]:
                continue
            data, sender = self.sock.recvfrom(65536)
            self.requests.append(data)
            for datagram in self.answer(data):
                self.sock.sendto(datagram, sender)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2)
        self.sock.close()


@pytest.fixture
def udp_responder():
    made: list[UdpResponder] = []

    def make(answer):
        made.append(UdpResponder(answer))
        return made[-1]

    yield make
    for responder in made:
        responder.close()


def mbap_reply(request: bytes, pdu: bytes, tid: int | None = None) -> bytes:
    tid = struct.unpack(">H", request[:2])[0] if tid is None else tid
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, request[6]) + pdu


READ_3 = bytes.fromhex("03 06 0001 0002 0003")  # FC03's reply: 1, 2, 3


def test_a_datagram_ends_its_frame_so_a_short_one_never_swallows_the_next(udp_responder):
    """A datagram whose MBAP length promises more than it holds is not a frame; the next
    datagram is a frame of its own, not the rest of the short one (which would have read
    wrong values)."""
    peer = udp_responder(lambda request: [mbap_reply(request, READ_3)[:-4], mbap_reply(request, READ_3)])
    res = expect_ok(
        run_cli("read-holding-registers", "0", "3", "-p", f"udp://127.0.0.1:{peer.port}", "--hex")
    )
    assert plain_pairs(res) == [(0, "1"), (1, "2"), (2, "3")]
    assert "truncated" in res.stderr


def test_a_reply_with_another_transaction_id_is_dropped_as_not_ours(udp_responder):
    peer = udp_responder(
        lambda request: [mbap_reply(request, READ_3, tid=0x4242), mbap_reply(request, READ_3)]
    )
    res = expect_ok(
        run_cli("read-holding-registers", "0", "3", "-p", f"udp://127.0.0.1:{peer.port}", "--hex")
    )
    assert plain_pairs(res) == [(0, "1"), (1, "2"), (2, "3")]
    assert "reply has transaction id 16962, expected 1\n" in res.stderr  # the --hex trace's note
    only_strangers = udp_responder(lambda request: [mbap_reply(request, READ_3, tid=0x4242)])
    res = run_cli(
        "read-holding-registers", "0", "3", "-p", f"udp://127.0.0.1:{only_strangers.port}", "-t", "0.3"
    )
    line = assert_one_error_line(res, 5)
    assert "reply has transaction id 16962, expected 1, discarded" in line


def test_a_lost_datagram_is_a_timeout_that_retries_resend(udp_responder):
    asked = []

    def every_other(request: bytes) -> list[bytes]:
        asked.append(request)
        return [mbap_reply(request, READ_3)] if len(asked) == 3 else []

    peer = udp_responder(every_other)
    target = f"udp://127.0.0.1:{peer.port}"
    line = assert_one_error_line(run_cli("read-holding-registers", "0", "3", "-p", target, "-t", "0.3"), 3)
    assert line == "mbtool: no response from unit 1 within 0.3 s"
    res = expect_ok(run_cli("read-holding-registers", "0", "3", "-p", target, "-t", "0.3", "--retries", "1"))
    assert plain_pairs(res) == [(0, "1"), (1, "2"), (2, "3")]
    assert len(peer.requests) == 3


def test_rtu_in_datagrams_checks_the_crc(udp_responder):
    def answer(request: bytes) -> list[bytes]:
        frame = bytes([request[0]]) + READ_3
        return [frame + bytes([crc16(frame)[0] ^ 0xFF, crc16(frame)[1]]), frame + crc16(frame)]

    peer = udp_responder(answer)
    res = expect_ok(
        run_cli("read-holding-registers", "0", "3", "-p", f"rtu+udp://127.0.0.1:{peer.port}", "--hex")
    )
    assert plain_pairs(res) == [(0, "1"), (1, "2"), (2, "3")]
    assert "BAD" in res.stderr


def test_nothing_on_the_port_is_exit_6():
    port = free_udp_port()
    line = assert_one_error_line(run_cli("read-holding-registers", "0", "-p", f"udp://127.0.0.1:{port}"), 6)
    assert line == f"mbtool: nothing listens on udp://127.0.0.1:{port} (the host says: port unreachable)"


def test_a_udp_link_has_no_echo_nor_rts():
    line = assert_one_error_line(run_cli("read-coils", "0", "-p", "udp://127.0.0.1:9", "--echo"), 2)
    assert line == "mbtool: --echo strips a half-duplex serial adapter's echo; a udp:// link has none"
    line = assert_one_error_line(run_cli("read-coils", "0", "-p", "rtu+udp://127.0.0.1:9", "--rs485"), 2)
    assert line == "mbtool: --rs485 drives the RTS line of a serial port; a rtu+udp:// target has none"
