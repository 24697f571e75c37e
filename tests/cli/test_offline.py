"""decode, crc, lrc and raw: every worked example of the seeds, and frames gone wrong."""

from __future__ import annotations

import json

import pytest
from helpers.checks import assert_one_error_line, expect_ok, parse_hex_lines
from helpers.frames import rtu
from helpers.run import TESTS_DIR, run_cli, run_mbtool

VECTORS = json.loads((TESTS_DIR / "data" / "vectors.json").read_text())
SERIAL = VECTORS["serial"]


def pairs(res) -> dict[str, str]:
    out = {}
    for line in res.lines:
        name, _, value = line.partition(" ")
        out[name] = value
    return out


def expected_kind(name: str) -> set[str]:
    if name.endswith("-request") or name.startswith("fc0") and "request" in name:
        return {"request", "request or echo"}
    if name.startswith("exception-response"):
        return {"exception"}
    return {"response"}


# ----------------------------------------------------------------------------- decode: seed vectors


@pytest.mark.parametrize("vector", SERIAL, ids=lambda v: v["name"])
@pytest.mark.parametrize("form", ["rtu_frame", "ascii_frame"])
def test_decode_seed_vector(vector, form):
    text = vector[form].replace("\r\n", "")
    res = expect_ok(run_cli("decode", text, "-o", "json"))
    data = json.loads(res.stdout)
    assert data["framing"] == form.split("_")[0]
    assert data["checksum"]["ok"] is True
    assert data["unit"] == int(vector["unit_and_pdu"].split()[0], 16)
    assert data["kind"] in expected_kind(vector["name"]), data
    assert data["error"] is None


@pytest.mark.parametrize("vector", VECTORS["tcp"], ids=lambda v: v["name"])
def test_decode_seed_tcp(vector):
    res = expect_ok(run_cli("decode", vector["adu"]))
    got = pairs(res)
    assert got["frame"].startswith("tcp ")
    assert got["unit_id"] == "9" and got["mbap"].endswith("ok")


def test_decode_fc03_reply_fields_like_the_seed_table():
    """Seed 002 fig. 15: 555, 0, 100 from unit 17, byte count 6."""
    res = expect_ok(run_cli("decode", "11 03 06 02 2B 00 00 00 64 C8 BA"))
    got = pairs(res)
    assert got["slave_address"] == "17" and got["byte_count"] == "6"
    assert [got[f"register[{i}]"].split()[0] for i in range(3)] == ["555", "0", "100"]


def test_decode_event_log_names_events():
    res = expect_ok(run_cli("decode", ":110C08000001080121200090"))
    got = pairs(res)
    assert got["event_count"] == "264" and got["message_count"] == "289"
    assert got["event[0]"] == "0x20 unrecognised event 0x20"
    assert got["event[1]"] == "0x00 communications restart"


def test_decode_exception_names_the_code():
    res = expect_ok(run_cli("decode", "0A 81 02 B0 53"))
    assert pairs(res)["exception_code"] == "02 Illegal Data Address"


def test_decode_mask_write_shows_the_formula():
    res = expect_ok(run_cli("decode", "11 16 00 04 00 F2 00 25 66 E2"))
    assert "(current AND 0x00F2) OR (0x0025 AND NOT 0x00F2)" in pairs(res)["result"]


@pytest.mark.parametrize("vector", VECTORS["bad_crc"], ids=lambda v: v["name"])
def test_decode_seed_003_bad_crc_exit_5(vector):
    res = run_cli("decode", vector["frame"])
    line = assert_one_error_line(res, 5)
    assert f"expected {vector['expected_crc']}" in line
    assert f"expected {vector['expected_crc']}" in pairs(res)["crc"]  # the fields are still shown


def test_decode_bad_lrc_exit_5():
    res = run_cli("decode", ":0A0104A1000150")
    assert "expected 4F" in assert_one_error_line(res, 5)


def test_decode_stdin_several_frames_pairs_request_and_reply():
    """Seed 003's FC01 reply (fixed CRCs): 10 coils answered with 6B, whose top 6 bits must be 0."""
    frames = "# seed 003\n01 01 00 13 00 0A 4D C8\n01 01 02 CD 6B AC 83\n"
    res = expect_ok(run_mbtool("decode", input=frames))
    assert "unused high bits of the last byte are not zero" in res.stdout
    assert "coils 27-28: ON ON" in res.stdout


