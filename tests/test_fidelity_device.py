"""``mbtool serve`` against independent peers (issues 12 and 13):

* unit 0 on Modbus TCP addresses the device itself (libmodbus's and pymodbus's clients get
  answers), while with RTU/ASCII framing it stays a broadcast;
* FC08 sub 01 (restart) keeps the diagnostic register, only sub 0A clears it.

The device itself is checked PDU by PDU first; then pymodbus's client (over TCP and a pty)
and a small C program built on libmodbus talk to a real ``mbtool serve``.
"""

from __future__ import annotations

import shutil
import subprocess
import time
from pathlib import Path

import pytest
from conftest import run_mbtool
from test_serve_abuse import PROMPT, mbap, serve

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


# --- unit 0: the device itself on Modbus TCP, a broadcast elsewhere ----------------------------


@pytest.mark.parametrize("unit", [0, 0xFF])
def test_tcp_unit_0_and_ff_are_the_lowest_unit_served(unit):
    d = Device(demo_model(), frozenset({17, 1}))
    assert over(d, "tcp", unit, "06 0005 1234") == mbap(7, unit, H("06 0005 1234"))
    assert over(d, "tcp", unit, "03 0005 0001") == mbap(7, unit, H("03 02 1234"))
    assert ask(d, "03 0005 0001", unit=1) == H("03 02 1234")  # unit 1 was written
    assert ask(d, "03 0005 0001", unit=17) == H("03 02 0005")  # unit 17 was not


@pytest.mark.parametrize("framer_name", ["rtu", "ascii"])
def test_serial_framing_unit_0_stays_a_broadcast(framer_name):
    d = Device(demo_model(), frozenset({17, 1}))
    assert over(d, framer_name, 0, "06 0005 1234") is None
    assert over(d, framer_name, 0, "03 0005 0001") is None
    for unit in (1, 17):
        assert ask(d, "03 0005 0001", unit=unit) == H("03 02 1234")


def test_pymodbus_unit_0_over_tcp_reads_and_writes_the_device(tmp_path):
    from pymodbus.client import ModbusTcpClient

    with serve(tmp_path, "-u", "1,17") as server:
        client = ModbusTcpClient(server.host, port=server.port, timeout=PROMPT, retries=0)
        assert client.connect()
        try:
            assert client.read_holding_registers(7, count=2, device_id=0).registers == [7, 8]
            assert not client.write_register(7, 4242, device_id=0).isError()
            assert not client.write_coils(400, [True, True], device_id=0).isError()
            assert client.read_holding_registers(7, count=1, device_id=1).registers == [4242]
            assert client.read_holding_registers(7, count=1, device_id=17).registers == [7]
            assert client.read_coils(400, count=2, device_id=0).bits[:2] == [True, True]
        finally:
            client.close()


def test_rtu_over_tcp_unit_0_stays_a_broadcast(tmp_path):
    from pymodbus import FramerType
    from pymodbus.client import ModbusTcpClient

    with serve(tmp_path, "-u", "1,17", "--framer", "rtu") as server:
        client = ModbusTcpClient(
            server.host, port=server.port, framer=FramerType.RTU, timeout=PROMPT, retries=0
        )
        assert client.connect()
        try:
            client.write_register(51, 5, device_id=0, no_response_expected=True)
            time.sleep(0.1)
            for unit in (1, 17):
                assert client.read_holding_registers(51, count=1, device_id=unit).registers == [5]
        finally:
            client.close()


LIBMODBUS_CLIENT = r"""
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <modbus.h>

/* unit 0 (or any): write holding register 40, read 38..41, write coils 300..301, read them */
int main(int argc, char **argv)
{
    modbus_t *ctx = modbus_new_tcp(argv[1], atoi(argv[2]));
    uint16_t regs[4];
    uint8_t bits[2] = {1, 1}, got[2];
    if (ctx == NULL || modbus_set_slave(ctx, atoi(argv[3])) == -1) {
        fprintf(stderr, "setup: %s\n", modbus_strerror(errno));
        return 2;
    }
    modbus_set_response_timeout(ctx, 2, 0);
    if (modbus_connect(ctx) == -1) {
        fprintf(stderr, "connect: %s\n", modbus_strerror(errno));
        return 2;
    }
    if (modbus_write_register(ctx, 40, 4321) != 1) {
        fprintf(stderr, "write register: %s\n", modbus_strerror(errno));
        return 1;
    }
    if (modbus_read_registers(ctx, 38, 4, regs) != 4) {
        fprintf(stderr, "read registers: %s\n", modbus_strerror(errno));
        return 1;
    }
    if (modbus_write_bits(ctx, 300, 2, bits) != 2 || modbus_read_bits(ctx, 300, 2, got) != 2) {
        fprintf(stderr, "coils: %s\n", modbus_strerror(errno));
        return 1;
    }
    printf("%u %u %u %u %u %u\n", regs[0], regs[1], regs[2], regs[3], got[0], got[1]);
    modbus_close(ctx);
    modbus_free(ctx);
    return 0;
}
"""


@pytest.fixture(scope="module")
def libmodbus_client(tmp_path_factory) -> Path:
    """LIBMODBUS_CLIENT built with gcc against the system's libmodbus (libmodbus-dev)."""
    gcc = shutil.which("gcc")
    if gcc is None:
        pytest.skip("gcc is not installed: the libmodbus client cannot be built")
    include = next(
        (p for p in (Path("/usr/include/modbus"), Path("/usr/local/include/modbus")) if p.is_dir()), None
    )
    if include is None:
        pytest.skip("libmodbus headers are not installed (Debian: apt-get install libmodbus-dev)")
    where = tmp_path_factory.mktemp("libmodbus")
    (where / "client.c").write_text(LIBMODBUS_CLIENT)
    build = subprocess.run(
        [gcc, "-o", str(where / "client"), str(where / "client.c"), f"-I{include}", "-lmodbus"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    if build.returncode != 0:
        pytest.skip(f"the libmodbus client does not build here: {build.stderr.strip()[-300:]}")
    return where / "client"


@pytest.mark.parametrize("unit", [0, 0xFF])
def test_libmodbus_unit_0_over_tcp_gets_answers(tmp_path, libmodbus_client, unit):
    with serve(tmp_path, "-u", "1,17") as server:
        run = subprocess.run(
            [str(libmodbus_client), server.host, str(server.port), str(unit)],
            capture_output=True,
            text=True,
            timeout=20,
        )
        assert run.returncode == 0, run.stderr
        assert run.stdout.split() == ["38", "39", "4321", "41", "1", "1"]
        # the device itself is unit 1, the lowest served: what libmodbus wrote is there
        res = run_mbtool(
            "read-holding-registers", "40", "-u", "1", "-p", f"tcp://{server.host}:{server.port}"
        )
        assert res.returncode == 0 and res.stdout.split() == ["40", "4321"], str(res)


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
