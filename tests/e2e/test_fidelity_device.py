"""``mbtool serve`` against independent peers (issues 12 and 13):

* unit 0 on Modbus TCP addresses the device itself (libmodbus's and pymodbus's clients get
  answers), while with RTU/ASCII framing it stays a broadcast;
* a sparse ``--data`` file defines only the addresses it lists: exception 02 elsewhere;
* FC08 sub 01 (restart) keeps the diagnostic register, only sub 0A clears it;
* ``--read-only`` answers every function that writes data with exception 01.

The device itself is checked PDU by PDU first; then pymodbus's client (over TCP and a pty)
and a small C program built on libmodbus talk to a real ``mbtool serve``.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest
from helpers.checks import assert_one_error_line
from helpers.devices import build_libmodbus
from helpers.frames import mbap
from helpers.ptys import PtyPair
from helpers.run import REPO_ROOT, run_cli
from helpers.served import PROMPT, serve

from mbtool.codec.framing import make_framer
from mbtool.device.datafile import load_data
from mbtool.device.device import Device
from mbtool.device.model import demo_model

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

    with serve("-u", "1,17") as server:
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

    with serve("-u", "1,17", "--framer", "rtu") as server:
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
    return build_libmodbus(tmp_path_factory, "client", LIBMODBUS_CLIENT)


@pytest.mark.parametrize("unit", [0, 0xFF])
def test_libmodbus_unit_0_over_tcp_gets_answers(tmp_path, libmodbus_client, unit):
    with serve("-u", "1,17") as server:
        run = subprocess.run(
            [str(libmodbus_client), server.host, str(server.port), str(unit)],
            capture_output=True,
            text=True,
            timeout=20,
        )
        assert run.returncode == 0, run.stderr
        assert run.stdout.split() == ["38", "39", "4321", "41", "1", "1"]
        # the device itself is unit 1, the lowest served: what libmodbus wrote is there
        res = run_cli("read-holding-registers", "40", "-u", "1", "-p", f"tcp://{server.host}:{server.port}")
        assert res.returncode == 0 and res.stdout.split() == ["40", "4321"], str(res)


# --- sparse data files: exception 02 where nothing was defined ---------------------------------


SPARSE = """
sparse = true
diagnostic_register = 0x1234

[holding_registers]
0 = [10, 11, 12]
100 = 7
200 = [2, 0x1111, 0x2222]        # a FIFO queue: count, entries
300 = 1                          # a FIFO pointer whose entry is not defined

[coils]
5 = [1, 0]

[files.4]
7 = [0x06AF, 0x04BE]