def test_decode_stdin_every_rtu_vector_in_one_stream():
    frames = "\n".join(v["rtu_frame"] for v in SERIAL) + "\n"
    res = expect_ok(run_mbtool("decode", "-", "-o", "json", input=frames))
    objects = [json.loads(line) for line in res.stdout.splitlines()]
    assert len(objects) == len(SERIAL)
    assert all(o["checksum"]["ok"] for o in objects)


def test_decode_stdin_reports_which_frame_is_bad():
    frames = "11 07 4C 22\n01 03 00 10 00 02 C5 CD\n"
    res = run_mbtool("decode", input=frames)
    assert res.returncode == 5
    assert res.stderr.splitlines() == [
        "mbtool: line 2: CRC C5 CD BAD, expected C5 CE",
        "mbtool: 1 of 2 frames failed; the first: line 2: CRC C5 CD BAD, expected C5 CE",
    ]


def test_decode_response_flag_reads_fc08_as_a_reply():
    res = expect_ok(run_cli("decode", "--response", rtu(bytes.fromhex("11 08 00 0B 01 2C")).hex()))
    assert pairs(res)["frame"] == "rtu response"


def test_decode_request_flag_is_honoured():
    res = expect_ok(run_cli("decode", "--request", "11 07 4C 22"))
    assert pairs(res)["frame"] == "rtu request"


def test_decode_unknown_function_is_shown_as_hex():
    res = expect_ok(run_cli("decode", rtu(bytes.fromhex("01 41 AA BB")).hex(" ")))
    got = pairs(res)
    assert got["data"] == "AA BB" and got["warning"] == "FC 65 (0x41) is not a function code the codec knows"


def test_decode_wrong_byte_count_exit_5():
    res = run_cli("decode", rtu(bytes.fromhex("11 03 04 00 01")).hex())
    assert_one_error_line(res, 5)


def test_decode_modicon_584_report_slave_id():
    """Seed 002 §17: the 584 layout, machine state word and stop code decoded bit by bit."""
    pdu = bytes.fromhex("11 09 03 FF 02 04 06 00 90 80 01")
    res = expect_ok(run_cli("decode", rtu(b"\x11" + pdu).hex(), "--response"))
    got = pairs(res)
    assert got["slave_id"] == "3 (Modicon 584)"
    assert "battery not OK" in got["machine_state"] and "power on" in got["machine_state"]
    assert "peripheral port stop" in got["stop_code"] and "illegal configuration" in got["stop_code"]


def test_decode_table_and_csv():
    res = expect_ok(run_cli("decode", "11 03 00 6B 00 03 76 87", "-o", "table"))
    assert "Starting" not in res.stdout and "starting address" in res.stdout and "00 6B" in res.stdout
    res = expect_ok(run_cli("decode", "11 03 00 6B 00 03 76 87", "-o", "csv"))
    assert res.lines[0] == "name,value,bytes" and "starting_address,107 (0x006B),00 6B" in res.lines


@pytest.mark.parametrize("args", [["zz"], ["01 02"], ["--framer", "tcp", "00 01"]])
def test_decode_not_a_frame_exit_2(args):
    assert_one_error_line(run_cli("decode", *args), 2)


# ----------------------------------------------------------------------------- crc / lrc


def test_crc_of_the_spec_example():
    res = expect_ok(run_cli("crc", "11 03 00 6B 00 03"))
    assert pairs(res) == {"crc": "76 87", "frame": "11 03 00 6B 00 03 76 87"}


@pytest.mark.parametrize("vector", VECTORS["bad_crc"], ids=lambda v: v["name"])
def test_crc_gives_the_corrected_seed_003_values(vector):
    body = vector["frame"].split()[:-2]
    res = expect_ok(run_cli("crc", *body, "-o", "json"))
    assert json.loads(res.stdout)["crc_bytes"] == vector["expected_crc"]


def test_lrc_of_the_spec_example():
    res = expect_ok(run_cli("lrc", "0A0104A10001"))
    assert pairs(res) == {"lrc": "4F", "frame": ":0A0104A100014F"}
    assert json.loads(run_cli("lrc", "0A0104A10001", "-o", "json").stdout)["frame"] == ":0A0104A100014F\r\n"


