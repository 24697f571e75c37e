"""Modicon references and register maps (issue 15): parsing, scaling, loading, planning reads."""

from __future__ import annotations

import struct

import pytest
from helpers.fakes import device_executor

from mbtool.codec.errors import ModbusException, RequestError
from mbtool.codec.tables import (
    COILS,
    DISCRETE_INPUTS,
    HOLDING_REGISTERS,
    INPUT_REGISTERS,
    parse_reference,
    reference,
)
from mbtool.codec.values import encode_values
from mbtool.device.device import Device
from mbtool.device.model import DataModel
from mbtool.errors import ExitCode, PartialRead, UsageError, exit_code_for
from mbtool.registermap.load import MapError, load_map
from mbtool.registermap.plan import (
    MapReader,
    bit_request,
    plan_reads,
    read_points,
    with_bit,
    write_request,
)
from mbtool.registermap.point import Point

# --- references ---------------------------------------------------------------


@pytest.mark.parametrize(
    "text, table, address",
    [
        ("00001", COILS, 0),
        ("09999", COILS, 9998),
        ("10001", DISCRETE_INPUTS, 0),
        ("30001", INPUT_REGISTERS, 0),
        ("40108", HOLDING_REGISTERS, 107),
        ("400108", HOLDING_REGISTERS, 107),
        ("465536", HOLDING_REGISTERS, 65535),
        ("000001", COILS, 0),
        ("165536", DISCRETE_INPUTS, 65535),
        ("4x0108", HOLDING_REGISTERS, 107),
        ("3X0001", INPUT_REGISTERS, 0),
        ("0x65536", COILS, 65535),
    ],
)
def test_references_of_device_manuals(text, table, address):
    assert parse_reference(text) == (table, address)


@pytest.mark.parametrize(
    "text, words",
    [
        ("40000", "40001 is holding register 1, wire address 0"),
        ("1", "a reference has 5 or 6 digits: 00001 for coil 1"),
        ("4000", "5 or 6 digits"),
        ("4000001", "5 or 6 digits"),
        ("20001", "no table has the prefix 2"),
        ("465537", "up to 65536"),
        ("4x0", "holding registers count from 1"),
        ("", "5 or 6 digits"),
        ("4O001", "5 or 6 digits"),
    ],
)
def test_invalid_references_say_why(text, words):
    with pytest.raises(RequestError, match=words) as caught:
        parse_reference(text)
    assert exit_code_for(caught.value) == ExitCode.USAGE
    assert "'" not in str(caught.value)


@pytest.mark.parametrize("address, text", [(0, "40001"), (107, "40108"), (9998, "49999"), (9999, "410000")])
def test_reference_of_an_address_uses_five_digits_while_they_suffice(address, text):
    assert reference(HOLDING_REGISTERS, address) == text
    assert parse_reference(text) == (HOLDING_REGISTERS, address)


# --- points -------------------------------------------------------------------


def _point(**keys) -> Point:
    return Point(
        keys.pop("name", "p"), keys.pop("table", HOLDING_REGISTERS), keys.pop("address", 107), **keys
    )


def test_scaled_value_is_exact_in_decimal():
    from decimal import Decimal

    flow = _point(type="uint16", scale=Decimal("0.1"))
    assert flow.value_of([225]) == 22.5
    assert repr(flow.value_of([3])) == "0.3"  # not 0.30000000000000004
    assert flow.value_of([1230]) == 123
    assert isinstance(flow.value_of([1230]), int)


def test_float32_in_cdab_with_scale_and_offset():
    from decimal import Decimal

    point = _point(type="float32", order="CDAB", scale=Decimal("10"), offset=Decimal("-1"))
    registers = encode_values([2.5], "float32", "CDAB")
    assert point.value_of(registers) == 24
    assert point.registers_for("24") == registers


def test_enum_labels_both_ways():
    state = _point(enum={0: "stopped", 1: "running", 2: "fault"}, writable=True)
    assert state.value_of([1]) == "running"
    assert state.value_of([7]) == 7  # a value the manual does not name stays a number
    assert state.registers_for("Running") == [1]
    assert state.registers_for("2") == [2]
    with pytest.raises(UsageError, match="none of stopped, running, fault"):
        state.registers_for("paused")


