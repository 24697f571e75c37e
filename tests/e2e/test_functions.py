"""FC 07, 08, 11, 12, 17, 20-24 and 43/14 end to end: pymodbus's server, sim://, and malformed replies."""

from __future__ import annotations

import json

import pytest
from helpers.checks import assert_one_error_line, expect_ok, parse_hex_lines
from helpers.devices import HOLDING
from helpers.frames import rtu
from helpers.ptys import PTY_SERIAL_OPTS
from helpers.run import run_cli


def pairs(res) -> dict[str, str]:
    """Plain output as {NAME: VALUE-TEXT} (a NAME may repeat only in lists; last wins)."""
    out = {}
    for line in res.lines:
        name, _, value = line.partition(" ")
        out[name] = value
    return out


# ----------------------------------------------------------------------------- pymodbus over TCP


def test_read_exception_status(tcp_device):
    res = expect_ok(run_cli("read-exception-status", "-p", tcp_device.target))
    got = pairs(res)
    assert got["status"] == "0x00"
    assert [got[f"bit{i}"] for i in range(8)] == ["OFF"] * 8


def test_read_exception_status_json(tcp_device):
    res = expect_ok(run_cli("read-exception-status", "-p", tcp_device.target, "-o", "json"))
    data = json.loads(res.stdout)
    assert data["function"] == 7 and data["name"] == "Read Exception Status"
    assert data["status"] == 0 and data["bits"] == [False] * 8


def test_diag_return_query_data_matches(tcp_device):
    res = expect_ok(run_cli("diag", "return-query-data", "1234ABCD", "-p", tcp_device.target))
    got = pairs(res)
    assert got["sent"] == got["received"] == "12 34 AB CD"
    assert got["echo"] == "matched"


def test_diag_by_number_is_the_same_sub_function(tcp_device):
    res = expect_ok(run_cli("diag", "0x0B", "-p", tcp_device.target, "--hex"))
    assert pairs(res)["bus_message_count"].isdigit()
    tx = [h for h in parse_hex_lines(res.stderr) if h.direction == "TX"]
    assert tx[0].data.endswith(bytes.fromhex("0108000B0000"))


@pytest.mark.parametrize(
    "name",
    [
        "bus-message-count",
        "bus-comm-error-count",
        "bus-exception-count",
        "slave-message-count",
        "slave-no-response-count",
        "slave-nak-count",
        "slave-busy-count",
        "bus-char-overrun-count",
        "iop-overrun-count",
    ],
)
def test_diag_counter(tcp_device, name):
    res = expect_ok(run_cli("diag", name, "-p", tcp_device.target))
    assert pairs(res)[name.replace("-", "_")] == "0"


@pytest.mark.parametrize(
    "args", [["restart-comms"], ["restart-comms", "--clear-log"], ["clear-counters"], ["clear-overrun"]]
)
def test_diag_echo_sub_functions(tcp_device, args):
    res = expect_ok(run_cli("diag", *args, "-p", tcp_device.target))
    assert pairs(res)["echo"] == "matched"


def test_diag_change_ascii_delimiter_sends_char_00(tcp_device):
    res = expect_ok(run_cli("diag", "change-ascii-delimiter", "!", "-p", tcp_device.target, "--hex"))
    assert pairs(res)["data"] == "21 00"


def test_diag_counters_table(tcp_device):
    res = expect_ok(run_cli("diag", "counters", "-p", tcp_device.target, "-o", "json"))
    data = json.loads(res.stdout)
    assert data["bus_message_count"] == 0 and data["bus_char_overrun_count"] == 0
    assert len([k for k in data if k.endswith("_count")]) == 8


def test_diag_diagnostic_register_plain(tcp_device):
    res = expect_ok(run_cli("diag", "diagnostic-register", "--controller", "884", "-p", tcp_device.target))
    assert pairs(res)["diagnostic_register"] == "0x0000"


