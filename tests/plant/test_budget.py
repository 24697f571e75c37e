"""The line budget of a serial link (mbtool/plant/budget.py, issue 44), figured by hand here
from the frames' sizes, the line's character and its silences."""

from __future__ import annotations

import math

import pytest

from mbtool.codec.tables import table_named
from mbtool.link.connection import Connection, connection_of
from mbtool.plant.budget import link_budget, transaction_seconds
from mbtool.plant.schedule import DeviceSpec, Group, LinkSpec
from mbtool.registermap.plan import MapReader
from mbtool.registermap.point import Point

HOLDING = table_named("holding")


def registers(first: int, count: int, name: str = "r") -> MapReader:
    """One read of ``count`` holding registers from ``first``: a point a register, contiguous."""
    return MapReader([Point(f"{name}{n}", HOLDING, first + n, "uint16") for n in range(count)])


def link(**settings) -> LinkSpec:
    """A serial link, 8N1 unless told (mbtool's default is the spec's 8E1)."""
    return LinkSpec("bus1", connection_of(port="/dev/ttyUSB0", **({"parity": "N"} | settings)))


def device(*groups: Group, unit: int = 1) -> DeviceSpec:
    return DeviceSpec("m", "bus1", unit, None, {}, 10.0, groups=groups)


def test_an_rtu_read_is_its_two_frames_and_two_silences_at_8n1():
    # FC03 of 4 registers in RTU: request unit + 5 PDU bytes + CRC = 8; reply unit, FC, byte
    # count, 8 data bytes, CRC = 13.  8N1: 10 bits a character; t3.5 = 3.5 characters.
    char = 10 / 9600
    expected = (8 + 13) * char + 2 * 3.5 * char
    assert transaction_seconds(
        link(baud=9600).connection, 1, registers(0, 4).blocks[0].request
    ) == pytest.approx(expected)


def test_parity_adds_a_bit_a_character_and_a_longer_pause_replaces_the_second_silence():
    char = 11 / 19200  # 8E1
    expected = (8 + 5 + 2 * 100) * char + 3.5 * char + 0.05
    reader = registers(0, 100)
    seconds = transaction_seconds(
        link(baud=19200, parity="E", pause=0.05).connection, 1, reader.blocks[0].request
    )
    assert seconds == pytest.approx(expected)


def test_above_19200_baud_the_silence_is_a_fixed_1_75_ms():
    char = 10 / 115200
    assert transaction_seconds(
        link(baud=115200).connection, 1, registers(0, 4).blocks[0].request
    ) == pytest.approx((8 + 13) * char + 2 * 0.00175)


def test_ascii_frames_are_two_hex_characters_a_byte_between_a_colon_and_crlf():
    # ":" + hex of (unit, 5 PDU bytes, LRC) + CRLF = 1 + 14 + 2 = 17; the reply's
    # 1 + 2 * (1 + 1 + 1 + 8 + 1) + 2 = 27.  7E1: 10 bits.
    char = 10 / 9600
    seconds = transaction_seconds(
        link(baud=9600, framer="ascii", bytesize=7, parity="E").connection,
        1,
        registers(0, 4).blocks[0].request,
    )
    assert seconds == pytest.approx((17 + 27) * char + 2 * 3.5 * char)


def test_a_links_load_adds_each_groups_reads_over_its_interval_and_leaves_out_what_is_read_once():
    """Issue 44's plant: 4 registers every second, 100 every minute, at 9600 8N1."""
    char = 10 / 9600
    fast = (8 + 13 + 7) * char  # 28 characters' time: the frames and two silences
    slow = (8 + 205 + 7) * char
    budget = link_budget(
        link(baud=9600),
        [device(Group("fast", 1.0, registers(0, 4)), Group("slow", 60.0, registers(100, 100, "s")),
                Group("once", math.inf, registers(1000, 10, "o")))],
    )  # fmt: skip
    assert budget.seconds == pytest.approx(fast + slow / 60)  # 0.0329861: 28 + 220 / 60 characters' time
    assert budget.reads == pytest.approx(1 + 1 / 60)
    assert budget.line() == (
        "bus1: the asked polls need 0.033 s of line time a second at 9600 baud (3.3%), 1.0 reads/s"
    )


def test_the_same_plant_read_whole_every_second_needs_more_than_the_line_has_at_1200_baud():
    char = 10 / 1200
    whole = Group("default", 1.0, MapReader([*registers(0, 4).points, *registers(100, 100, "s").points]))
    budget = link_budget(link(baud=1200), [device(whole)])
    assert budget.seconds == pytest.approx((8 + 13 + 7) * char + (8 + 205 + 7) * char)
    assert budget.seconds > 1


def test_a_tcp_link_has_no_line_budget():
    tcp = LinkSpec("gw", Connection(port="tcp://192.0.2.1:502"))
    assert link_budget(tcp, [device(Group("fast", 1.0, registers(0, 4)))]) is None