def test_bits_of_a_register():
    alarm = _point(type="bool", bit=3)
    assert alarm.value_of([0b1000]) is True
    assert alarm.value_of([0b0111]) is False
    assert alarm.raw_for("on") is True and alarm.raw_for("OFF") is False
    with pytest.raises(UsageError, match="not on or off"):
        alarm.raw_for("maybe")


def test_written_value_must_be_a_whole_number_of_steps():
    from decimal import Decimal

    setpoint = _point(scale=Decimal("0.1"), writable=True)
    assert setpoint.registers_for("22.5") == [225]
    with pytest.raises(UsageError, match="nearest writable values are 22.5 and 22.6"):
        setpoint.registers_for("22.53")


def test_written_value_must_fit_the_type():
    from decimal import Decimal

    setpoint = _point(type="int16", scale=Decimal("0.1"), unit="°C", writable=True)
    assert setpoint.registers_for("-5") == [0xFFCE]
    with pytest.raises(UsageError, match="raw 40000.*out of range -32768..32767"):
        setpoint.registers_for("4000")
    with pytest.raises(UsageError, match="not a number"):
        setpoint.registers_for("warm")


def test_every_refused_value_names_its_point():
    from decimal import Decimal

    period = _point(name="demand_period", type="float32", writable=True)
    with pytest.raises(UsageError, match="^demand_period: 1e39 is out of float32's range$"):
        period.raw_for("1e39")
    counter = _point(name="count", type="uint16", writable=True)
    for text, words in (
        ("nan", "count: nan is not a number a uint16 can hold"),
        ("inf", "count: inf is not a number a uint16 can hold"),
        ("1e39", "count: 1e39 is out of range 0..65535 for uint16"),
    ):
        with pytest.raises(UsageError, match=f"^{words}$"):
            counter.raw_for(text)
    wide = _point(name="total", type="float64", writable=True)
    with pytest.raises(UsageError, match="^total: 1e400 is out of float64's range$"):
        wide.raw_for("1e400")  # float() would make it +inf: 7F F0 00 ... on the wire
    tiny = _point(name="d", type="float32", scale=Decimal("1e-300"), writable=True)
    with pytest.raises(UsageError, match="^d: 1e10 \\(raw 1E\\+310\\) is out of float32's range$"):
        tiny.raw_for("1e10")  # was 7F 80 00 00 (+inf) sent, then an internal error


def test_a_value_past_decimals_own_range_is_out_of_the_points():
    from decimal import Decimal

    setpoint = _point(name="setpoint", scale=Decimal("0.1"), writable=True)
    for text in ("1e999999", "-1e99999999999"):  # was decimal.Overflow: an internal error
        with pytest.raises(UsageError, match=f"^setpoint: {text} \\(raw .*\\) is out of range 0..65535"):
            setpoint.raw_for(text)
    level = _point(name="level", type="float32", scale=Decimal("0.1"), writable=True)
    with pytest.raises(UsageError, match="^level: 1e999999 \\(raw .*\\) is out of float32's range$"):
        level.raw_for("1e999999")


def test_nan_and_inf_are_written_only_when_the_user_insists():
    import math

    level = _point(name="level", type="float32", writable=True)
    for text in ("nan", "inf", "-Infinity"):
        with pytest.raises(UsageError, match=f"^level: {text} is not a finite number"):
            level.raw_for(text)
    assert math.isnan(level.raw_for("nan", nonfinite=True))
    assert level.registers_of(level.raw_for("-inf", nonfinite=True)) == [0xFF80, 0x0000]
    assert level.value_of([0x7F80, 0x0000]) == float("inf")


def test_a_scaled_float_point_reads_nan_and_inf_without_failing():
    import math
    from decimal import Decimal

    scaled = _point(type="float32", scale=Decimal("0.1"), offset=Decimal("2"))
    assert scaled.value_of([0x7F80, 0x0000]) == float("inf")  # was OverflowError: internal error
    assert scaled.value_of([0xFF80, 0x0000]) == float("-inf")
    assert math.isnan(scaled.value_of([0x7FC0, 0x0000]))