def test_diag_modbus_plus_reply_without_byte_count_is_invalid(tcp_device):
    """pymodbus answers 0003 and 54 words with no byte count (spec §4 wants 0x6C): exit 5."""
    res = run_cli("diag", "modbus-plus-stats", "-p", tcp_device.target)
    assert_one_error_line(res, 5)


def test_event_counter(tcp_device):
    res = expect_ok(run_cli("event-counter", "-p", tcp_device.target))
    assert pairs(res) == {"status": "idle", "event_count": "0"}


def test_event_log_json(tcp_device):
    res = expect_ok(run_cli("event-log", "-p", tcp_device.target, "-o", "json"))
    data = json.loads(res.stdout)
    assert data["status"] == "idle" and data["busy"] is False
    assert data["event_count"] == 0 and data["message_count"] == 0 and data["events"] == []


def test_report_id_generic(tcp_device):
    """pymodbus packs its identifier into id and run bytes: decoded generically, with a warning."""
    res = expect_ok(run_cli("report-id", "-p", tcp_device.target))
    got = pairs(res)
    assert got["slave_id"] == str(ord("P"))
    assert got["extra_text"].startswith("modbus")
    assert "run indicator" in got["warning"]


def test_read_file_record_pymodbus_dummy_records_are_refused(tcp_device):
    """pymodbus answers 10 fixed registers to any read: not what was asked, so exit 5."""
    res = run_cli("read-file-record", "4", "1", "2", "-p", tcp_device.target)
    line = assert_one_error_line(res, 5)
    assert "groups of 10 registers, expected 2" in line


def test_write_file_record_two_groups(tcp_device):
    res = expect_ok(
        run_cli(
            "write-file-record", "4", "7", "0x6AF", "0x4BE", ",", "3", "9", "100", "-p", tcp_device.target
        )
    )
    assert res.lines == ["4:7 1711", "4:8 1214", "3:9 100"]


def test_mask_write_register_and_formula(tcp_device, pymodbus_tcp_client):
    pymodbus_tcp_client.write_register(4, 0x12, device_id=1)
    res = expect_ok(run_cli("mask-write-register", "4", "0xF2", "0x25", "-p", tcp_device.target))
    assert "(current AND 0x00F2) OR (0x0025 AND NOT 0x00F2)" in pairs(res)["result"]
    assert pymodbus_tcp_client.read_holding_registers(4, count=1, device_id=1).registers == [0x17]
    pymodbus_tcp_client.write_register(4, HOLDING[4], device_id=1)


def test_read_write_registers(tcp_device, pymodbus_tcp_client):
    res = expect_ok(run_cli("read-write-registers", "0", "3", "15", "7", "-p", tcp_device.target))
    assert res.lines == [f"{i} {HOLDING[i]}" for i in range(3)]
    assert pymodbus_tcp_client.read_holding_registers(15, count=1, device_id=1).registers == [7]
    pymodbus_tcp_client.write_register(15, HOLDING[15], device_id=1)


def test_read_write_registers_write_first(tcp_device, pymodbus_tcp_client):
    """Spec §3: the write happens before the read, so the read sees the new value."""
    res = expect_ok(run_cli("read-write-registers", "5", "1", "5", "4242", "-p", tcp_device.target))
    assert res.lines == ["5 4242"]
    pymodbus_tcp_client.write_register(5, HOLDING[5], device_id=1)


def test_fifo(tcp_device):
    res = expect_ok(run_cli("fifo", "0", "-p", tcp_device.target, "-o", "json"))
    data = json.loads(res.stdout)
    assert data["count"] == len(data["values"]) <= 31


@pytest.mark.parametrize(
    ("level", "names"),
    [
        ("basic", ["VendorName", "ProductCode", "MajorMinorRevision"]),
        (
            "regular",
            [
                "VendorName",
                "ProductCode",
                "MajorMinorRevision",
                "VendorUrl",
                "ProductName",
                "ModelName",
                "UserApplicationName",
            ],
        ),
    ],
)
def test_device_id_levels(tcp_device, level, names):
    res = expect_ok(run_cli("device-id", "--level", level, "-p", tcp_device.target))
    got = pairs(res)
    assert list(got) == names
    assert got["VendorName"] == "Pymodbus" and got["ProductCode"] == "PM-TEST"


