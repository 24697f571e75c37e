"""The quality gates of the device library (issue 43, docs/maps-library.md): every map mbtool
ships loads, says what device it is and from which manual, uses units from a fixed list,
identifies its device by reads alone, and has a twin that answers every point plausibly."""

from __future__ import annotations

import math

import pytest
from helpers.fakes import device_executor

from mbtool.codec.tables import READS
from mbtool.device.datafile import load_data
from mbtool.device.device import Device
from mbtool.library import library_names, load_named_map, twin_path
from mbtool.library.identify import judge, probe
from mbtool.registermap.header import KINDS
from mbtool.registermap.plan import MapReader

# SI and what meters, inverters and chargers print (docs/maps-library.md).
UNITS = {
    "",
    "V",
    "kV",
    "A",
    "mA",
    "W",
    "kW",
    "VA",
    "kVA",
    "var",
    "kvar",
    "Wh",
    "kWh",
    "MWh",
    "varh",
    "kvarh",
    "Hz",
    "°C",
    "%",
    "s",
    "min",
    "h",
    "Ah",
    "kΩ",
    "Ω",
    "deg",
}
READ_CODES = {0x01, 0x02, 0x03, 0x04}
NAMES = library_names()


def test_the_library_has_maps_of_several_kinds():
    kinds = {load_named_map(name).header.kind for name in NAMES}
    assert len(NAMES) >= 40 and len(kinds) >= 4, (len(NAMES), kinds)


@pytest.fixture(params=NAMES)
def name(request):
    return request.param


def test_the_header_says_what_device_and_which_manual(name):
    header = load_named_map(name).header
    assert header is not None, f"{name}: no [device] header"
    assert header.manufacturer and header.model, name
    assert header.kind in KINDS and header.transport, name
    assert len(header.source) > 10, f"{name}: source names the manual, its version and pages"
    assert header.signature, f"{name}: identify needs a signature"
    if header.transport in ("rtu", "both"):
        assert header.baud and header.parity and header.stopbits, f"{name}: serial defaults"


def test_units_come_from_the_list(name):
    units = {point.unit for point in load_named_map(name).points.values()}
    assert units <= UNITS, f"{name}: {sorted(units - UNITS)} not among the library's units"


def test_a_signature_says_something_of_the_values(name):
    """A signature of registers that merely answer fits any device that answers everything
    (pymodbus's default device does): one probe at least has a shape."""
    expectations = {check.expect for check in load_named_map(name).header.signature}
    assert expectations & {"equals", "within", "matches"}, f"{name}: only {sorted(expectations)}"


def test_signature_probes_are_reads(name):
    for check in load_named_map(name).header.signature:
        point = check.point
        request = READS[point.table.name](point.address, point.size)
        assert request.function_code in READ_CODES


def test_the_twin_answers_every_point_as_it_holds_it(name):
    """One read of the whole map through the planner, in-process: every point answers, with
    the value its registers hold in the twin, scaled, and a plausible one (no word order
    mixed up between map and twin: no 1e-36 V)."""
    register_map = load_named_map(name)
    model, _ = load_data(str(twin_path(name)), frozenset({1}))
    requests: list = []
    readings = MapReader(list(register_map.points.values()), register_map.max_gap).read(
        device_executor(Device(model), requests)
    )
    assert [r.point.name for r in readings if r.error is not None] == []
    for reading in readings:
        point = reading.point
        held = _held(model, point)
        assert list(reading.raw) == held, point.name
        assert reading.value == point.value_of(held), point.name
        if isinstance(reading.value, float):
            plausible = reading.value == 0 or 1e-3 <= abs(reading.value) < 1e9
            assert math.isfinite(reading.value) and plausible, (
                f"{name}: {point.name} reads {reading.value}: word order or scale?"
            )


def test_the_twin_fits_its_signature(name):
    """Read as identify reads it (library.identify.probe), the twin fits every probe."""
    header = load_named_map(name).header
    model, _ = load_data(str(twin_path(name)), frozenset({1}))
    answers = probe(device_executor(Device(model), []), {name: header}, deadline=math.inf)
    for check in header.signature:
        fits, evidence = judge(check, answers)
        assert fits, f"{name}: {evidence}"


TABLES = {
    "coils": "coils",
    "discrete": "discrete_inputs",
    "input": "input_registers",
    "holding": "holding_registers",
}


def _held(model, point) -> list:
    """What the twin holds at the point: its registers, or its bit."""
    table = getattr(model, TABLES[point.table.name])
    if point.table.bits:
        return [bool(table[point.address])]
    return list(table[point.address : point.address + point.size])