def test_hex_is_a_number_as_everywhere_else():
    from decimal import Decimal

    period = _point(name="period", type="uint16", writable=True)
    assert period.raw_for("0x0F") == 15 and period.raw_for("0X10") == 16
    word = _point(name="word", type="hex", writable=True)
    assert word.registers_for("0x00FF") == [0x00FF]
    scaled = _point(name="flow", type="uint16", scale=Decimal("0.5"), writable=True)
    assert scaled.raw_for("0x10") == 32  # 16 in the point's units
    state = _point(enum={0: "stopped", 1: "running"}, writable=True)
    assert state.raw_for("0x1") == 1
    with pytest.raises(UsageError, match="^p: 0xZZ is none of stopped, running$"):
        state.raw_for("0xZZ")


def test_a_float_that_cannot_hold_the_decimal_given_says_what_it_holds():
    from decimal import Decimal

    level = _point(type="float32", writable=True)
    assert level.held("1.25", level.raw_for("1.25")) is None  # exact: nothing to say
    assert level.held("0.1", level.raw_for("0.1")) is None  # 0.1 reads back as 0.1
    assert level.held("16777217", level.raw_for("16777217")) == 16777216
    assert level.held("123.456789", level.raw_for("123.456789")) == 123.45679
    third = _point(type="float32", scale=Decimal("3"), writable=True)
    assert third.held("1", third.raw_for("1")) == 1.00000002
    assert _point(writable=True).held("5", 5) is None  # integers are exact or refused


def test_write_requests_pick_the_function_code():
    from decimal import Decimal

    single = _point(scale=Decimal("0.1"), writable=True)
    assert write_request(single, "22.5").function_code == 0x06
    assert write_request(single, "22.5", multiple=True).function_code == 0x10
    wide = _point(type="float32", writable=True)
    assert write_request(wide, "1.5").function_code == 0x10
    coil = _point(table=COILS, address=3, type="bool", writable=True)
    assert write_request(coil, "on").function_code == 0x05
    assert write_request(coil, "on", multiple=True).function_code == 0x0F
    bit = _point(type="bool", bit=3, writable=True)
    request = write_request(bit, "on")
    assert request.function_code == 0x16
    assert (request.and_mask, request.or_mask) == (0xFFF7, 0x0008)


def test_read_only_points_are_not_written():
    with pytest.raises(UsageError, match="not writable: the map does not mark it rw"):
        write_request(_point(), "1")
    with pytest.raises(UsageError, match="input registers are read-only"):
        write_request(_point(table=INPUT_REGISTERS), "1")


def test_bit_masks_set_and_clear_one_bit_only():
    from mbtool.codec.data_access import mask_write_result

    for current in (0x0000, 0xFFFF, 0x1234):
        for bit in (0, 7, 15):
            for on in (True, False):
                request = bit_request(10, bit, on)
                assert mask_write_result(current, request.and_mask, request.or_mask) == with_bit(
                    current, bit, on
                )
                assert bool(with_bit(current, bit, on) >> bit & 1) is on
                others = ~(1 << bit) & 0xFFFF
                assert with_bit(current, bit, on) & others == current & others


# --- map files ----------------------------------------------------------------

PUMP = """
[device]
order = "CDAB"
max_gap = 0

[points.flow]
ref = 40108
type = "float32"
scale = 0.1
unit = "m3/h"
description = "Outlet flow"

[points.state]
ref = 40110
enum = { 0 = "stopped", 1 = "running", 2 = "fault" }

[points.alarm_high]
ref = 40111
bit = 3

[points.setpoint]
ref = 40120
scale = 0.1
access = "rw"

[points.run]
ref = "00001"
access = "rw"

[points.speed]
table = "input"
address = 4
type = "int16"
"""