def test_device_id_extended_follows_more_follows(tcp_device):
    res = expect_ok(run_cli("device-id", "--level", "extended", "-p", tcp_device.target, "--hex"))
    got = pairs(res)
    assert [name for name in got if name.startswith("Private")] == [f"Private8{i}" for i in range(5)]
    assert len([h for h in parse_hex_lines(res.stderr) if h.direction == "TX"]) > 1


def test_device_id_one_object_json(tcp_device):
    res = expect_ok(run_cli("device-id", "--object", "4", "-p", tcp_device.target, "-o", "json"))
    assert json.loads(res.stdout)["objects"] == {"ProductName": "pymodbus test device"}


def test_raw_known_function(tcp_device):
    res = expect_ok(run_cli("raw", "01", "03", "00", "00", "00", "02", "-p", tcp_device.target))
    got = pairs(res)
    assert got["register[0]"].startswith(f"{HOLDING[0]} ") and got["mbap"].endswith("ok")


def test_raw_exception_is_shown_then_exit_4(tcp_device):
    res = run_cli("raw", "01 03 FF FF 00 01", "-p", tcp_device.target)
    assert_one_error_line(res, 4)
    assert "Illegal Data Address" in pairs(res)["exception_code"]


# ----------------------------------------------------------------------------- pymodbus on a serial line


def test_serial_rtu_event_log_and_device_id(serial_rtu_device):
    port = serial_rtu_device.target
    expect_ok(run_cli("event-log", "-p", port, *PTY_SERIAL_OPTS))
    res = expect_ok(run_cli("device-id", "--level", "extended", "-p", port, *PTY_SERIAL_OPTS))
    assert "Private84" in pairs(res)


def test_serial_ascii_diag_and_report_id(serial_ascii_device):
    port = serial_ascii_device.target
    res = expect_ok(
        run_cli("diag", "return-query-data", "A537", "-p", port, "--framer", "ascii", *PTY_SERIAL_OPTS)
    )
    assert pairs(res)["echo"] == "matched"
    expect_ok(run_cli("report-id", "-p", port, "--framer", "ascii", *PTY_SERIAL_OPTS))


# ----------------------------------------------------------------------------- sim://

SIM_COMMANDS = [
    ["read-exception-status"],
    ["diag", "return-query-data"],
    ["diag", "diagnostic-register", "--controller", "584/984"],
    ["diag", "counters"],
    ["diag", "restart-comms", "--clear-log"],
    ["event-counter"],
    ["event-log"],
    ["report-id"],
    ["read-file-record", "4", "1", "2", "3", "9", "2"],
    ["write-file-record", "4", "7", "0x6AF", "0x4BE", ",", "3", "9", "100"],
    ["mask-write-register", "4", "0xF2", "0x25"],
    ["read-write-registers", "0", "3", "10", "7", "8"],
    ["fifo", "0"],
    ["device-id", "--level", "regular"],
    ["device-id", "--object", "1"],
    ["raw", "01 03 00 00 00 02"],
]


@pytest.mark.parametrize("args", SIM_COMMANDS, ids=lambda a: " ".join(a))
def test_sim(args):
    for fmt in ("plain", "json", "csv", "table"):
        res = expect_ok(run_cli(*args, "-p", "sim://", "-o", fmt))
        assert res.stdout.strip(), str(res)
        if fmt == "json":
            data = json.loads(res.stdout)
            assert {"unit", "function", "name"} <= set(data)


def test_sim_force_listen_only_expects_no_reply():
    res = expect_ok(run_cli("diag", "force-listen-only", "-p", "sim://", "--hex", "-t", "0.2"))
    assert "none within 0.2 s, as expected" in pairs(res)["reply"]
    assert [h.direction for h in parse_hex_lines(res.stderr)] == ["TX"]


