"""mbtool over Modbus TCP (tcp://) against pymodbus's server, checked with pymodbus's client.

Address plan on the shared (session) device, so write tests never disturb each other or the
read tests: 0..19 hold the fixed data; each write test owns its own addresses >= 100.
"""

from __future__ import annotations

import json
import struct

import pytest
from helpers.checks import expect_ok, parse_hex_lines, plain_pairs
from helpers.devices import COILS, DISCRETE, HOLDING, INPUT
from helpers.run import run_cli, run_mbtool, start_mbtool
from helpers.served import serve

pytestmark = pytest.mark.timeout(60)


def mb(dev, *args):
    """mbtool ARGS -p DEV in this process: what a run reads and prints needs no process of its own."""
    return run_cli(*args, "-p", dev.target)


def bit(b: bool) -> str:
    return "1" if b else "0"


# ----------------------------------------------------------------------------- reads


def test_read_holding_registers(tcp_device):
    res = expect_ok(run_mbtool("read-holding-registers", "0", "20", "-p", tcp_device.target))  # the program
    assert plain_pairs(res) == [(i, str(v)) for i, v in enumerate(HOLDING)]


def test_read_input_registers(tcp_device):
    res = expect_ok(mb(tcp_device, "read-input-registers", "0", "20"))
    assert plain_pairs(res) == [(i, str(v)) for i, v in enumerate(INPUT)]


def test_read_coils(tcp_device):
    res = expect_ok(mb(tcp_device, "read-coils", "0", "20"))
    assert plain_pairs(res) == [(i, bit(v)) for i, v in enumerate(COILS)]


def test_read_discrete_inputs(tcp_device):
    res = expect_ok(mb(tcp_device, "read-discrete-inputs", "0", "20"))
    assert plain_pairs(res) == [(i, bit(v)) for i, v in enumerate(DISCRETE)]


def test_count_defaults_to_one(tcp_device):
    res = expect_ok(mb(tcp_device, "read-holding-registers", "5"))
    assert plain_pairs(res) == [(5, "105")]
    res = expect_ok(mb(tcp_device, "read-coils", "3"))
    assert plain_pairs(res) == [(3, "0")]


def test_hex_numbers_accepted(tcp_device):
    res = expect_ok(mb(tcp_device, "read-holding-registers", "0x0A", "0x2"))
    assert plain_pairs(res) == [(10, "110"), (11, "111")]


def test_read_beyond_the_data_reads_zero(tcp_device):
    res = expect_ok(mb(tcp_device, "read-input-registers", "18", "4"))
    assert plain_pairs(res) == [(18, "218"), (19, "219"), (20, "0"), (21, "0")]


def test_unit_option_and_env(tcp_device):
    res = expect_ok(mb(tcp_device, "read-holding-registers", "1", "-u", "2", "-o", "json", "--hex"))
    assert json.loads(res.stdout)["unit"] == 2
    tx = [h for h in parse_hex_lines(res.stderr) if h.direction == "TX"]
    assert tx and tx[0].data[6] == 2, str(res)  # MBAP unit identifier

    res = expect_ok(
        run_cli(
            "read-holding-registers",
            "1",
            "-o",
            "json",
            env={"MBTOOL_PORT": tcp_device.target, "MBTOOL_UNIT": "2"},
        )
    )
    doc = json.loads(res.stdout)
    assert doc["unit"] == 2 and doc["values"] == [101]


# ----------------------------------------------------------------------------- writes


@pytest.mark.parametrize("word,expected", [("on", True), ("off", False), ("1", True), ("0", False)])
def test_write_coil(tcp_device, pymodbus_tcp_client, word, expected):
    addr = {"on": 110, "off": 111, "1": 112, "0": 113}[word]
    # start from the opposite state so the write is visible
    pymodbus_tcp_client.write_coil(addr, not expected, device_id=1)
    res = expect_ok(mb(tcp_device, "write-coil", str(addr), word))
    assert plain_pairs(res) == [(addr, bit(expected))]
    back = expect_ok(mb(tcp_device, "read-coils", str(addr)))
    assert plain_pairs(back) == [(addr, bit(expected))]
    assert pymodbus_tcp_client.read_coils(addr, count=1, device_id=1).bits[0] is expected