def test_crc_bad_hex_exit_2():
    assert_one_error_line(run_cli("crc", "0x1G"), 2)


# ----------------------------------------------------------------------------- raw


def test_raw_unknown_function_reply_ends_by_silence(raw_responder):
    """FC 0x41 is unknown: the RTU reply has no implicit length, so a pause ends it."""
    srv = raw_responder(rtu(bytes.fromhex("01 41 01 02 03")))
    res = expect_ok(run_cli("raw", "01 41 00", "-p", srv.socket_target, "-t", "0.5", "--hex"))
    got = pairs(res)
    assert got["data"] == "01 02 03" and got["crc"].endswith("ok")
    assert srv.received_bytes() == rtu(bytes.fromhex("01 41 00"))


def test_raw_adds_lrc_for_ascii(raw_responder):
    srv = raw_responder(b":010302006496\r\n")
    res = expect_ok(run_cli("raw", "01 03 00 00 00 01", "--framer", "ascii", "-p", srv.socket_target))
    assert pairs(res)["register[0]"].startswith("100 ")
    assert srv.received_bytes() == b":010300000001FB\r\n"


def test_raw_adu_sends_exact_bytes_even_a_bad_crc(raw_responder):
    srv = raw_responder(rtu(bytes.fromhex("01 03 02 00 64")))
    res = expect_ok(run_cli("raw", "--adu", "01 03 00 00 00 01 00 00", "-p", srv.socket_target, "-t", "0.5"))
    assert srv.received_bytes() == bytes.fromhex("01 03 00 00 00 01 00 00")
    assert pairs(res)["register[0]"].startswith("100 ")


def test_raw_adu_tcp_keeps_the_users_transaction_id(raw_responder):
    reply = bytes.fromhex("12 34 00 00 00 05 01 03 02 00 64")
    srv = raw_responder(reply)
    target = f"tcp://127.0.0.1:{srv.port}"
    res = expect_ok(run_cli("raw", "--adu", "12 34 00 00 00 06 01 03 00 00 00 01", "-p", target, "-t", "0.5"))
    assert srv.received_bytes() == bytes.fromhex("12 34 00 00 00 06 01 03 00 00 00 01")
    assert pairs(res)["transaction_id"] == str(0x1234)


def test_raw_bad_crc_reply_is_shown_with_its_verdict(raw_responder):
    good = rtu(bytes.fromhex("01 03 02 00 64"))
    srv = raw_responder(good[:-1] + bytes([good[-1] ^ 0xFF]))
    res = run_cli("raw", "01 03 00 00 00 01", "-p", srv.socket_target, "-t", "0.3", "--hex")
    assert_one_error_line_in_stderr(res, 5)
    assert "BAD" in pairs(res)["crc"]
    assert any("BAD" in h.verdict for h in parse_hex_lines(res.stderr))


def test_raw_malformed_known_reply_exit_5(raw_responder):
    srv = raw_responder(rtu(bytes.fromhex("01 03 04 00 64")))
    res = run_cli("raw", "01 03 00 00 00 01", "-p", srv.socket_target, "-t", "0.3")
    assert res.returncode == 5, str(res)


def test_raw_broadcast_expects_nothing(silent_server):
    res = expect_ok(run_cli("raw", "00 06 00 01 00 03", "-p", silent_server.socket_target, "-t", "0.3"))
    assert "broadcast" in pairs(res)["reply"]


def test_raw_no_reply_exit_3(silent_server):
    res = run_cli("raw", "01 03 00 00 00 01", "-p", silent_server.socket_target, "-t", "0.3")
    assert_one_error_line_in_stderr(res, 3)


def assert_one_error_line_in_stderr(res, code: int) -> None:
    """Like assert_one_error_line, but --hex lines may share stderr."""
    assert res.returncode == code, str(res)
    assert "Traceback" not in res.stderr
    errors = [line for line in res.stderr.splitlines() if line.startswith("mbtool: ")]
    assert len(errors) == 1, str(res)


def test_decode_warns_about_padding_bits_of_an_fc15_request():
    res = expect_ok(run_cli("decode", rtu(bytes.fromhex("11 0F 00 13 00 0A 02 CD 41")).hex()))
    assert pairs(res)["warning"] == "unused high bits of the last byte are not zero"