[units.17.input_registers]
0 = 99
"""


def sparse_device(tmp_path) -> Device:
    path = tmp_path / "sparse.toml"
    path.write_text(SPARSE)
    model, unit_models = load_data(str(path), frozenset({1, 17}))
    return Device(model, frozenset({1, 17}), unit_models)


@pytest.mark.parametrize(
    ("pdu", "reply"),
    [
        ("03 0000 0003", "03 06 000A 000B 000C"),
        ("03 0000 0004", "83 02"),  # one past what was defined
        ("03 0003 0001", "83 02"),
        ("03 0064 0001", "03 02 0007"),
        ("04 0000 0001", "84 02"),  # input registers: none defined for unit 1
        ("01 0005 0002", "01 01 01"),
        ("01 0004 0002", "81 02"),
        ("02 0000 0001", "82 02"),
        ("06 0064 0009", "06 0064 0009"),
        ("06 0065 0009", "86 02"),
        ("05 0006 FF00", "05 0006 FF00"),
        ("05 0007 FF00", "85 02"),
        ("0F 0005 0002 01 03", "0F 0005 0002"),
        ("0F 0005 0003 01 07", "8F 02"),
        ("10 0001 0002 04 00150016", "10 0001 0002"),
        ("10 0002 0002 04 00150016", "90 02"),
        ("16 0000 00F2 0025", "16 0000 00F2 0025"),
        ("16 0063 00F2 0025", "96 02"),
        ("17 0000 0001 0064 0001 02 0008", "17 02 000A"),  # both ranges defined
        ("17 0000 0001 0065 0001 02 0008", "97 02"),  # the write range is not
        ("17 0063 0001 0064 0001 02 0008", "97 02"),  # the read range is not
        ("18 00C8", "18 0006 0002 1111 2222"),
        ("18 00C7", "98 02"),  # no pointer there
        ("18 012C", "98 02"),  # a pointer whose entry is not defined
        ("14 07 06 0004 0007 0002", "14 06 05 06 06AF 04BE"),
        ("14 07 06 0004 0007 0003", "94 02"),  # record 9 is not defined
        ("14 07 06 0005 0000 0001", "94 02"),  # file 5 is not listed
        ("15 09 06 0004 0008 0001 0001", "15 09 06 0004 0008 0001 0001"),
        ("15 09 06 0004 0009 0001 0001", "95 02"),
        ("15 09 06 0006 0000 0001 0001", "95 02"),
        ("07", "07 00"),  # not an address: answered
        ("08 0002 0000", "08 0002 1234"),
    ],
)
def test_sparse_device_answers_02_where_nothing_was_defined(tmp_path, pdu, reply):
    assert ask(sparse_device(tmp_path), pdu) == H(reply.replace(" ", ""))


def test_sparse_refusals_change_nothing_and_units_add_their_own(tmp_path):
    d = sparse_device(tmp_path)
    assert ask(d, "17 0000 0001 0065 0001 02 0008") == H("97 02")
    assert ask(d, "17 0063 0001 0064 0001 02 0008") == H("97 02")
    assert ask(d, "03 0064 0001") == H("03 02 0007")  # neither refused FC23 wrote
    assert ask(d, "15 12 06 0004 0008 0001 0009 06 0006 0000 0001 0001") == H("95 02")
    assert ask(d, "14 07 06 0004 0008 0001") == H("14 04 03 06 04BE")  # nor did the FC21
    assert ask(d, "04 0000 0001", unit=17) == H("04 02 0063")  # unit 17's own section
    assert ask(d, "03 0000 0001", unit=17) == H("03 02 000A")  # and the file's common tables
    assert ask(d, "04 0001 0001", unit=17) == H("84 02")


def test_sparse_broadcast_reaches_only_defined_addresses(tmp_path):
    d = sparse_device(tmp_path)
    assert over(d, "rtu", 0, "06 0064 0009") is None
    assert over(d, "rtu", 0, "06 0065 0009") is None  # not defined: nothing happens
    for unit in (1, 17):
        assert ask(d, "03 0064 0001", unit=unit) == H("03 02 0009")
        assert ask(d, "03 0065 0001", unit=unit) == H("83 02")


def test_not_sparse_stays_as_it_was(tmp_path):
    path = tmp_path / "dense.toml"
    path.write_text(SPARSE.replace("sparse = true", "sparse = false"))
    model, unit_models = load_data(str(path), frozenset({1, 17}))
    d = Device(model, frozenset({1, 17}), unit_models)
    assert ask(d, "03 0003 0001") == H("03 02 0000")
    assert ask(d, "14 07 06 0005 0000 0001") == H("14 04 03 06 0000")


def test_readme_sparse_example(tmp_path):
    """The sparse TOML example of docs/simulator.md's "Simulating a device" does what the text says."""
    page = (REPO_ROOT / "docs" / "simulator.md").read_text(encoding="utf-8")
    section = page.split("## Simulating a device", 1)[1].split("\n## ", 1)[0]
    blocks = [text.split("```", 1)[0] for text in section.split("```toml\n")[1:]]
    path = tmp_path / "sparse.toml"
    path.write_text(next(block for block in blocks if "sparse = true" in block))
    model, _ = load_data(str(path), frozenset({1}))
    d = Device(model)
    assert ask(d, "03 0000 0003") == H("03 06 00E6 00E7 00E5")
    assert ask(d, "03 0003 0001") == H("83 02")
    assert ask(d, "14 07 06 0004 0007 0002") == H("14 06 05 06 06AF 04BE")
    assert ask(d, "14 07 06 0003 0007 0001") == H("94 02")