def test_write_register(tcp_device, pymodbus_tcp_client):
    res = expect_ok(mb(tcp_device, "write-register", "120", "1234"))
    assert plain_pairs(res) == [(120, "1234")]
    back = expect_ok(mb(tcp_device, "read-holding-registers", "120"))
    assert plain_pairs(back) == [(120, "1234")]
    assert pymodbus_tcp_client.read_holding_registers(120, count=1, device_id=1).registers == [1234]


def test_write_register_hex_value(tcp_device, pymodbus_tcp_client):
    expect_ok(mb(tcp_device, "write-register", "0x7A", "0xBEEF"))
    assert pymodbus_tcp_client.read_holding_registers(0x7A, count=1, device_id=1).registers == [0xBEEF]


def test_write_register_negative_without_double_dash(tcp_device, pymodbus_tcp_client):
    # exactly the contract's example: mbtool write-register 100 -5
    res = expect_ok(run_cli("write-register", "100", "-5", "-p", tcp_device.target))
    assert len(res.lines) == 1 and plain_pairs(res)[0][0] == 100, str(res)
    assert pymodbus_tcp_client.read_holding_registers(100, count=1, device_id=1).registers == [65531]
    back = expect_ok(mb(tcp_device, "read-holding-registers", "100"))
    assert plain_pairs(back) == [(100, "65531")]
    signed = expect_ok(mb(tcp_device, "read-holding-registers", "100", "--type", "int16"))
    assert plain_pairs(signed) == [(100, "-5")]


def test_write_register_extremes(tcp_device, pymodbus_tcp_client):
    expect_ok(mb(tcp_device, "write-register", "125", "-32768"))
    expect_ok(mb(tcp_device, "write-register", "126", "65535"))
    assert pymodbus_tcp_client.read_holding_registers(125, count=2, device_id=1).registers == [0x8000, 0xFFFF]


def test_write_coils(tcp_device, pymodbus_tcp_client):
    bits = ["1", "0", "1", "1", "0", "0", "1", "0", "1"]
    res = expect_ok(mb(tcp_device, "write-coils", "130", *bits))
    assert plain_pairs(res) == [(130 + i, b) for i, b in enumerate(bits)]
    back = expect_ok(mb(tcp_device, "read-coils", "130", str(len(bits))))
    assert plain_pairs(back) == [(130 + i, b) for i, b in enumerate(bits)]
    got = pymodbus_tcp_client.read_coils(130, count=len(bits), device_id=1).bits[: len(bits)]
    assert got == [b == "1" for b in bits]


def test_write_registers(tcp_device, pymodbus_tcp_client):
    values = ["1", "2", "0xFFFF", "-1", "40000", "-32768"]
    expected = [1, 2, 0xFFFF, 0xFFFF, 40000, 0x8000]
    res = expect_ok(mb(tcp_device, "write-registers", "140", *values))
    # one 'ADDRESS VALUE' line per register written; the value may be echoed signed or unsigned
    pairs = plain_pairs(res)
    assert [a for a, _ in pairs] == list(range(140, 146)), str(res)
    assert [int(v, 0) & 0xFFFF for _, v in pairs] == expected, str(res)
    back = expect_ok(mb(tcp_device, "read-holding-registers", "140", "6"))
    assert plain_pairs(back) == [(140 + i, str(v)) for i, v in enumerate(expected)]
    assert pymodbus_tcp_client.read_holding_registers(140, count=6, device_id=1).registers == expected


def test_write_registers_plain_output_is_one_line_per_register(tcp_device):
    res = expect_ok(mb(tcp_device, "write-registers", "150", "7", "8", "9"))
    assert plain_pairs(res) == [(150, "7"), (151, "8"), (152, "9")]


