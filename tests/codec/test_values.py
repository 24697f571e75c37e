"""Typed register values and the four byte orders (spec §1)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from mbtool.codec.errors import RequestError
from mbtool.codec.values import (
    ORDERS,
    decode_values,
    encode_values,
    parse_register,
    parse_registers,
    parse_value,
    registers_needed,
    value_addresses,
)

# 0x11223344 as uint32 in each order: the bytes A B C D are 11 22 33 44.
UINT32_ORDERS = {
    "ABCD": [0x1122, 0x3344],
    "CDAB": [0x3344, 0x1122],
    "BADC": [0x2211, 0x4433],
    "DCBA": [0x4433, 0x2211],
}


@pytest.mark.parametrize("order", ORDERS)
def test_uint32_in_every_order(order):
    assert encode_values([0x11223344], "uint32", order) == UINT32_ORDERS[order]
    assert decode_values(tuple(UINT32_ORDERS[order]), "uint32", order) == [0x11223344]


def test_float32_abcd_is_big_endian():
    assert encode_values([1.5], "float32") == [0x3FC0, 0x0000]
    assert encode_values([1.5], "float32", "CDAB") == [0x0000, 0x3FC0]


def test_uint64_word_order_reverses_all_four_words():
    value = 0x1122334455667788
    assert encode_values([value], "uint64", "ABCD") == [0x1122, 0x3344, 0x5566, 0x7788]
    assert encode_values([value], "uint64", "CDAB") == [0x7788, 0x5566, 0x3344, 0x1122]


def test_addresses_step_by_the_width_of_the_type():
    registers = tuple(encode_values([1.0, 2.0, 3.0], "float32"))
    assert decode_values(registers, "float32") == [1.0, 2.0, 3.0]
    assert value_addresses("float32", 100, len(registers)) == [100, 102, 104]
    assert value_addresses("float64", 0, 9) == [0, 4]  # a partial value at the end is not one
    assert value_addresses("uint16", 7, 3) == [7, 8, 9]
    assert value_addresses("string", 5, 3) == [5]  # one string, the whole block


def test_registers_needed():
    assert registers_needed("uint16", 5) == 5
    assert registers_needed("float32", 5) == 10
    assert registers_needed("float64", 2) == 8
    assert registers_needed("string", 4) == 4


def test_strings_pack_two_characters_a_register_and_escape_control_bytes():
    assert encode_values(["Hello"], "string") == [0x4865, 0x6C6C, 0x6F00]
    assert decode_values((0x4865, 0x6C6C, 0x6F00), "string") == ["Hello"]
    assert decode_values((0x4865, 0x6C6C, 0x6F00), "string", "BADC") == ["eHll\\x00o"]
    assert decode_values((0x0001,), "string") == ["\\x00\\x01"]


def test_hex_type_shows_each_register():
    assert decode_values((0x00FF, 0x1234), "hex") == ["0x00FF", "0x1234"]


@pytest.mark.parametrize(
    ("text", "kind"),
    [
        ("65536", "uint16"),
        ("-1", "uint32"),
        ("2147483648", "int32"),
        ("32768", "int16"),
        ("1e39", "float32"),
        ("abc", "int32"),
        ("1.5", "uint16"),
    ],
)
def test_out_of_range_or_malformed_values_are_refused(text, kind):
    with pytest.raises(RequestError):
        parse_value(text, kind)


def test_a_number_past_a_double_is_not_written_as_infinity():
    for kind in ("float64", "float32"):
        with pytest.raises(RequestError, match=f"1e999 is out of {kind}'s range"):
            parse_value("1e999", kind)
        with pytest.raises(RequestError, match=f"-1E\\+400 is out of {kind}'s range"):
            parse_value("-1E+400", kind)
        # typed as such and insisted on (--allow-nonfinite), it is meant
        assert parse_value("-Infinity", kind, nonfinite=True) == -math.inf
        assert parse_value("inf", kind, nonfinite=True) == math.inf


def test_plain_register_values_accept_negatives_as_twos_complement():
    assert parse_register("-5") == 65531
    assert parse_register("0xFFFF") == 65535
    assert parse_register("-32768") == 0x8000
    for bad in ("-32769", "65536", "12x"):
        with pytest.raises(RequestError):
            parse_register(bad)


@given(st.integers(-(2**31), 2**31 - 1), st.sampled_from(ORDERS))
def test_int32_round_trip(value, order):
    assert decode_values(tuple(encode_values([value], "int32", order)), "int32", order) == [value]


@given(st.floats(width=64), st.sampled_from(ORDERS))
def test_float64_round_trip(value, order):
    (back,) = decode_values(tuple(encode_values([value], "float64", order)), "float64", order)
    assert back == value or (math.isnan(back) and math.isnan(value))


# --- float32 printed as the shortest decimal that reads back as it (issue 12.11) ---------------


def test_float32_is_the_shortest_decimal_that_reads_back():
    import random
    import struct

    from mbtool.codec.values import shortest_float32

    assert repr(shortest_float32(struct.unpack(">f", struct.pack(">f", 123.456))[0])) == "123.456"
    assert repr(shortest_float32(struct.unpack(">f", struct.pack(">f", 1e-40))[0])) == "1e-40"  # subnormal
    rnd = random.Random(12)
    for _ in range(20000):
        value = struct.unpack(">f", rnd.randbytes(4))[0]
        if value != value or value in (float("inf"), float("-inf")):
            continue
        short = shortest_float32(value)
        assert struct.unpack(">f", struct.pack(">f", short))[0] == value
        # no shorter decimal reads back as the same float32
        digits = len(f"{short:.9e}".split("e")[0].rstrip("0").replace(".", "").replace("-", ""))
        if digits > 1:
            shorter = float(f"{value:.{digits - 1}g}")
            assert struct.unpack(">f", struct.pack(">f", shorter))[0] != value, (value, short)


def test_float64_stays_pythons_repr():
    from mbtool.codec.values import decode_values, encode_values

    assert decode_values(tuple(encode_values([0.1], "float64")), "float64") == [0.1]
    assert decode_values(tuple(encode_values([123.456], "float32", "CDAB")), "float32", "CDAB") == [123.456]


# --- a written value is the value typed, or refused (issues 28 §2, 29 item 7) ------------------


@pytest.mark.parametrize(
    ("text", "kind", "words"),
    [
        ("1e400", "float64", "1e400 is out of float64's range"),  # float() makes it +inf
        ("-1e400", "float32", "-1e400 is out of float32's range"),
        ("1e39", "float32", "1e39 is out of float32's range"),
        ("nan", "float32", "nan is not a finite number"),
        ("-inf", "float64", "-inf is not a finite number"),
        ("Infinity", "float32", "Infinity is not a finite number"),
        ("snan", "float32", "snan is not a valid float32 value"),
    ],
)
def test_a_float_typed_is_finite_and_in_its_types_range(text, kind, words):
    with pytest.raises(RequestError, match=words):
        parse_value(text, kind)


def test_nan_and_inf_are_written_only_when_the_user_insists():
    assert math.isnan(parse_value("nan", "float32", nonfinite=True))
    assert parse_value("-inf", "float64", nonfinite=True) == float("-inf")
    # Out of range is never +inf, insisting or not: 1e400 is not what the user typed.
    with pytest.raises(RequestError, match="out of float64's range"):
        parse_value("1e400", "float64", nonfinite=True)
    assert parse_registers(["inf"], "float32", nonfinite=True) == [0x7F80, 0x0000]
    with pytest.raises(RequestError, match="not a finite number"):
        parse_registers(["inf"], "float32")