# ----------------------------------------------------------------------------- usage errors: nothing sent


@pytest.mark.parametrize(
    "args",
    [
        ["diag", "no-such-thing"],
        ["diag", "bus-message-count", "123"],
        ["diag", "restart-comms", "FF00"],
        ["diag", "counters", "0000"],
        ["diag", "change-ascii-delimiter"],
        ["diag", "return-query-data", "xyz"],
        ["read-file-record", "4", "1"],
        ["read-file-record", "0", "1", "2"],
        ["read-file-record", "4", "10000", "1"],
        ["write-file-record", "4", "7"],
        ["write-file-record", "4", "7", "1", ",", ","],
        ["mask-write-register", "4", "0x10000", "0"],
        ["read-write-registers", "0", "126", "0", "1"],
        ["device-id", "--object", "256"],
        ["raw", "01"],
        ["raw", "0G 03"],
        ["event-log", "-u", "0"],
    ],
    ids=lambda a: " ".join(a),
)
def test_bad_input_exit_2(args, silent_server):
    res = run_cli(*args, "-p", silent_server.socket_target, "-t", "0.3")
    assert_one_error_line(res, 2)
    assert silent_server.received_bytes() == b""


# ----------------------------------------------------------------------------- malformed replies: exit 5


def _answer(pdu_hex: str):
    pdu = bytes.fromhex(pdu_hex.replace(" ", ""))

    def reply(request: bytes) -> bytes:
        return rtu(bytes([request[0]]) + pdu)

    return reply


# command -> (good reply, then malformed ones: short, long, wrong byte count or field)
MALFORMED = {
    ("read-exception-status",): ("07 6D", ["07", "07 6D 00"]),
    ("diag", "bus-message-count"): ("08 000B 012C", ["08 000B 01", "08 000B 012C 00", "08 000C 012C"]),
    ("diag", "return-query-data", "A537"): ("08 0000 A537", ["08 0000 A5", "08 0000 A538"]),
    ("event-counter",): ("0B 0000 0108", ["0B 0000 01", "0B 0000 0108 00"]),
    ("event-log",): (
        "0C 08 0000 0108 0121 2000",
        ["0C 08 0000 0108 01", "0C 09 0000 0108 0121 2000 00 00", "0C 05 0000 0108 01"],
    ),
    ("report-id",): ("11 04 02 FF 0006", ["11 01 02", "11 04 02 FF 00 06 00", "11 02 02"]),
    ("read-file-record", "4", "1", "2"): (
        "14 06 05 06 0DFE 0020",
        ["14 06 05 06 0DFE", "14 08 07 06 0DFE 0020 0001", "14 04 03 06 0DFE"],
    ),
    ("write-file-record", "4", "7", "0x6AF"): (
        "15 09 06 0004 0007 0001 06AF",
        ["15 09 06 0004 0007 0001", "15 09 06 0004 0007 0001 06AE"],
    ),
    ("mask-write-register", "4", "0xF2", "0x25"): (
        "16 0004 00F2 0025",
        ["16 0004 00F2", "16 0004 00F2 0026"],
    ),
    ("read-write-registers", "0", "2", "10", "5"): (
        "17 04 0001 0002",
        ["17 04 0001", "17 06 0001 0002 0003", "17 02 0001"],
    ),
    ("fifo", "0"): (
        "18 0006 0002 01B8 1284",
        ["18 0006 0002 01B8", "18 0008 0002 01B8 1284 0000", "18 0008 0003 01B8 1284"],
    ),
    ("device-id",): (
        "2B 0E 01 01 00 00 01 00 03 414243",
        ["2B 0E 01 01 00 00", "2B 0E 01 01 00 00 01 00 05 414243", "2B 0E 02 01 00 00 01 00 03 414243"],
    ),
}


