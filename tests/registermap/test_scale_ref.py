"""A map point scaled by another point's value (``scale_ref``, SunSpec's W and W_SF) and the
values SunSpec calls unimplemented as ``invalid`` (NaN, a string of NULs) (issue 34).

The reads go to a device of the test's own: a dict of holding registers behind the
``execute`` a map read takes, answering exception 02 where it has no register, so every
request the planner makes is seen.
"""

from __future__ import annotations

import json
import struct

import pytest
from helpers.run import TESTS_DIR, run_cli

from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.codec.errors import ModbusException
from mbtool.errors import PartialRead, UsageError
from mbtool.registermap.load import MapError, load_map
from mbtool.registermap.plan import MapReader, plan_reads, write_request
from mbtool.registermap.point import NoScaleFactor

INVERTER = (TESTS_DIR / "data" / "scale-ref-inverter.toml").read_text()


def _map(tmp_path, text=INVERTER):
    path = tmp_path / "inverter.toml"
    path.write_text(text)
    return load_map(path)


class Registers:
    """Holding registers at the addresses given, exception 02 elsewhere; the reads it got."""

    def __init__(self, values: dict[int, int]) -> None:
        self.values = values
        self.requests: list[tuple[int, int]] = []

    def execute(self, request):
        assert isinstance(request, ReadHoldingRegisters)
        self.requests.append((request.address, request.count))
        wanted = range(request.address, request.address + request.count)
        if any(address not in self.values for address in wanted):
            raise ModbusException(3, 2)
        registers = [self.values[address] for address in wanted]
        pdu = bytes([3, 2 * len(registers)]) + struct.pack(f">{len(registers)}H", *registers)
        return request.decode_response(pdu)


def _around(values: dict[int, int], first: int = 80, last: int = 130) -> dict[int, int]:
    return {address: 0 for address in range(first, last)} | values


# --- reading --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("raw", "factor", "value"),
    [(1234, -1, 123.4), (1234, 0, 1234), (1234, 2, 123400), (-5, -2, -0.05), (0x7FFF, -10, 3.2767e-06)],
)
def test_a_value_is_raw_times_ten_to_its_scale_factor(tmp_path, raw, factor, value):
    inverter = _map(tmp_path)
    device = Registers(_around({100: raw & 0xFFFF, 120: factor & 0xFFFF}))
    (reading,) = MapReader([inverter.points["W"]]).read(device.execute)
    assert reading.value == value
    assert repr(reading.value) == repr(value)  # exact in decimal: 123.4, not 123.39999999999999


def test_a_point_and_its_scale_factor_are_read_in_one_request_over_the_gap(tmp_path):
    """W at 100 and W_SF at 120, max_gap 0: one read of 21 registers, not two."""
    inverter = _map(tmp_path)
    device = Registers(_around({100: 50, 120: 1}))
    readings = MapReader([inverter.points["W"]], max_gap=0).read(device.execute)
    assert device.requests == [(100, 21)]
    assert [(r.point.name, r.value) for r in readings] == [("W", 500)]  # W_SF read, not shown


def test_a_scale_factor_before_its_point_is_read_with_it_too(tmp_path):
    """SunSpec's model 160: each module's DCA after the model's DCA_SF."""
    text = INVERTER.replace("address = 120", "address = 60")
    inverter = _map(tmp_path, text)
    device = Registers(_around({100: 7, 60: 0xFFFF}, first=50))
    (reading,) = MapReader([inverter.points["W"]]).read(device.execute)
    assert device.requests == [(60, 41)]
    assert reading.value == 0.7


def test_points_between_a_point_and_its_factor_join_the_read_and_unrelated_runs_do_not(tmp_path):
    inverter = _map(tmp_path)
    blocks = plan_reads(inverter.points.values(), 0)
    # A (90) reaches A_SF (94) and W (100) reaches W_SF (120): two reads; with no scale
    # factors four runs would be four reads.
    assert [(b.address, b.count) for b in blocks] == [(90, 5), (100, 21)]


def test_a_scale_factor_out_of_one_reads_reach_is_read_apart(tmp_path):
    text = INVERTER.replace("address = 120", "address = 300")
    inverter = _map(tmp_path, text)
    device = Registers(_around({100: 50, 300: 0xFFFE}, last=310))
    (reading,) = MapReader([inverter.points["W"]]).read(device.execute)
    assert device.requests == [(100, 1), (300, 1)]
    assert reading.value == 0.5


def test_an_unimplemented_scale_factor_leaves_its_point_with_no_value(tmp_path):
    """0x8000 in W_SF: W has no value (null, "invalid"), never the raw number unscaled."""
    inverter = _map(tmp_path)
    device = Registers(_around({100: 1234, 120: 0x8000}))
    (reading,) = MapReader([inverter.points["W"]]).read(device.execute)
    assert reading.value is None and reading.error is None


def test_a_scale_factor_the_device_refuses_fails_its_point_and_names_the_factor(tmp_path):
    inverter = _map(tmp_path, INVERTER.replace("address = 120", "address = 300"))
    device = Registers(_around({100: 1234}))  # 300 answers exception 02
    with pytest.raises(PartialRead) as caught:
        MapReader([inverter.points["W"], inverter.points["A"]]).read(device.execute)
    readings = {r.point.name: r for r in caught.value.readings}
    assert readings["W"].value is None
    assert "its scale factor W_SF (40301): exception 02" in str(readings["W"].error)
    assert readings["A"].value == 0 and readings["A"].error is None