def test_a_write_echoes_the_value_as_typed(tcp_device, pymodbus_tcp_client):
    """Issue 39 item 19: -5 is echoed as -5 (not 65531, the same register), a bit of a register
    as its reference, bit and state; the JSON keeps the register the device holds."""
    assert expect_ok(mb(tcp_device, "write-register", "180", "-5")).stdout == "180 -5\n"
    assert expect_ok(mb(tcp_device, "write-registers", "181", "-5", "7", "0x10")).stdout == (
        "181 -5\n182 7\n183 16\n"
    )
    assert expect_ok(mb(tcp_device, "write", "40185", "-2")).stdout == "40185 -2\n"
    assert pymodbus_tcp_client.read_holding_registers(180, count=5, device_id=1).registers == [
        65531,
        65531,
        7,
        16,
        65534,
    ]
    doc = json.loads(expect_ok(mb(tcp_device, "write-register", "180", "-5", "-o", "json")).stdout)
    assert (doc["values"], doc["registers"]) == ([-5], [65531])
    table = expect_ok(mb(tcp_device, "write-register", "180", "-5", "-o", "table")).stdout
    assert "-5" in table and "0xFFFB" in table
    assert expect_ok(mb(tcp_device, "write-bit", "40187", "2", "on")).stdout == "40187 bit 2 on\n"
    assert expect_ok(mb(tcp_device, "write-bit", "4x0187", "15", "0")).stdout == "4x0187 bit 15 off\n"
    assert pymodbus_tcp_client.read_holding_registers(186, count=1, device_id=1).registers == [0x0004]
    doc = json.loads(expect_ok(mb(tcp_device, "write-bit", "40187", "2", "on", "-o", "json")).stdout)
    assert (doc["values"], doc["bit"], doc["refs"]) == ([True], 2, ["40187"])


# ----------------------------------------------------------------------------- typed values


def test_float32_write_and_read_abcd_cdab(tcp_device, pymodbus_tcp_client):
    c = pymodbus_tcp_client
    # ABCD (default): big-endian words -> 0x3FC0 0x0000
    res = expect_ok(mb(tcp_device, "write-registers", "300", "1.5", "--type", "float32"))
    assert len(res.lines) == 1 and plain_pairs(res)[0][0] == 300 and float(plain_pairs(res)[0][1]) == 1.5, (
        str(res)
    )
    assert c.read_holding_registers(300, count=2, device_id=1).registers == [0x3FC0, 0x0000]
    back = expect_ok(mb(tcp_device, "read-holding-registers", "300", "1", "--type", "float32"))
    assert [(a, float(v)) for a, v in plain_pairs(back)] == [(300, 1.5)]
    explicit = expect_ok(
        mb(tcp_device, "read-holding-registers", "300", "1", "--type", "float32", "--order", "ABCD")
    )
    assert [(a, float(v)) for a, v in plain_pairs(explicit)] == [(300, 1.5)]
    # the same registers read word-swapped are another number: 0x0000 0x3FC0 -> 0x00003FC0
    swapped = expect_ok(
        mb(tcp_device, "read-holding-registers", "300", "1", "--type", "float32", "--order", "CDAB")
    )
    ((addr, text),) = plain_pairs(swapped)
    assert addr == 300 and float(text) == pytest.approx(struct.unpack(">f", bytes.fromhex("00003FC0"))[0])

    # CDAB write: word-swapped -> 0x0000 0x3FC0
    expect_ok(mb(tcp_device, "write-registers", "310", "1.5", "--type", "float32", "--order", "CDAB"))
    assert c.read_holding_registers(310, count=2, device_id=1).registers == [0x0000, 0x3FC0]
    back = expect_ok(
        mb(tcp_device, "read-holding-registers", "310", "1", "--type", "float32", "--order", "CDAB")
    )
    assert [(a, float(v)) for a, v in plain_pairs(back)] == [(310, 1.5)]


def test_float32_count_is_values_not_registers(tcp_device, pymodbus_tcp_client):
    expect_ok(mb(tcp_device, "write-registers", "320", "1.5", "-2.25", "--type", "float32"))
    regs = pymodbus_tcp_client.read_holding_registers(320, count=4, device_id=1).registers
    assert regs == [0x3FC0, 0x0000, 0xC010, 0x0000]
    res = expect_ok(mb(tcp_device, "read-holding-registers", "320", "2", "--type", "float32"))
    assert [(a, float(v)) for a, v in plain_pairs(res)] == [(320, 1.5), (322, -2.25)]


