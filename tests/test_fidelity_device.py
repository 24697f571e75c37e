"""``mbtool serve`` against independent peers (issues 12 and 13):

* FC08 sub 01 (restart) keeps the diagnostic register, only sub 0A clears it.

The device itself is checked PDU by PDU first; then pymodbus's client (over TCP and a pty)
talks to a real ``mbtool serve``.
"""

from __future__ import annotations

import pytest
from test_serve_abuse import PROMPT, serve

from mbtool.codec.framing import make_framer
from mbtool.device import Device, demo_model, load_data

pytestmark = pytest.mark.timeout(60)

H = bytes.fromhex


def ask(device: Device, pdu: str, unit: int = 1) -> bytes | None:
    return device.handle(unit, H(pdu.replace(" ", "")))


def over(device: Device, framer_name: str, unit: int, pdu: str) -> bytes | None:
    """The device's reply ADU to one request framed as a master on ``framer_name`` frames it."""
    framer = make_framer(framer_name, responses=False)
    framer.feed(make_framer(framer_name).build(unit, H(pdu.replace(" ", "")), 7))
    return device.answer_frame(framer.next_event(), framer)


# --- FC08: restart keeps the diagnostic register -------------------------------------------


def test_restart_keeps_the_diagnostic_register_clear_counters_clears_it(tmp_path):
    path = tmp_path / "diag.toml"
    path.write_text("diagnostic_register = 0x1234\n")
    model, _ = load_data(str(path), frozenset({1}))
    d = Device(model)
    ask(d, "03 0000 0001")
    assert ask(d, "08 000E 0000") == H("08 000E 0002")  # slave messages: the read and this poll
    for data in ("0000", "FF00"):
        assert ask(d, f"08 0001 {data}") == H(f"08 0001 {data}")
        assert ask(d, "08 000E 0000") == H("08 000E 0001")  # the counters were cleared ...
        assert ask(d, "08 0002 0000") == H("08 0002 1234")  # ... the register was not
    assert ask(d, "08 000A 0000") == H("08 000A 0000")
    assert ask(d, "08 0002 0000") == H("08 0002 0000")  # sub 0A clears both
    assert ask(d, "08 000E 0000") == H("08 000E 0002")


def test_listen_only_leaves_only_on_a_valid_restart():
    d = Device(demo_model())
    assert ask(d, "08 0004 0000") is None
    assert ask(d, "08 0001 1234") is None  # answered 03 when listening: no restart either
    assert ask(d, "03 0000 0001") is None  # still listen-only
    assert ask(d, "08 0001 0000") is None
    assert ask(d, "03 0000 0001") == H("03 02 0000")


def test_pymodbus_restart_keeps_the_diagnostic_register(tmp_path):
    from pymodbus.client import ModbusTcpClient

    path = tmp_path / "diag.toml"
    path.write_text("diagnostic_register = 0x1234\n")
    with serve(tmp_path, "--data", str(path)) as server:
        client = ModbusTcpClient(server.host, port=server.port, timeout=PROMPT, retries=0)
        assert client.connect()
        try:
            assert not client.diag_restart_communication(True).isError()  # FF00: the log too
            assert client.diag_read_diagnostic_register().message in ([0x1234], 0x1234)
            assert not client.diag_clear_counters().isError()
            assert client.diag_read_diagnostic_register().message in ([0], 0)
        finally:
            client.close()