def _check_sparse_with_pymodbus(client) -> None:
    """What an independent master sees of SPARSE: values where defined, exception 02 elsewhere."""
    from pymodbus.pdu.file_message import FileRecord

    assert client.read_holding_registers(0, count=3).registers == [10, 11, 12]
    for address, count in ((0, 4), (3, 1), (99, 1), (65535, 1)):
        r = client.read_holding_registers(address, count=count)
        assert r.isError() and r.exception_code == 2, (address, count)
    assert client.read_holding_registers(100, count=1).registers == [7]
    assert not client.write_register(100, 8).isError()
    r = client.write_register(101, 8)
    assert r.isError() and r.exception_code == 2
    assert client.read_coils(5, count=2).bits[:2] == [True, False]
    r = client.read_coils(4, count=2)
    assert r.isError() and r.exception_code == 2
    r = client.read_input_registers(0, count=1)
    assert r.isError() and r.exception_code == 2
    r = client.read_discrete_inputs(0, count=1)
    assert r.isError() and r.exception_code == 2
    r = client.write_registers(2, [1, 2])
    assert r.isError() and r.exception_code == 2
    r = client.readwrite_registers(read_address=0, read_count=1, write_address=101, values=[1])
    assert r.isError() and r.exception_code == 2
    r = client.mask_write_register(address=99, and_mask=0xF2, or_mask=0x25)
    assert r.isError() and r.exception_code == 2
    # pymodbus 3.16 takes a read's record_length in bytes (it sends record_length // 2 registers)
    r = client.read_file_record([FileRecord(file_number=4, record_number=7, record_length=4)])
    assert r.records[0].record_data == b"\x06\xaf\x04\xbe"
    r = client.read_file_record([FileRecord(file_number=5, record_number=0, record_length=2)])
    assert r.isError() and r.exception_code == 2
    assert client.read_holding_registers(100, count=1).registers == [8]


def test_pymodbus_reads_a_sparse_serve_over_tcp(tmp_path):
    from pymodbus.client import ModbusTcpClient

    path = tmp_path / "sparse.toml"
    path.write_text(SPARSE)
    with serve("--data", str(path), "-u", "1,17") as server:
        client = ModbusTcpClient(server.host, port=server.port, timeout=PROMPT, retries=0)
        assert client.connect()
        try:
            _check_sparse_with_pymodbus(client)
            assert client.read_fifo_queue(address=200).values == [0x1111, 0x2222]
            r = client.read_fifo_queue(address=300)
            assert r.isError() and r.exception_code == 2
        finally:
            client.close()


def test_pymodbus_reads_a_sparse_serve_over_a_serial_line(tmp_path):
    from pymodbus import FramerType
    from pymodbus.client import ModbusSerialClient

    path = tmp_path / "sparse.toml"
    path.write_text(SPARSE)
    pair = PtyPair()
    try:
        with serve("--data", str(path), "-u", "1,17", "--parity", "N", target=pair.device_path):
            client = ModbusSerialClient(
                pair.mbtool_path, framer=FramerType.RTU, baudrate=19200, timeout=PROMPT, retries=0
            )
            assert client.connect()
            try:
                _check_sparse_with_pymodbus(client)
            finally:
                client.close()
    finally:
        pair.close()


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
    with serve("--data", str(path)) as server:
        client = ModbusTcpClient(server.host, port=server.port, timeout=PROMPT, retries=0)
        assert client.connect()
        try:
            assert not client.diag_restart_communication(True).isError()  # FF00: the log too
            assert client.diag_read_diagnostic_register().message in ([0x1234], 0x1234)
            assert not client.diag_clear_counters().isError()
            assert client.diag_read_diagnostic_register().message in ([0], 0)
        finally:
            client.close()


# --- --read-only ---------------------------------------------------------------------------


WRITES = [
    "05 0001 FF00",
    "06 0001 0009",
    "0F 0001 0002 01 03",
    "10 0001 0001 02 0009",
    "15 09 06 0004 0007 0001 0009",
    "16 0001 00F2 0025",
    "17 0000 0001 0001 0001 02 0009",
    "06 0001",  # a malformed write is still a function this device does not do
]


@pytest.mark.parametrize("pdu", WRITES)
def test_read_only_device_refuses_every_write_with_01(pdu):
    d = Device(demo_model())
    d.read_only = True
    code = H(pdu.replace(" ", ""))[0]
    assert ask(d, pdu) == bytes([code | 0x80, 0x01])
    assert ask(d, "03 0001 0001") == H("03 02 0001")  # nothing was written
    assert ask(d, "01 0001 0002") == H("01 01 02")  # the demo coils: 1 off, 2 on