@pytest.mark.parametrize(
    "order,expected",
    [
        ("ABCD", 0x00640065),  # 100, 101
        ("CDAB", 0x00650064),
        ("BADC", 0x64006500),
        ("DCBA", 0x65006400),
    ],
)
def test_uint32_orders_on_device_data(tcp_device, order, expected):
    res = expect_ok(mb(tcp_device, "read-holding-registers", "0", "1", "--type", "uint32", "--order", order))
    assert plain_pairs(res) == [(0, str(expected))]


def test_float32_json_values_are_numbers(tcp_device):
    expect_ok(mb(tcp_device, "write-registers", "330", "3.25", "--type", "float32"))
    res = expect_ok(mb(tcp_device, "read-holding-registers", "330", "1", "--type", "float32", "-o", "json"))
    doc = json.loads(res.stdout)
    assert doc["values"] == [3.25] and isinstance(doc["values"][0], float)
    assert doc["function"] == 3 and doc["address"] == 330


# ----------------------------------------------------------------------------- output formats


def test_plain_is_default_in_a_pipe_and_explicit(tcp_device):
    default = expect_ok(run_mbtool("read-holding-registers", "0", "3", "-p", tcp_device.target))  # a pipe
    plain = expect_ok(mb(tcp_device, "read-holding-registers", "0", "3", "-o", "plain"))
    assert default.stdout == plain.stdout == "0 100\n1 101\n2 102\n"


def test_json_registers(tcp_device):
    res = expect_ok(mb(tcp_device, "read-holding-registers", "0", "3", "-o", "json"))
    doc = json.loads(res.stdout)
    assert isinstance(doc, dict)
    assert doc["unit"] == 1 and doc["function"] == 3 and doc["address"] == 0
    assert doc["values"] == [100, 101, 102]


def test_json_bits_are_booleans(tcp_device):
    for cmd, fc, expected in (("read-coils", 1, COILS[:4]), ("read-discrete-inputs", 2, DISCRETE[:4])):
        res = expect_ok(mb(tcp_device, cmd, "0", "4", "--format", "json"))
        doc = json.loads(res.stdout)
        assert doc["function"] == fc and doc["address"] == 0
        assert doc["values"] == expected and all(isinstance(v, bool) for v in doc["values"])


def test_json_input_registers(tcp_device):
    doc = json.loads(expect_ok(mb(tcp_device, "read-input-registers", "2", "2", "-o", "json")).stdout)
    assert (doc["unit"], doc["function"], doc["address"], doc["values"]) == (1, 4, 2, [202, 203])


def test_json_writes(tcp_device):
    doc = json.loads(expect_ok(mb(tcp_device, "write-register", "160", "42", "-o", "json")).stdout)
    assert (doc["unit"], doc["function"], doc["address"]) == (1, 6, 160) and doc["values"] == [42]
    doc = json.loads(expect_ok(mb(tcp_device, "write-registers", "161", "1", "2", "-o", "json")).stdout)
    assert (doc["function"], doc["address"], doc["values"]) == (16, 161, [1, 2])
    doc = json.loads(expect_ok(mb(tcp_device, "write-coil", "170", "on", "-o", "json")).stdout)
    assert (doc["function"], doc["address"], doc["values"]) == (5, 170, [True])
    doc = json.loads(expect_ok(mb(tcp_device, "write-coils", "171", "1", "0", "-o", "json")).stdout)
    assert (doc["function"], doc["address"], doc["values"]) == (15, 171, [True, False])


def test_csv(tcp_device):
    res = expect_ok(mb(tcp_device, "read-holding-registers", "0", "3", "-o", "csv"))
    assert res.stdout.splitlines() == ["address,value", "0,100", "1,101", "2,102"]
    res = expect_ok(mb(tcp_device, "read-coils", "0", "3", "-o", "csv"))
    assert res.stdout.splitlines()[0] == "address,value"
    assert [row.split(",")[0] for row in res.stdout.splitlines()[1:]] == ["0", "1", "2"]
    assert len(res.stdout.splitlines()) == 4