def _write(tmp_path, text, name="pump.toml"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_a_toml_map_loads_with_device_defaults(tmp_path):
    pump = load_map(_write(tmp_path, PUMP))
    flow = pump.points["flow"]
    assert (flow.table, flow.address, flow.type, flow.order, flow.unit) == (
        HOLDING_REGISTERS,
        107,
        "float32",
        "CDAB",
        "m3/h",
    )
    assert pump.points["run"].table is COILS and pump.points["run"].writable
    assert pump.points["speed"].table is INPUT_REGISTERS and pump.points["speed"].address == 4
    assert not pump.points["state"].writable
    assert pump.points["alarm_high"].bit == 3


def test_a_csv_map_reads_as_the_toml_one(tmp_path):
    csv_map = _write(
        tmp_path,
        "name,ref,type,order,scale,unit,description,enum,bit,access\n"
        "flow,40108,float32,CDAB,0.1,m3/h,Outlet flow,,,\n"
        "state,40110,,CDAB,,,,0=stopped; 1=running; 2=fault,,\n"
        "alarm_high,40111,,CDAB,,,,,3,\n"
        "run,00001,,,,,,,,rw\n",
        "pump.csv",
    )
    points = load_map(csv_map).points
    toml_points = load_map(_write(tmp_path, PUMP)).points
    for name in ("flow", "state", "alarm_high", "run"):
        assert points[name] == toml_points[name], name
    assert points["state"].enum == toml_points["state"].enum


@pytest.mark.parametrize(
    "text, words",
    [
        ("[points.a]\nref = 40001\ncolour = 'red'\n", "point a: unknown key colour"),
        (
            "[points.a]\nref = 40001\ntype = 'float32'\n[points.b]\nref = 40002\n",
            "point b: key ref: 40002 overlaps point a",
        ),
        ("[points.a]\nref = 40001\ntype = 'float32'\nbit = 2\n", "point a: key bit: .*not of a float32"),
        ("[points.a]\nref = 465536\ntype = 'uint32'\n", "point a: key ref: .*runs past the last register"),
        ("[points.a]\nref = 30001\naccess = 'rw'\n", "point a: key access: input registers are read-only"),
        ("[points.a]\nref = 1\n", "point a: key ref: .*00001 for coil 1"),
        ("[points.a]\nref = 40001\nbit = 16\n", "point a: key bit: 16 is not a whole number in 0..15"),
        ("[points.a]\nref = 40001\nscale = 'x'\n", "point a: key scale: x is not a number"),
        ("[points.a]\nref = 40001\nscale = 0\n", "point a: key scale"),
        ("[points.a]\nref = 40001\ntype = 'float16'\n", "point a: key type: unknown type"),
        ("[points.a]\nref = 40001\norder = 'ACBD'\n", "point a: key order: unknown order"),
        ("[points.a]\nref = 40001\ntype = 'string'\n", "point a: key count"),
        ("[points.a]\nref = '00001'\nscale = 2\n", "point a: key scale: coils hold one bit each"),
        ("[points.a]\nref = 40001\ntable = 'holding'\n", "point a: key ref: give either ref or table"),
        ("[points.a]\ntable = 'holding'\n", "point a: no location"),
        (
            "[points.a]\nref = 40001\nbit = 1\n[points.b]\nref = 40001\nbit = 1\n",
            "point b: key bit: bit 1 of 40001",
        ),
        ("[device]\nspeed = 3\n[points.a]\nref = 40001\n", r"\[device\]: unknown key speed"),
        ("[points.a]\nref = 40001\nenum = { x = 'on' }\n", "point a: key enum"),
        ("[pointz.a]\nref = 40001\n", "unknown section pointz"),
        ("[device]\n", "the map has no points"),
        ("[points.a\n", "not a valid TOML map"),
        # Names, units and labels are written on one line in every format (issue 29.11, 29.12).
        ('[points."line\\nbreak"]\nref = 40001\n', r"point 'line\\nbreak': .*no control characters"),
        ('[points."tab\\there"]\nref = 40001\n', r"point 'tab\\there': .*no control characters"),
        ('[points.""]\nref = 40001\n', "a point with an empty name"),
        ('[points.a]\nref = 40001\nunit = "m\\n3"\n', r"point a: key unit: 'm\\n3' .*no control characters"),
        (
            '[points.a]\nref = 40001\nenum = { 1 = "on\\roff" }\n',
            r"point a: key enum: 'on\\roff' .*no control characters",
        ),
    ],
)
def test_bad_maps_name_file_point_and_key(tmp_path, text, words):
    path = _write(tmp_path, text)
    with pytest.raises(MapError, match=words) as caught:
        load_map(path)
    assert str(caught.value).startswith(str(path))
    assert exit_code_for(caught.value) == ExitCode.USAGE


def test_bits_of_one_register_do_not_overlap(tmp_path):
    text = "[points.a]\nref = 40001\nbit = 0\n[points.b]\nref = 40001\nbit = 1\n"
    assert set(load_map(_write(tmp_path, text)).points) == {"a", "b"}


def test_unreadable_and_non_utf8_maps(tmp_path):
    with pytest.raises(MapError, match="cannot read map"):
        load_map(tmp_path / "missing.toml")
    path = tmp_path / "latin.toml"
    path.write_bytes(b"[points.caf\xe9]\nref = 40001\n")
    with pytest.raises(MapError, match="not UTF-8"):
        load_map(path)


def test_unknown_point_names_are_listed(tmp_path):
    pump = load_map(_write(tmp_path, PUMP))
    with pytest.raises(MapError, match="no point named pressure"):
        pump.select(["pressure"])
    assert [p.name for p in pump.select(["state", "flow"])] == ["state", "flow"]
    assert len(pump.select([])) == 6


# --- planning and reading -----------------------------------------------------


def _spread_map(tmp_path) -> str:
    """50 points over the four tables, with gaps and runs, as a real device has them."""
    lines = []
    for i in range(15):  # holding: 0..28 step 2 (uint16) and far 1000..
        lines.append(f"[points.h{i}]\nref = {40001 + 2 * i}\n")
    for i in range(5):
        lines.append(f"[points.hf{i}]\nref = {41001 + 2 * i}\ntype = 'float32'\n")
    for i in range(10):
        lines.append(f"[points.i{i}]\nref = {30001 + 13 * i}\n")
    for i in range(10):
        lines.append(f"[points.c{i}]\nref = '{1 + 250 * i:05d}'\n")
    for i in range(10):
        lines.append(f"[points.d{i}]\nref = {10001 + i}\n")
    return "".join(lines)


def test_a_map_of_50_points_over_4_tables_is_read_in_the_fewest_requests(tmp_path):
    path = _write(tmp_path, _spread_map(tmp_path))
    points = load_map(path).points.values()
    assert len(points) == 50
    # max_gap 0: every gap splits a block, so one read per run of adjacent points.
    assert len(plan_reads(points, 0)) == 15 + 1 + 10 + 10 + 1  # hf are adjacent: one read
    # A gap allowance bridges the gaps: holding 0..28 and 1000..1009 are 2 blocks (the
    # second is too far), input 0..118 fits one, coils 0..2250 are two (2000 bits a read).
    blocks = plan_reads(points, 1000)
    assert [(b.table.name, b.address, b.count) for b in blocks] == [
        ("holding", 0, 29),
        ("holding", 1000, 10),
        ("input", 0, 118),
        ("coils", 0, 1751),
        ("coils", 2000, 251),
        ("discrete", 0, 10),
    ]
    # The fewest the limits allow: holding spans 1010 registers (> 125) and coils 2251
    # bits (> 2000), so each needs two reads; input and discrete need one.
    assert len(blocks) == 2 + 1 + 2 + 1


def test_blocks_respect_the_read_limits():
    points = [_point(name=f"p{i}", address=i, type="uint32") for i in range(0, 200, 2)]
    blocks = plan_reads(points, 0)
    assert [b.count for b in blocks] == [124, 76]
    assert all(b.count <= 125 for b in blocks)


def test_read_points_decodes_every_point(tmp_path):
    pump = load_map(_write(tmp_path, PUMP))
    device = Device(DataModel())
    flow = encode_values([123.4], "float32", "CDAB")
    device.model.holding_registers[107:111] = type(device.model.holding_registers)("H", [*flow, 1, 0b1000])
    device.model.holding_registers[119] = 225
    device.model.coils[0] = 1
    device.model.input_registers[4] = struct.unpack(">H", struct.pack(">h", -40))[0]
    requests: list = []
    readings = read_points(device_executor(device, requests), list(pump.points.values()), pump.max_gap)
    values = {r.point.name: r.value for r in readings}
    assert values == {
        "flow": pytest.approx(12.34, rel=1e-6),
        "state": "running",
        "alarm_high": True,
        "setpoint": 22.5,
        "run": True,
        "speed": -40,
    }
    assert [r.point.name for r in readings] == list(pump.points)
    assert len(requests) == 4  # 40108..40111, 40120, coil 1, input 5


def test_a_merged_read_refused_with_exception_02_is_retried_point_by_point(tmp_path):
    device = Device(DataModel())
    device.model.defined = {"holding_registers": bytearray(65536)}
    device.model.defined["holding_registers"][0] = 1
    device.model.defined["holding_registers"][2] = 1
    device.model.holding_registers[0] = 5
    device.model.holding_registers[2] = 7
    points = [_point(name="a", address=0), _point(name="b", address=2)]
    requests: list = []
    readings = read_points(device_executor(device, requests), points, max_gap=5)
    assert [r.value for r in readings] == [5, 7]
    assert [(r.address, r.count) for r in requests] == [(0, 3), (0, 1), (2, 1)]


def test_the_point_at_fault_is_named_and_the_others_are_read(tmp_path):
    """Issue 28 §3: one missing point no longer blanks out the whole read."""
    device = Device(DataModel())
    device.model.defined = {"holding_registers": bytearray(65536)}
    device.model.defined["holding_registers"][0] = 1
    device.model.holding_registers[0] = 5
    points = [_point(name="a", address=0), _point(name="missing", address=1)]
    with pytest.raises(PartialRead, match=r"missing \(40002\): exception 02 Illegal Data Address") as caught:
        read_points(device_executor(device, []), points)
    assert str(caught.value).endswith("; 1 of 2 points read")
    assert exit_code_for(caught.value) == ExitCode.PARTIAL
    a, missing = caught.value.readings
    assert (a.value, a.error) == (5, None)
    assert missing.value is None and missing.error.answer.startswith("exception 02 Illegal Data Address")


def test_a_refused_merged_read_stays_split_for_the_next_read():
    device = Device(DataModel())
    device.model.defined = {"holding_registers": bytearray(65536)}
    for address in (0, 2, 10):
        device.model.defined["holding_registers"][address] = 1
    points = [_point(name=name, address=address) for name, address in (("a", 0), ("b", 2), ("c", 10))]
    reader = MapReader(points, max_gap=20)
    requests: list = []
    for _ in range(3):
        assert [r.value for r in reader.read(device_executor(device, requests))] == [0, 0, 0]
    assert [(r.address, r.count) for r in requests] == [(0, 11), (0, 1), (2, 1), (10, 1)] + [
        (0, 1),
        (2, 1),
        (10, 1),
    ] * 2


def test_a_point_the_device_refuses_outright_fails_alone_and_all_refused_is_the_error():
    device = Device(DataModel())
    device.model.defined = {"holding_registers": bytearray(65536), "input_registers": bytearray(65536)}
    device.model.defined["holding_registers"][0] = 1
    # Input registers answer exception 02 for every address: the point there is refused, the
    # holding register is read.
    points = [_point(name="h", address=0), _point(name="i", table=INPUT_REGISTERS, address=0)]
    with pytest.raises(PartialRead, match=r"^i \(30001\): exception 02"):
        read_points(device_executor(device, []), points)
    with pytest.raises(ModbusException, match=r"^i \(30001\): exception 02") as caught:
        read_points(device_executor(device, []), points[1:])
    assert exit_code_for(caught.value) == ExitCode.EXCEPTION


# --- non-finite values (issues 28 §3 and 29) --------------------------------------


NAN_32, INF_32, NEG_INF_32 = [0x7FC0, 0x0000], [0x7F80, 0x0000], [0xFF80, 0x0000]


@pytest.mark.parametrize("scale, offset", [(None, None), ("0.1", None), ("10", "-5"), (None, "3")])
def test_nan_and_infinity_read_as_themselves_scaled_or_not(scale, offset):
    import math
    from decimal import Decimal

    point = _point(
        type="float32",
        scale=None if scale is None else Decimal(scale),
        offset=None if offset is None else Decimal(offset),
    )
    assert math.isnan(point.value_of(NAN_32))
    assert point.value_of(INF_32) == math.inf
    assert point.value_of(NEG_INF_32) == -math.inf
    assert math.isnan(point.number_of(point.value_of(NAN_32)))
    wide = _point(type="float64", scale=point.scale, offset=point.offset)
    assert wide.value_of(encode_values([math.inf], "float64")) == math.inf


def test_a_negative_scale_turns_infinity_round():
    import math
    from decimal import Decimal

    point = _point(type="float32", scale=Decimal("-0.5"), offset=Decimal(7))
    assert point.value_of(INF_32) == -math.inf
    assert point.value_of(NEG_INF_32) == math.inf


def test_a_scaled_value_beyond_a_double_is_infinite_as_float_arithmetic_makes_it():
    import math
    from decimal import Decimal

    point = _point(type="float64", scale=Decimal("1e10"))
    assert point.value_of(encode_values([1e300], "float64")) == math.inf
    assert point.value_of(encode_values([-1e300], "float64")) == -math.inf
    assert point.value_of(encode_values([1e290], "float64")) == 10**300  # still a whole number


def test_a_written_value_too_large_for_any_step_is_out_of_range():
    from decimal import Decimal

    setpoint = _point(scale=Decimal("0.1"), writable=True)
    for text in ("1e999999", "-1e99999999999"):
        with pytest.raises(UsageError, match="out of range"):
            setpoint.registers_for(text)


# --- what a map may say (issues 28 §5 and 29) --------------------------------------


@pytest.mark.parametrize(
    "value, words",
    [
        ('"1e999999999"', "1e999999999 is beyond a double"),
        ('"1e5000"', "1e5000 is beyond a double"),
        ('"-1e309"', "-1e309 is beyond a double"),
        ('"1e-400"', "1e-400 is too small"),
    ],
)
@pytest.mark.parametrize("key", ["scale", "offset"])
def test_scale_and_offset_are_numbers_a_double_holds(tmp_path, key, value, words):
    if key == "offset" and "too small" in words:
        return  # an offset that small is 0 to a double: harmless, and allowed
    path = _write(tmp_path, f"[points.flow]\nref = 40001\n{key} = {value}\n")
    with pytest.raises(MapError, match=f"point flow: key {key}: {words}") as caught:
        load_map(path)
    assert str(caught.value).startswith(str(path))


def test_a_tiny_offset_and_the_largest_double_load(tmp_path):
    path = _write(tmp_path, '[points.a]\nref = 40001\noffset = "1e-400"\nscale = "1.7976931348623157e308"\n')
    assert load_map(path).points["a"].scale == __import__("decimal").Decimal("1.7976931348623157e308")


@pytest.mark.parametrize(
    "text",
    [
        "[points.a]\nref = 40001\ndescription = " + "[" * 5000 + "]" * 5000 + "\n",
        "[points.a]\nref = 40001\ndescription = " + "{a=" * 5000 + "1" + "}" * 5000 + "\n",
    ],
)
def test_a_deeply_nested_map_is_refused(tmp_path, text):
    path = _write(tmp_path, text)
    with pytest.raises(MapError, match="nested too deeply") as caught:
        load_map(path)
    assert str(caught.value).startswith(str(path))
    assert exit_code_for(caught.value) == ExitCode.USAGE


@pytest.mark.parametrize(
    "enum",
    ['{ 1 = "day", "0x1" = "night" }', '{ 1 = "day", "+1" = "night" }'],
)
def test_a_raw_value_labelled_twice_is_refused(tmp_path, enum):
    path = _write(tmp_path, f"[points.tariff]\nref = 40001\nenum = {enum}\n")
    with pytest.raises(MapError, match="point tariff: key enum: raw value 1 is labelled twice"):
        load_map(path)


def test_a_raw_value_labelled_twice_in_a_csv_cell_is_refused(tmp_path):
    path = _write(tmp_path, "name,ref,enum\ntariff,40001,1=day; 1=night\n", "m.csv")
    with pytest.raises(MapError, match="point tariff: key enum: raw value 1 is labelled twice"):
        load_map(path)


@pytest.mark.parametrize(
    "kind, enum, words",
    [
        ("uint16", "{ 70000 = 'x' }", "70000 is out of range 0..65535 for uint16"),
        ("int16", "{ -40000 = 'x' }", "-40000 is out of range -32768..32767 for int16"),
        ("float32", "{ 16777217 = 'x' }", "a float32 cannot hold 16777217"),
    ],
)
def test_a_raw_value_the_type_cannot_hold_is_refused(tmp_path, kind, enum, words):
    path = _write(tmp_path, f"[points.mode]\nref = 40001\ntype = '{kind}'\nenum = {enum}\n")
    with pytest.raises(MapError, match=f"point mode: key enum: {words}"):
        load_map(path)


@pytest.mark.parametrize("kind", ["float32", "float64"])
def test_an_enum_on_a_float_point_labels_its_whole_values(tmp_path, kind):
    import math

    path = _write(
        tmp_path,
        f"[points.mode]\nref = 40001\ntype = '{kind}'\nenum = {{ 0 = 'off', 1 = 'heat', 2 = 'cool' }}\n"
        "access = 'rw'\n",
    )
    mode = load_map(path).points["mode"]
    assert mode.value_of(encode_values([2.0], kind)) == "cool"
    assert mode.value_of(encode_values([-0.0], kind)) == "off"
    assert mode.value_of(encode_values([1.5], kind)) == 1.5  # between labels: the number
    assert math.isnan(mode.value_of(encode_values([math.nan], kind)))
    assert mode.number_of("heat") == 1
    assert mode.registers_for("heat") == encode_values([1.0], kind)
    assert mode.registers_for("2") == encode_values([2.0], kind)


def test_a_value_an_enum_does_not_label_is_said_to_have_no_label():
    state = _point(enum={0: "stopped", 1: "running"})
    assert state.no_label(state.value_of([7])) and state.no_label(state.value_of([0])) is False
    assert state.value_of([7]) == 7 and state.number_of(7) == 7
    assert _point().no_label(7) is False  # a point without enum has no labels to miss
    float_state = _point(type="float32", enum={1: "on"})
    assert float_state.no_label(float_state.value_of(encode_values([1.5], "float32")))


# --- CSV maps by the csv module's rules (issue 29) ------------------------------------


def _csv(tmp_path, text: str, encoding: str = "utf-8"):
    path = tmp_path / "meter.csv"
    path.write_bytes(text.encode(encoding))
    return path


def test_a_line_separator_inside_a_cell_is_text(tmp_path):
    path = _csv(tmp_path, "name,ref,description\nflow,40001,outlet\u2028flow\nlevel,40002,tank\n")
    points = load_map(path).points
    assert list(points) == ["flow", "level"]
    assert points["flow"].description == "outlet\u2028flow"


def test_a_quoted_newline_stays_in_its_cell(tmp_path):
    path = _csv(tmp_path, 'name,ref,description\r\nflow,40001,"outlet\r\nflow"\r\nlevel,40002,tank\r\n')
    points = load_map(path).points
    assert list(points) == ["flow", "level"]
    assert points["flow"].description == "outlet\r\nflow"


def test_an_excel_csv_with_a_byte_order_mark_loads(tmp_path):
    path = _csv(tmp_path, "name,ref,unit\r\nflow,40001,m3/h\r\n", "utf-8-sig")
    assert load_map(path).points["flow"].unit == "m3/h"


@pytest.mark.parametrize(
    "text, words",
    [
        ("name,ref,colour\nflow,40001,\n", "line 1: unknown column colour \\(known: name, ref, table"),
        ("name,ref,ref\nflow,40001,40002\n", "line 1: column ref is named twice"),
        ("name,ref,\nflow,40001,red\n", "line 2: a cell under no column name"),
        ("name;ref;unit\nflow;40001;m3/h\n", "columns are separated by commas"),
        ("ref,unit\n40001,m3/h\n", "the first row names the columns, one of them name"),
    ],
)
def test_csv_columns_are_checked_by_their_header(tmp_path, text, words):
    path = _csv(tmp_path, text)
    with pytest.raises(MapError, match=words) as caught:
        load_map(path)
    assert str(caught.value).startswith(str(path))


def test_trailing_empty_columns_from_a_spreadsheet_are_allowed(tmp_path):
    path = _csv(tmp_path, "name,ref,unit,,\nflow,40001,m3/h,,\n")
    assert load_map(path).points["flow"].unit == "m3/h"


def test_a_csv_cell_over_128_kib_is_refused_by_its_key(tmp_path):
    path = _csv(tmp_path, "name,ref,description\nflow,40001," + "x" * (128 * 1024 + 1) + "\n")
    with pytest.raises(MapError, match="line 2: point flow: key description: .*128 KiB") as caught:
        load_map(path)
    assert str(caught.value).startswith(str(path))
    import csv

    assert csv.field_size_limit() == 128 * 1024  # the csv module's limit is left as it was
    path = _csv(tmp_path, "name,ref\n" + "f" * (128 * 1024 + 1) + ",40001\n")
    with pytest.raises(MapError, match="line 2: key name: a name of 131073 characters"):
        load_map(path)
