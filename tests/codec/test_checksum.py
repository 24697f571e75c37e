"""CRC-16/MODBUS and LRC against the spec's check values and every vector (spec §2, §7)."""

from __future__ import annotations

import json

import pytest
from helpers.run import TESTS_DIR
from hypothesis import given, settings
from hypothesis import strategies as st

from mbtool.codec.checksum import crc16, crc_bytes, lrc

VECTORS = json.loads((TESTS_DIR / "data" / "vectors.json").read_text())
SERIAL = VECTORS["serial"]


def test_crc_check_value():
    assert crc16(bytes.fromhex("11 03 00 6B 00 03")) == 0x8776


def test_crc_goes_on_the_wire_low_byte_first():
    assert crc_bytes(bytes.fromhex("11 03 00 6B 00 03")) == bytes.fromhex("76 87")


def test_crc_catalogue_check_value():
    # CRC-16/MODBUS in the CRC catalogue: check ("123456789") = 0x4B37.
    assert crc16(b"123456789") == 0x4B37


def test_crc_of_nothing_is_the_initial_value():
    assert crc16(b"") == 0xFFFF


def test_lrc_check_value():
    assert lrc(bytes.fromhex("0A 01 04 A1 00 01")) == 0x4F


def test_lrc_of_nothing():
    assert lrc(b"") == 0


# Spec §7: seed 003 prints every CRC wrong; these are the checked ones.
SEED003_CORRECTED = [
    ("01 01 00 13 00 0A", "4D C8"),
    ("01 01 02 CD 6B", "AC 83"),
    ("01 03 00 10 00 02", "C5 CE"),
    ("01 03 04 00 64 27 10", "A1 D0"),
    ("01 06 00 20 00 64", "89 EB"),
    ("01 0F 00 13 00 0A 02 CD 01", "72 CB"),
    ("01 0F 00 13 00 0A", "24 09"),
    ("01 10 00 10 00 02 04 00 64 27 10", "A9 40"),
    ("01 10 00 10 00 02", "40 0D"),
]


@pytest.mark.parametrize(("body", "crc"), SEED003_CORRECTED)
def test_seed003_errata(body, crc):
    assert crc_bytes(bytes.fromhex(body)) == bytes.fromhex(crc)


@pytest.mark.parametrize("vector", SERIAL, ids=[v["name"] for v in SERIAL])
def test_crc_of_every_vector(vector):
    body = bytes.fromhex(vector["unit_and_pdu"])
    frame = bytes.fromhex(vector["rtu_frame"])
    assert frame[:-2] == body
    assert crc_bytes(body) == frame[-2:]
    assert crc16(frame) == 0  # the residue of a whole RTU frame


@pytest.mark.parametrize("vector", SERIAL, ids=[v["name"] for v in SERIAL])
def test_lrc_of_every_vector(vector):
    body = bytes.fromhex(vector["unit_and_pdu"])
    text = vector["ascii_frame"]
    assert text.startswith(":") and text.endswith("\r\n")
    assert bytes.fromhex(text[1:-2]) == body + bytes([lrc(body)])
    assert text[1:-2] == text[1:-2].upper()


@pytest.mark.parametrize("vector", VECTORS["bad_crc"], ids=[v["name"] for v in VECTORS["bad_crc"]])
def test_bad_crc_vectors_really_are_bad(vector):
    frame = bytes.fromhex(vector["frame"])
    assert crc_bytes(frame[:-2]) == bytes.fromhex(vector["expected_crc"])
    assert frame[-2:] != bytes.fromhex(vector["expected_crc"])


@settings(max_examples=50)
@given(st.binary(max_size=64))
def test_lrc_makes_the_sum_zero(data):
    assert (sum(data) + lrc(data)) & 0xFF == 0


@settings(max_examples=50)
@given(st.binary(max_size=64))
def test_crc_residue_is_zero(data):
    assert crc16(data + crc_bytes(data)) == 0


def test_the_crc_verdict_never_contradicts_itself():
    """A 3-byte frame (unit and CRC) that the hex trace shows: a matching CRC is ok, never
    "BAD, expected" the very bytes it carries; crc_ok still refuses it as a frame."""
    from mbtool.codec.checksum import crc_ok
    from mbtool.codec.rtu import RtuFramer

    short = b"\x07" + crc_bytes(b"\x07")
    assert RtuFramer().check(short) == f"CRC {short[1]:02X} {short[2]:02X} ok"
    assert not crc_ok(short)
    bad = b"\x07\x00\x00"
    assert RtuFramer().check(bad) == f"CRC 00 00 BAD, expected {short[1]:02X} {short[2]:02X}"
