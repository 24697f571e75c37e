"""In-process tests of the pieces behind the function-code commands: Modicon tables, raw PDUs,
offline decoding and the Report renderer."""

from __future__ import annotations

import io
import json

import pytest

from mbtool.cli.sinks import render
from mbtool.cli.results import Report, Row
from mbtool.codec.data_access import mask_formula
from mbtool.codec.describe import describe, parse_hex, split_frame
from mbtool.codec.errors import RequestError
from mbtool.codec.modicon import (
    CONTROLLERS,
    DIAGNOSTIC_REGISTER_BITS,
    diagnostic_register_bits,
    modicon_fields,
    modicon_layout,
)
from mbtool.codec.pdu import UNKNOWN
from mbtool.codec.raw import RawRequest, RawResponse
from mbtool.codec.rtu import RtuFramer

# ----------------------------------------------------------------------------- Modicon (seed 002)


def test_every_controller_family_of_the_spec():
    assert CONTROLLERS == ("184/384", "484", "584/984", "884")
    for bits in DIAGNOSTIC_REGISTER_BITS.values():
        assert set(bits) <= set(range(16))


def test_diagnostic_register_bits_named():
    assert diagnostic_register_bits(0x8001, "584/984") == [
        (0, "illegal configuration"),
        (15, "peripheral port stop executed (not an error)"),
    ]
    assert diagnostic_register_bits(0x0010, "184/384") == [(4, "force listen only mode")]
    assert diagnostic_register_bits(0x0200, "884") == [(9, "unassigned bit")]
    assert diagnostic_register_bits(0x0400, "484") == [(10, "ROM chip 1000-17FF test failed")]


@pytest.mark.parametrize(
    ("slave_id", "extra_len", "layout"),
    [
        (2, 2, "184/384"),
        (2, 72, "184/384"),
        (3, 7, "584"),
        (9, 7, "984"),
        (9, 6, None),
        (1, 7, None),
        (80, 7, None),
    ],
)
def test_modicon_layout_needs_id_and_byte_count(slave_id, extra_len, layout):
    assert modicon_layout(slave_id, bytes(extra_len)) == layout


def test_184_384_status_word():
    fields = dict((name, text) for name, _, text in modicon_fields("184/384", bytes([0x00, 0x06])))
    assert fields["status_word"] == "0x0006: model 384, memory protect on"


def test_984_stop_code_and_state():
    extra = bytes([4, 8, 2, 0x00, 0x81, 0x40, 0x00])
    fields = {name: text for name, _, text in modicon_fields("984", extra)}
    assert "memory downsized" in fields["machine_state"] and "power on" in fields["machine_state"]
    assert fields["stop_code"] == "0x4000: extended memory partially failed (984A, B, X)"


def test_mask_formula_of_seed_002_example():
    text = mask_formula(0x00F2, 0x0025)
    assert "OR 0x0005" in text and "clears 0xFF08" in text


# ----------------------------------------------------------------------------- raw PDUs


def test_raw_request_known_function_borrows_its_length():
    request = RawRequest(bytes.fromhex("03 00 00 00 02"))
    assert request.response_length(bytes.fromhex("03 04")) == 6
    assert request.response_length(bytes.fromhex("83")) == 2


def test_raw_request_unknown_function_has_unknown_length():
    request = RawRequest(bytes.fromhex("41 00"))
    assert request.response_length(bytes.fromhex("41 01")) == UNKNOWN
    assert request.function_code == 0x41 and request.encode() == bytes.fromhex("41 00")


def test_raw_request_keeps_any_reply():
    request = RawRequest(bytes.fromhex("03 00 00 00 02"))
    assert request.decode_response(bytes.fromhex("03 01")) == RawResponse(bytes.fromhex("03 01"))


def test_raw_request_of_force_listen_only_expects_no_reply():
    assert RawRequest(bytes.fromhex("08 00 04 00 00")).expects_response is False