# FC08 sub-functions that change the device's state (spec §4): restart (which also leaves
# listen-only and clears the counters), the ASCII delimiter, force listen-only, clear counters
# and diagnostic register, clear overrun, clear Modbus Plus statistics.
STATE_CHANGING_DIAGNOSTICS = [
    "08 0001 0000",
    "08 0001 FF00",
    "08 0003 3A00",
    "08 0004 0000",
    "08 000A 0000",
    "08 0014 0000",
    "08 0015 0004",
    "08 0004 0001",  # malformed: still a function this device does not do
]


@pytest.mark.parametrize("pdu", STATE_CHANGING_DIAGNOSTICS)
def test_read_only_device_refuses_diagnostics_that_change_its_state_with_01(pdu):
    d = Device(demo_model())
    d.read_only = True
    d.model.diagnostic_register = 0x1234
    ask(d, "03 0000 0001")
    assert ask(d, pdu) == H("88 01")
    assert ask(d, "03 0001 0001") == H("03 02 0001")  # not silenced (sub 04)
    assert ask(d, "08 0002 0000") == H("08 0002 1234")  # the diagnostic register is kept (sub 0A)
    assert ask(d, "08 000E 0000") == H("08 000E 0005")  # the counters too (subs 01, 0A)
    assert d.stations[1].ascii_delimiter == 0x0A  # and the delimiter (sub 03)
    # Reading diagnostics changes nothing: those are still answered.
    assert ask(d, "08 0000 A537") == H("08 0000 A537")
    assert ask(d, "08 0015 0003")[:6] == H("08 0015 0003 6C")


def test_read_only_device_ignores_broadcast_writes():
    d = Device(demo_model(), frozenset({1, 2}))
    d.read_only = True
    assert over(d, "rtu", 0, "06 0001 0009") is None
    assert ask(d, "03 0001 0001", unit=2) == H("03 02 0001")


def test_read_only_serve_with_pymodbus_and_mbtool(tmp_path):
    from pymodbus.client import ModbusTcpClient
    from pymodbus.pdu.file_message import FileRecord

    with serve("--read-only") as server:
        assert "read-only" in server.first_line, server.first_line
        client = ModbusTcpClient(server.host, port=server.port, timeout=PROMPT, retries=0)
        assert client.connect()
        try:
            for r in (
                client.write_coil(1, True),
                client.write_register(1, 9),
                client.write_coils(1, [True, False]),
                client.write_registers(1, [9]),
                client.write_file_record([FileRecord(file_number=4, record_number=7, record_data=b"\0\1")]),
                client.mask_write_register(address=1, and_mask=0xF2, or_mask=0x25),
                client.readwrite_registers(read_address=0, read_count=1, write_address=1, values=[9]),
            ):
                assert r.isError() and r.exception_code == 1, r
            assert client.read_holding_registers(0, count=3).registers == [0, 1, 2]
            assert client.diag_clear_counters().exception_code == 1  # nor are the counters cleared
            assert not client.diag_read_bus_message_count().isError()  # reading them is fine
        finally:
            client.close()
        target = f"tcp://{server.host}:{server.port}"
        line = assert_one_error_line(run_cli("write-register", "1", "9", "-p", target), 4)
        assert "exception 01" in line, line


def test_read_only_serve_cannot_be_silenced_by_one_client(tmp_path):
    """Issue 29 item 6: FC08 sub 04 from one client made the device deaf to every client."""
    with serve("--read-only") as server:
        with server.connect() as hostile:
            for tid, pdu in enumerate(STATE_CHANGING_DIAGNOSTICS):
                hostile.sendall(mbap(tid, 1, H(pdu.replace(" ", ""))))
                assert hostile.recv(100) == mbap(tid, 1, H("88 01")), pdu
        with server.connect() as other:
            other.sendall(mbap(99, 1, H("03 0007 0001")))
            assert other.recv(100) == mbap(99, 1, H("03 02 0007"))


def test_read_only_startup_line_in_the_log(tmp_path):
    with serve("--read-only", quiet=False) as server:
        pass
    first = server.log().splitlines()[0]
    assert first.endswith("read-only: writes get exception 01"), first