def test_nan_and_a_string_of_nuls_are_no_value_when_the_map_says_so(tmp_path):
    text = """
[points.Hz]
table = "holding"
address = 0
type = "float32"
invalid = [nan]
[points.SN]
table = "holding"
address = 2
type = "string"
count = 2
invalid = [""]
"""
    points = _map(tmp_path, text).points
    nan = struct.unpack(">2H", struct.pack(">f", float("nan")))
    device = Registers({0: nan[0], 1: nan[1], 2: 0, 3: 0})
    assert [r.value for r in MapReader(points.values()).read(device.execute)] == [None, None]
    device = Registers({0: 0x4248, 1: 0, 2: 0x4142, 3: 0})
    assert [r.value for r in MapReader(points.values()).read(device.execute)] == [50.0, "AB"]


# --- checked when the map is loaded -----------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (
            ('scale_ref = "W_SF"', 'scale_ref = "X_SF"'),
            "point W: key scale_ref: the map has no point named X_SF",
        ),
        (
            ('scale_ref = "W_SF"', 'scale_ref = "W"'),
            "point W: key scale_ref: a point cannot be its own scale factor",
        ),
        (
            ('scale_ref = "W_SF"', 'scale_ref = "W_SF"\nscale = 0.1'),
            "the scale is read from W_SF; scale does not go",
        ),
        (
            ('type = "int16"\nunit = "W"', 'type = "string"\ncount = 2\nunit = "W"'),
            "a string has no number to scale",
        ),
        (('address = 120\ntype = "int16"', 'address = 120\ntype = "float32"'), "W_SF is not a whole number"),
        (
            ('address = 94\ntype = "int16"', 'address = 94\ntype = "int16"\nscale = 2'),
            "A_SF is scaled or labelled",
        ),
        (("[points.W_SF]", '[points.W_SF]\nscale_ref = "A_SF"'), "W_SF has a scale_ref of its own"),
        (('scale_ref = "W_SF"', "scale_ref = 3"), "point W: key scale_ref: 3 is not a point's name"),
        (("invalid = [0x8000]\n\n[points.W_SF]", "invalid = [nan]\n\n[points.W_SF]"), "a int16 holds no NaN"),
    ],
)
def test_a_bad_scale_ref_is_refused_when_the_map_is_loaded(tmp_path, change, words):
    text = INVERTER.replace(*change)
    assert text != INVERTER
    with pytest.raises(MapError) as caught:
        _map(tmp_path, text)
    assert words in str(caught.value)


def test_a_string_takes_no_invalid_but_a_string_of_nuls(tmp_path):
    text = '[points.SN]\nref = 40001\ntype = "string"\ncount = 2\ninvalid = ["none"]\n'
    with pytest.raises(MapError, match=r'a string\'s no data is \[""\]'):
        _map(tmp_path, text)


# --- writing --------------------------------------------------------------------------------


def test_a_written_value_undoes_the_scale_factor_given(tmp_path):
    w = _map(tmp_path).points["W"]
    assert w.raw_for("50.5", scale_factor=-1) == 505
    assert w.registers_of(w.raw_for("-2000", scale_factor=2)) == [0xFFEC]
    with pytest.raises(UsageError, match="W: 50.55 is not a whole number of steps of 0.1; the nearest"):
        w.raw_for("50.55", scale_factor=-1)
    with pytest.raises(UsageError, match=r"W: 5000 W \(raw 50000\) is out of range"):
        w.raw_for("5000", scale_factor=-1)


def test_a_scaled_point_is_not_written_without_its_scale_factor(tmp_path):
    w = _map(tmp_path).points["W"]
    with pytest.raises(NoScaleFactor, match="W: its scale factor, W_SF, has no value: 50 cannot be scaled"):
        write_request(w, "50")
    with pytest.raises(UsageError, match="W: fifty is not a number") as caught:
        write_request(w, "fifty")  # what the value alone says is said before the device is asked
    assert not isinstance(caught.value, NoScaleFactor)


# --- write -m and diff -m, in-process ------------------------------------------------------------


def test_write_m_dry_run_shows_the_scale_factor_read_and_sends_nothing(tmp_path):
    path = tmp_path / "inverter.toml"
    path.write_text(INVERTER)
    res = run_cli("write", "-m", path, "W=12.5", "-p", "tcp://127.0.0.1:9", "--dry-run")
    assert res.returncode == 0, res
    assert "Read Holding Registers" in res.stdout and "Write" not in res.stdout
    assert "then each point is written in the scale its scale factor reads" in res.stderr


def test_write_m_of_a_scaled_point_to_unit_0_is_refused_before_anything_is_sent(tmp_path):
    path = tmp_path / "inverter.toml"
    path.write_text(INVERTER)
    res = run_cli("write", "-m", path, "W=12.5", "-p", "/dev/null", "-u", "0")
    assert res.returncode == 2
    assert "W_SF is read first, to scale what is written: unit 0 (broadcast) cannot be read" in res.stderr


def test_diff_m_scales_each_side_by_its_own_scale_factor(tmp_path):
    """Two dumps of an inverter: W raw 1234 with W_SF -1, then 1234 with W_SF -2."""
    before, after = tmp_path / "before.toml", tmp_path / "after.toml"
    before.write_text("sparse = true\n[holding_registers]\n100 = 1234\n120 = 0xFFFF\n")
    after.write_text("sparse = true\n[holding_registers]\n100 = 1235\n120 = 0xFFFE\n")
    path = tmp_path / "inverter.toml"
    path.write_text(INVERTER)
    res = run_cli("diff", before, after, "-m", path, "-o", "json")
    assert res.returncode == 1, res
    changes = {change["name"]: (change["a"], change["b"]) for change in json.loads(res.stdout)["differences"]}
    assert changes == {"W": (123.4, 12.35), "W_SF": (-1, -2)}