def test_rtu_framer_waits_for_silence_on_unknown_raw_function():
    framer = RtuFramer()
    framer.expect = RawRequest(bytes.fromhex("41"))
    framer.expect_unit = 1
    framer.feed(bytes.fromhex("01 41 01 02"))
    assert framer.next_event() is None and framer.waiting_for_silence


@pytest.mark.parametrize("pdu", [b"", bytes(254)])
def test_raw_request_limits(pdu):
    with pytest.raises(RequestError):
        RawRequest(pdu)


# ----------------------------------------------------------------------------- offline decoding


@pytest.mark.parametrize(
    ("text", "expected"),
    [("01 03 00", b"\x01\x03\x00"), ("0103", b"\x01\x03"), ("0x01,0x03", b"\x01\x03"), ("1 3", b"\x01\x03")],
)
def test_parse_hex(text, expected):
    assert parse_hex(text) == expected


@pytest.mark.parametrize("text", ["0G", "123", "zz"])
def test_parse_hex_refuses(text):
    with pytest.raises(RequestError):
        parse_hex(text)


def test_split_frame_prefers_rtu_when_its_crc_checks():
    """01 03 00 00 00 02 C4 0B also reads as an MBAP header; the CRC decides."""
    assert split_frame("01 03 00 00 00 02 C4 0B")[0] == "rtu"
    assert split_frame("00 01 00 00 00 06 01 03 00 00 00 02")[0] == "tcp"


def test_describe_echo_is_request_or_echo():
    assert describe("11 06 00 01 00 03 9A 9B").kind == "request or echo"


def test_describe_uses_the_previous_request():
    request = describe("01 01 00 13 00 0A 4D C8")
    reply = describe("01 01 02 CD 6B AC 83", previous=request)
    assert reply.kind == "response"
    assert reply.warnings == ["unused high bits of the last byte are not zero"]


def test_describe_truncated_reply_says_why():
    from mbtool.codec.checksum import crc_bytes

    body = bytes.fromhex("11 0C 08 00 00 01")
    described = describe((body + crc_bytes(body)).hex(), direction="response")
    assert described.checksum_ok is True
    assert "expected 10" in described.error


# ----------------------------------------------------------------------------- the Report renderer


REPORT = Report(
    1,
    12,
    "Get Comm Event Log",
    [Row("status", "idle"), Row("event_count", 264), Row("event0", 0x20, "0x20 unrecognised", b"\x20")],
)


def rendered(fmt: str, report: Report = REPORT) -> str:
    out = io.StringIO()
    render(report, fmt, out)
    return out.getvalue()


def test_report_plain_is_one_name_value_line_per_row():
    assert rendered("plain") == "status idle\nevent_count 264\nevent0 0x20 unrecognised\n"


def test_report_json_has_unit_function_name_and_fields():
    assert json.loads(rendered("json")) == {
        "unit": 1,
        "function": 12,
        "name": "Get Comm Event Log",
        "status": "idle",
        "event_count": 264,
        "event0": 32,
    }


def test_report_json_data_overrides_rows():
    report = Report(1, 7, "X", [Row("a", 1)], {"bits": [True]})
    assert json.loads(rendered("json", report))["bits"] == [True]


def test_report_csv_adds_bytes_column_when_rows_carry_them():
    assert rendered("csv").splitlines() == [
        "name,value,bytes",
        "status,idle,",
        "event_count,264,",
        "event0,0x20 unrecognised,20",
    ]


def test_report_table_has_title_and_fields():
    text = rendered("table")
    assert "Get Comm Event Log · FC 12 (0x0C) · unit 1" in text
    assert "event count" in text and "264" in text


def test_modbus_plus_words_cover_the_54_of_the_reply():
    from mbtool.codec.modicon import MODBUS_PLUS_WORDS

    assert len(MODBUS_PLUS_WORDS) == 54
    assert MODBUS_PLUS_WORDS[53].endswith("path C8")