@pytest.mark.parametrize("command", list(MALFORMED), ids=lambda c: " ".join(c))
def test_malformed_replies_exit_5(raw_responder, command):
    good, bad = MALFORMED[command]
    srv = raw_responder(_answer(good))
    expect_ok(run_cli(*command, "-p", srv.socket_target, "-t", "0.3"))
    for pdu in bad:
        srv = raw_responder(_answer(pdu))
        res = run_cli(*command, "-p", srv.socket_target, "-t", "0.3")
        line = assert_one_error_line(res, 5)
        assert len(line) > len("mbtool: ") + 10, f"{pdu}: {line}"


# ----------------------------------------------------------------------------- Modicon decoding end to end


def test_diag_register_bits_named_per_controller(raw_responder):
    srv = raw_responder(_answer("08 0002 8001"))
    res = expect_ok(
        run_cli("diag", "diagnostic-register", "--controller", "584/984", "-p", srv.socket_target)
    )
    got = pairs(res)
    assert got["diagnostic_register"] == "0x8001"
    assert got["bit0"] == "illegal configuration"
    assert got["bit15"] == "peripheral port stop executed (not an error)"


def test_diag_register_without_controller_lists_set_bits(raw_responder):
    srv = raw_responder(_answer("08 0002 0012"))
    res = expect_ok(run_cli("diag", "diagnostic-register", "-p", srv.socket_target))
    assert pairs(res)["bits"] == "1 4"


def test_report_id_modicon_984_layout(raw_responder):
    srv = raw_responder(_answer("11 09 09 FF 04 08 02 0081 4000"))
    res = expect_ok(run_cli("report-id", "-p", srv.socket_target, "-o", "json"))
    data = json.loads(res.stdout)
    assert data["layout"] == "Modicon 984" and data["slave_id"] == 9 and data["run_indicator"] is True
    assert data["machine_state"] == 0x0081 and data["stop_code"] == 0x4000
    res = expect_ok(run_cli("report-id", "-p", srv.socket_target))
    got = pairs(res)
    assert got["slave_id"] == "9 (Modicon 984)"
    assert "extended memory partially failed" in got["stop_code"]


def test_event_log_events_in_words(raw_responder):
    srv = raw_responder(_answer("0C 09 FFFF 0108 0121 C2 42 04"))
    res = expect_ok(run_cli("event-log", "-p", srv.socket_target))
    got = pairs(res)
    assert got["status"] == "busy"
    assert got["event0"] == "0xC2 receive event: communication error, broadcast received"
    assert got["event1"] == "0x42 send event: slave abort exception sent (code 4)"
    assert got["event2"] == "0x04 entered listen-only mode"


def test_diag_counters_tolerate_an_unsupported_counter(raw_responder):
    def reply(request: bytes) -> bytes:
        sub = request[3]
        pdu = bytes([0x88, 0x01]) if sub == 0x0E else bytes([0x08, 0, sub, 0, sub])
        return rtu(request[:1] + pdu)

    srv = raw_responder(reply)
    res = expect_ok(run_cli("diag", "counters", "-p", srv.socket_target))
    got = pairs(res)
    assert got["bus_message_count"] == "11"
    assert got["slave_message_count"] == "not supported: exception 01 Illegal Function"


def test_diag_modbus_plus_statistics_named(raw_responder):
    words = "0001 0123 0005" + " 0000" * 51
    srv = raw_responder(_answer("08 0015 0003 6C " + words))
    res = expect_ok(run_cli("diag", "modbus-plus-stats", "-p", srv.socket_target, "-o", "json"))
    data = json.loads(res.stdout)
    assert data["word0"] == 1 and data["word2"] == 5 and "word53" in data
    got = pairs(expect_ok(run_cli("diag", "modbus-plus-stats", "get", "-p", srv.socket_target)))
    assert got["word0"].startswith("1 (0x0001) node type ID")
    assert got["word2"] == "5 (0x0005) network address of this station"