def test_table_format_runs(tcp_device):
    res = expect_ok(mb(tcp_device, "read-holding-registers", "0", "2", "-o", "table"))
    assert "100" in res.stdout and "101" in res.stdout


# ----------------------------------------------------------------------------- --hex


def test_hex_trace_tcp(tcp_device):
    res = expect_ok(mb(tcp_device, "read-holding-registers", "0", "2", "--hex"))
    assert res.stdout == "0 100\n1 101\n", "stdout must stay clean with --hex\n" + str(res)
    lines = parse_hex_lines(res.stderr)
    tx = [h for h in lines if h.direction == "TX"]
    rx = [h for h in lines if h.direction == "RX"]
    assert len(tx) == 1 and len(rx) == 1, str(res)
    # MBAP: tid(2) proto 0000 len 0006 unit 01 | PDU 03 0000 0002
    assert tx[0].data[2:] == bytes.fromhex("0000000601030000 0002".replace(" ", "")), str(res)
    assert rx[0].data[2:] == bytes.fromhex("00000007010304006400 65".replace(" ", "")), str(res)
    assert rx[0].data[:2] == tx[0].data[:2]  # transaction id echoed
    assert "BAD" not in res.stderr
    # every stderr line is a trace line
    assert len([ln for ln in res.stderr.splitlines() if ln.strip()]) == 2, str(res)


def test_terminal_default_is_table_not_plain(tcp_device):
    """On a terminal the default is the table; plain is only the default in a pipe."""
    import os
    import pty
    import select
    import time

    master, slave = pty.openpty()
    try:
        proc = start_mbtool(
            "read-holding-registers", "0", "2", "-p", tcp_device.target, stdout=slave, text=False
        )
        os.close(slave)
        slave = -1
        out = b""
        end = time.monotonic() + 15
        while time.monotonic() < end:
            r, _, _ = select.select([master], [], [], 0.1)
            if r:
                try:
                    chunk = os.read(master, 4096)
                except OSError:  # EIO: the child closed the terminal
                    break
                if not chunk:
                    break
                out += chunk
            elif proc.poll() is not None:
                break
        proc.wait(timeout=5)
        err = proc.stderr.read().decode()
        proc.stderr.close()
    finally:
        os.close(master)
        if slave >= 0:
            os.close(slave)
    text = out.decode(errors="replace").replace("\r\n", "\n")
    assert proc.returncode == 0, err
    assert "100" in text and "101" in text, text
    assert text != "0 100\n1 101\n", "plain output on a terminal; the table is expected there"


# ----------------------------------------------------------------------------- the wrong framing


def _speaks_modbus_tcp(res) -> None:
    """--framer rtu to a Modbus TCP device that answered: exit 5, one line that says so, and the
    trace's line of the reply is the error's (the same bytes, the same words)."""
    assert res.returncode == 5, res
    lines = res.stderr.strip().splitlines()
    error = lines[-1]
    assert error.startswith("mbtool: ") and "the device speaks Modbus TCP: leave --framer out" in error, res
    assert "CRC error" not in error, res
    received = [line for line in parse_hex_lines(res.stderr) if line.direction == "RX"]
    assert len(received) == 1 and received[0].verdict.endswith(error.removeprefix("mbtool: ")), res
    assert received[0].data.hex(" ").upper() in error, res


def test_framer_rtu_to_pymodbus_says_the_device_speaks_modbus_tcp(tcp_device):
    # pymodbus reads the RTU request as an MBAP header (protocol id 0) and answers it (issue 39.3).
    _speaks_modbus_tcp(
        run_cli("read-holding-registers", "0", "2", "-p", tcp_device.target, "--framer", "rtu", "--hex")
    )


def test_framer_rtu_to_serve_says_the_device_speaks_modbus_tcp():
    with serve("-u", "1-247") as server:
        res = run_cli(
            "read-holding-registers", "0", "2", "-u", "77", "-p", server.target, "--framer", "rtu", "--hex"
        )
    _speaks_modbus_tcp(res)
