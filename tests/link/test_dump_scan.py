"""Dumping a device (issue 16): the exact scan of link/dump.py against the device model with holes, and
the data file a dump makes."""

from __future__ import annotations

import random

import pytest
from helpers.fakes import device_executor as executor

from mbtool.codec.errors import ModbusException
from mbtool.codec.tables import COILS, HOLDING_REGISTERS
from mbtool.device.device import Device
from mbtool.device.model import DataModel
from mbtool.link.dump import Dumper, OutOfRequests, Span, TableDump, runs_of


def sparse_device(defined: dict[str, list[int]]) -> Device:
    """A device that has only the addresses listed, each holding a value of its own."""
    model = DataModel()
    model.defined = {}
    for table, addresses in defined.items():
        mask = model.defines(table, 65536)
        values = getattr(model, table)
        for address in addresses:
            mask[address] = 1
            values[address] = (address * 7 + 3) & (1 if table in ("coils", "discrete_inputs") else 0xFFFF)
    return Device(model)


@pytest.mark.parametrize("seed", range(8))
def test_the_dump_finds_every_hole_exactly(seed):
    rng = random.Random(seed)
    present = sorted(rng.sample(range(2000), rng.randint(1, 600)))
    present += list(range(3000, 3000 + rng.randint(1, 400)))  # and a long block
    device = sparse_device({"holding_registers": present})
    sent: list = []
    dump = TableDump(HOLDING_REGISTERS)
    Dumper(executor(device, sent)).dump(Span(HOLDING_REGISTERS, 0, 3999), dump)
    assert [(first, first + len(values) - 1) for first, values in dump.runs] == runs_of(sorted(present))
    values = {first + i: v for first, vs in dump.runs for i, v in enumerate(vs)}
    assert values == {a: (a * 7 + 3) & 0xFFFF for a in present}
    assert all(request.count <= 125 for request in sent)


def test_a_full_table_takes_one_request_per_limit():
    device = sparse_device({"holding_registers": list(range(1000))})
    sent: list = []
    dump = TableDump(HOLDING_REGISTERS)
    Dumper(executor(device, sent)).dump(Span(HOLDING_REGISTERS, 0, 999), dump)
    assert dump.count == 1000 and len(sent) == 8  # ceil(1000 / 125)


def test_a_hole_costs_one_request_and_a_block_few_more_than_its_reads():
    # Blocks of 100 with holes of 20 between them: each hole address is one refused
    # read; each block a handful of reads as the scan gallops back up to the limit.
    present = [a for a in range(1200) if a % 120 < 100]
    device = sparse_device({"holding_registers": present})
    sent: list = []
    dumper = Dumper(executor(device, sent))
    dumper.dump(Span(HOLDING_REGISTERS, 0, 1199), TableDump(HOLDING_REGISTERS))
    holes, blocks = 1200 - len(present), 10
    assert holes <= len(sent) <= holes + blocks * 16
    assert holes <= dumper.refused < len(sent)  # every hole is a refusal, counted


def test_scattered_registers_take_at_most_two_answered_reads_a_block():
    """Issue (reads that scale): registers scattered one by one, as in bench/dump.py."""
    present = sorted(random.Random(7).sample(range(5000), 750))
    device = sparse_device({"holding_registers": present})
    sent: list = []
    dumper = Dumper(executor(device, sent))
    dump = TableDump(HOLDING_REGISTERS)
    dumper.dump(Span(HOLDING_REGISTERS, 0, 4999), dump)
    assert dump.count == len(present)
    answered = len(sent) - dumper.refused
    assert answered <= 2 * len(runs_of(present))


def test_bits_are_read_up_to_2000_at_a_time():
    device = sparse_device({"coils": list(range(5000))})
    sent: list = []
    dump = TableDump(COILS)
    Dumper(executor(device, sent)).dump(Span(COILS, 0, 4999), dump)
    assert dump.count == 5000 and [r.count for r in sent] == [2000, 2000, 1000]
    assert dump.runs[0][1][:4] == [1, 0, 1, 0]  # (a * 7 + 3) & 1


def test_a_table_the_device_lacks_is_absent():
    device = sparse_device({"holding_registers": [0]})
    device.model  # noqa: B018 - the model answers exception 01 for nothing; a stand-in does
    sent: list = []

    def no_coils(request):
        sent.append(request)
        raise ModbusException(0x01, 0x01)

    dump = TableDump(COILS)
    Dumper(no_coils).dump(Span(COILS, 0, 65535), dump)
    assert dump.absent and dump.runs == [] and len(sent) == 1


def test_the_budget_stops_the_scan_with_what_was_read():
    device = sparse_device({"holding_registers": list(range(1000))})
    dump = TableDump(HOLDING_REGISTERS)
    with pytest.raises(OutOfRequests):
        Dumper(executor(device, []), max_requests=3).dump(Span(HOLDING_REGISTERS, 0, 999), dump)
    assert dump.runs == [(0, [(a * 7 + 3) & 0xFFFF for a in range(375)])]


def test_other_exceptions_end_the_dump():
    def failing(request):
        raise ModbusException(0x03, 0x04)

    with pytest.raises(ModbusException):
        Dumper(failing).dump(Span(HOLDING_REGISTERS, 0, 10), TableDump(HOLDING_REGISTERS))


def test_scattered_registers_cost_little_over_one_request_per_hole_and_run():
    # Exactness costs at least one request per hole (a refused read confirms at most one
    # address) plus one per run; the scan stays within a quarter of that.
    present = sorted(random.Random(7).sample(range(8000), 1500))
    device = sparse_device({"holding_registers": present})
    sent: list = []
    Dumper(executor(device, sent)).dump(Span(HOLDING_REGISTERS, 0, 7999), TableDump(HOLDING_REGISTERS))
    floor = (8000 - len(present)) + len(runs_of(present))
    assert floor <= len(sent) <= 1.25 * floor


def test_a_data_file_takes_runs_and_a_completeness_mark(tmp_path):
    from mbtool.device.datafile import load_data

    path = tmp_path / "dump.toml"
    path.write_text(
        "sparse = true\ncomplete = false\n[holding_registers]\n0 = [1, 2]\n"
        "[holding_registers.10]\nvalue = 7\ncount = 3\n"
    )
    model, _ = load_data(str(path), frozenset({1}))
    assert list(model.holding_registers[10:13]) == [7, 7, 7] and model.holding_registers[13] == 0
    device = Device(model)
    sent: list = []
    dump = TableDump(HOLDING_REGISTERS)
    Dumper(executor(device, sent)).dump(Span(HOLDING_REGISTERS, 0, 20), dump)
    assert dump.runs == [(0, [1, 2]), (10, [7, 7, 7])]


@pytest.mark.parametrize(
    "run, words", [("{ value = 1 }", "a run is"), ("{ value = 1, count = 0 }", "out of range")]
)
def test_a_bad_run_is_refused_naming_it(tmp_path, run, words):
    from mbtool.device.datafile import load_data
    from mbtool.errors import UsageError

    path = tmp_path / "bad.toml"
    path.write_text(f"[holding_registers]\n5 = {run}\n")
    with pytest.raises(UsageError, match=words):
        load_data(str(path), frozenset({1}))
