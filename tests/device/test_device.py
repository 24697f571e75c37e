"""The simulated device (mbtool.device.device) PDU by PDU: every function code of the spec,
its exception codes, the FC08 counters, the FC12 event log, broadcast and --data files."""

from __future__ import annotations

import json
import struct
import time

import pytest
from helpers.run import REPO_ROOT

from mbtool.codec.framing import make_framer
from mbtool.device.datafile import load_data
from mbtool.device.device import Device, Faults
from mbtool.device.model import MAX_FILES, demo_model
from mbtool.errors import UsageError

H = bytes.fromhex


def dev(units=(1,)) -> Device:
    return Device(demo_model(), frozenset(units))


def ask(device: Device, pdu: str, unit: int = 1) -> bytes | None:
    return device.handle(unit, H(pdu.replace(" ", "")))


# --- the tables -------------------------------------------------------------------------


def test_reads_of_the_demo_data():
    d = dev()
    assert ask(d, "03 0000 0003") == H("03 06 0000 0001 0002")
    assert ask(d, "04 0000 0002") == H("04 04 03E8 03E9")
    assert ask(d, "01 0000 000A") == H("01 02 55 01")  # LSB first, unused high bits 0 (spec §1)
    assert ask(d, "02 0000 0004") == H("02 01 09")


@pytest.mark.parametrize(
    ("pdu", "reply"),
    [
        ("01 0000 0000", "81 03"),  # quantity 0
        ("01 0000 07D1", "81 03"),  # 2001 bits
        ("03 0000 007E", "83 03"),  # 126 registers
        ("03 FFFF 0002", "83 02"),  # past 65535
        ("04 FFFF 0002", "84 02"),
        ("02 FFF0 0011", "82 02"),
        ("05 0001 FF01", "85 03"),  # FC05 value neither FF00 nor 0000 (spec §3)
        ("05 0001 00", "85 03"),  # truncated
        ("0F 0000 0000 00", "8F 03"),
        ("0F FFFF 0002 01 03", "8F 02"),
        ("10 0000 0002 03 000100", "90 03"),  # byte count does not fit the quantity
        ("10 FFFF 0002 04 00010002", "90 02"),
        ("17 0000 0001 0000 0000 00", "97 03"),  # FC23 write quantity 0
        ("2B 0D 01 00", "AB 01"),  # MEI type other than 0E
        ("2B 0E 05 00", "AB 03"),  # read code 5
        ("2B 0E 04 42", "AB 02"),  # no object 42
        ("08 0099 0000", "88 01"),  # unknown sub-function
        ("08 000B 0001", "88 03"),  # counter sub-functions take 0000
        ("41", "C1 01"),  # unknown function code
        ("14 07 07 0001 0000 0001 00", "94 03"),  # byte count 8 is not 7n
        ("14 07 05 0001 0000 0001", "94 02"),  # reference type 5
        ("14 07 06 0001 270F 0002", "94 02"),  # record 9999 + 2 runs past the file
    ],
)
def test_exception_codes(pdu, reply):
    assert ask(dev(), pdu) == H(reply)


def test_writes_and_echoes():
    d = dev()
    assert ask(d, "05 0010 FF00") == H("05 0010 FF00")
    assert ask(d, "01 0010 0001") == H("01 01 01")
    assert ask(d, "06 0010 1234") == H("06 0010 1234")
    assert ask(d, "0F 0020 000A 02 CD01") == H("0F 0020 000A")
    assert ask(d, "01 0020 000A") == H("01 02 CD 01")
    assert ask(d, "10 0030 0002 04 000A 0102") == H("10 0030 0002")
    assert ask(d, "03 0030 0002") == H("03 04 000A 0102")
    assert d.model.holding_registers[0x30] == 10


def test_mask_write_uses_the_complement():
    """Spec §3: current 0x12, AND 0xF2, OR 0x25 -> 0x17."""
    d = dev()
    ask(d, "06 0004 0012")
    assert ask(d, "16 0004 00F2 0025") == H("16 0004 00F2 0025")
    assert ask(d, "03 0004 0001") == H("03 02 0017")


def test_read_write_writes_before_it_reads():
    d = dev()
    assert ask(d, "17 0003 0002 0004 0001 02 ABCD") == H("17 04 0003 ABCD")


def test_fifo_queue():
    d = dev()
    assert ask(d, "18 00C8") == H("18 0008 0003 0101 0202 0303")
    ask(d, "06 0300 0000")
    assert ask(d, "18 0300") == H("18 0002 0000")
    ask(d, "06 0300 0020")  # 32 entries: more than 31 is exception 03 (spec §3)
    assert ask(d, "18 0300") == H("98 03")
    ask(d, "06 FFFF 0001")
    assert ask(d, "18 FFFF") == H("98 02")


def test_file_records():
    d = dev()
    assert ask(d, "15 0D 06 0004 0007 0003 06AF 04BE 100D") == H("15 0D 06 0004 0007 0003 06AF 04BE 100D")
    assert ask(d, "14 0E 06 0004 0008 0002 06 0003 0000 0002") == H("14 0C 05 06 04BE 100D 05 06 0000 0000")
    assert ask(d, "14 07 06 0004 270E 0001") == H("14 04 03 06 0000")


def test_exception_status():
    assert ask(dev(), "07") == H("07 6D")  # seed 002's example: 11 07 6D


def test_report_slave_id_default_is_the_unit():
    d = dev(units=(17,))
    assert ask(d, "11", unit=17) == H("11 08 11 FF") + b"mbtool"


# --- FC08, FC11, FC12: counters, listen-only and the event log -------------------------


def counter(d: Device, sub: int) -> int:
    reply = ask(d, f"08 {sub:04X} 0000")
    assert reply[:3] == H(f"08 {sub:04X}")
    return struct.unpack(">H", reply[3:])[0]


def test_return_query_data_and_diagnostic_register():
    d = dev()
    assert ask(d, "08 0000 A537") == H("08 0000 A537")
    assert ask(d, "08 0002 0000") == H("08 0002 0000")


def test_counters_count():
    d = dev(units=(1, 2))
    framer = make_framer("rtu", responses=False)
    ask(d, "03 0000 0001")
    ask(d, "03 FFFF 0002")  # an exception
    ask(d, "03 0000 0001", unit=2)  # another slave on the bus
    framer.feed(H("01 03 0000 0001 0000"))  # bad CRC
    for event in iter(framer.silence, None):
        d.answer_frame(event, framer)
    # bus messages: every frame seen, this poll included; the CRC error is counted by sub 0C
    assert counter(d, 0x0B) == 4
    assert counter(d, 0x0C) == 1  # CRC errors
    assert counter(d, 0x0D) == 1  # exceptions returned
    assert counter(d, 0x0E) == 6  # messages to unit 1: two reads and four counter polls
    assert counter(d, 0x0F) == 0
    assert counter(d, 0x10) == 0
    assert counter(d, 0x11) == 0
    assert counter(d, 0x12) == 0
    assert ask(d, "08 000A 0000") == H("08 000A 0000")  # clear counters
    assert counter(d, 0x0D) == 0


def test_listen_only_sequence_and_event_log():
    """Spec §4/§5: force listen-only, a read gets no reply, restart, the log shows both events."""
    d = dev()
    assert ask(d, "0B") == H("0B 0000 0000")
    ask(d, "03 0000 0001")
    assert ask(d, "0B") == H("0B 0000 0001")  # successful completions; polls not counted
    assert ask(d, "08 0004 0000") is None  # no reply to force listen-only
    assert ask(d, "03 0000 0001") is None  # silent while listening
    assert ask(d, "06 0000 0009") is None  # and does nothing
    assert ask(d, "08 0001 0000") is None  # restart leaves listen-only, still unanswered
    assert ask(d, "03 0000 0001") == H("03 02 0000")  # the write was not done
    log = ask(d, "0C")
    assert log[0] == 0x0C and log[1] == 6 + len(log[8:])
    status, events_count, messages = struct.unpack(">HHH", log[2:8])
    events = log[8:]
    assert status == 0
    # newest first: this poll's receive, the read's send and receive, the restart,
    # the three messages heard in listen-only mode, entering it, and before that
    assert list(events[:8]) == [0x80, 0x40, 0x80, 0x00, 0xA0, 0xA0, 0xA0, 0x04]
    assert events[8] == 0x80  # the force-listen-only request itself
    assert messages == 2  # the restart cleared the counters: the read and this poll since
    # an exception reply logs a send event with the read-exception bit
    ask(d, "03 FFFF 0002")
    assert ask(d, "0C")[9] == 0x41


def test_restart_ff00_clears_the_log_and_log_holds_64():
    d = dev()
    for _ in range(40):
        ask(d, "03 0000 0001")
    log = ask(d, "0C")
    assert len(log) == 8 + 64 and log[1] == 70
    assert ask(d, "08 0001 FF00") == H("08 0001 FF00")
    log = ask(d, "0C")
    assert list(log[8:]) == [0x80, 0x40, 0x00]


def test_ascii_delimiter_changes_for_what_follows():
    d = dev()
    framer = make_framer("ascii", responses=False)
    framer.feed(b":010800033E00B6\r\n")
    reply = d.answer_frame(framer.next_event(), framer)
    assert reply == b":010800033E00B6\r\n"  # its own echo still ends in LF
    assert framer.delimiter == 0x3E
    framer.feed(b":010300000001FB\r>")
    assert d.answer_frame(framer.next_event(), framer).endswith(b"\r>")


def test_modbus_plus_and_overrun_subfunctions():
    d = dev()
    reply = ask(d, "08 0015 0003")
    assert reply[:6] == H("08 0015 0003 6C") and len(reply) == 6 + 108
    assert ask(d, "08 0015 0004") == H("08 0015 0004")
    assert ask(d, "08 0014 0000") == H("08 0014 0000")
    assert ask(d, "08 0013 0000") == H("08 0013 0000")


# --- FC43/14 ------------------------------------------------------------------------------


def test_device_identification_levels():
    d = dev()
    basic = ask(d, "2B 0E 01 00")
    assert basic[:7] == H("2B 0E 01 82 00 00 03")
    regular = ask(d, "2B 0E 02 00")
    assert regular[6] == 7
    one = ask(d, "2B 0E 04 04")
    assert one == H("2B 0E 04 82 00 00 01 04 0C") + b"mbtool serve"
    # an object id outside the category restarts the stream at 0
    assert ask(d, "2B 0E 01 05")[7] == 0x00


def test_device_identification_splits_with_more_follows():
    d = dev()
    for object_id in range(0x80, 0x84):
        d.model.objects[object_id] = bytes([object_id]) * 100
    first = ask(d, "2B 0E 03 00")
    assert first[3] == 0x83 and first[4] == 0xFF and len(first) <= 253
    next_id = first[5]
    second = ask(d, f"2B 0E 03 {next_id:02X}")
    assert second[7] == next_id
    ids = []
    reply = first
    while True:
        at = 7
        for _ in range(reply[6]):
            ids.append(reply[at])
            at += 2 + reply[at + 1]
        if reply[4] != 0xFF:
            break
        reply = ask(d, f"2B 0E 03 {reply[5]:02X}")
    assert ids == [0, 1, 2, 3, 4, 5, 6, 0x80, 0x81, 0x82, 0x83]


# --- broadcast, several units, faults -------------------------------------------------------


def test_broadcast_reaches_every_unit_and_is_not_answered():
    d = dev(units=(1, 2, 3))
    ask(d, "06 0000 0007", unit=2)  # unit 2 exists already, 3 not yet
    assert ask(d, "06 0005 4242", unit=0) is None
    assert ask(d, "10 0006 0001 02 0001", unit=0) is None
    assert ask(d, "03 0000 0001", unit=0) is None  # a read broadcast is ignored
    for unit in (1, 2, 3):
        assert ask(d, "03 0005 0002", unit=unit) == H("03 04 4242 0001")
    assert ask(d, "03 0000 0001", unit=2) == H("03 02 0007")
    assert ask(d, "03 0000 0001", unit=3) == H("03 02 0000")  # units keep their own tables
    assert ask(d, "03 0000 0001", unit=4) is None  # not served: silent, like a slave on a bus
    # FC21 is a write too: file 4, records 7-8 reach every unit, unanswered
    assert ask(d, "15 0B 06 0004 0007 0002 06AF 04BE", unit=0) is None
    for unit in (1, 2, 3):
        assert ask(d, "14 07 06 0004 0007 0002", unit=unit) == H("14 06 05 06 06AF 04BE")


# --- what a master or a data file can make the device hold (issue 29 item 1) ----------------


def write_file(number: int, record: int = 0, value: int = 7) -> str:
    return f"15 09 06 {number:04X} {record:04X} 0001 {value:04X}"


def allocated(work) -> int:
    """Bytes ``work()`` leaves allocated (tracemalloc sees every bytearray and array)."""
    import gc
    import tracemalloc

    gc.collect()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        kept = work()
        after = tracemalloc.get_traced_memory()[0]
    finally:
        tracemalloc.stop()
    del kept
    return after - before


def test_a_unit_holds_at_most_max_files_and_another_file_is_exception_02():
    d = dev()
    for number in range(1, MAX_FILES + 1):
        assert ask(d, write_file(number * 1000)) == H(write_file(number * 1000).replace(" ", ""))
    assert ask(d, write_file(0xFFFF)) == H("95 02")  # the spec's "illegal data address"
    assert ask(d, write_file(1000, record=9999, value=9)) == H(write_file(1000, 9999, 9).replace(" ", ""))
    # A write of several groups is all or nothing: one file too many and none is written.
    both = "15 12 06 07D0 0005 0001 0042 06 FFFE 0005 0001 0042"
    assert ask(d, both) == H("95 02")
    assert ask(d, "14 07 06 07D0 0005 0001") == H("14 04 03 06 0000")
    # Reading a file never written reads zeros and makes nothing.
    assert ask(d, "14 07 06 FFFD 0000 0001") == H("14 04 03 06 0000")
    assert len(d.model.files) == MAX_FILES


def test_writes_to_every_file_number_keep_memory_bounded():
    """65535 file numbers took a serve from 17.5 MB to 1.39 GB before there was a bound."""
    d = dev()
    ask(d, write_file(1))  # the first write loads the file-record codec: not the files' memory

    def hostile():
        for number in range(2, 2001):
            ask(d, write_file(number))
        return d

    grown = allocated(hostile)
    assert grown < (MAX_FILES + 4) * 20_000, grown


def test_units_share_their_tables_until_one_is_written():
    units = range(1, 248)
    d = dev(units=units)

    def read_every_unit():
        for unit in units:
            assert ask(d, "03 0000 0001", unit=unit) == H("03 02 0000")
        return d

    assert allocated(read_every_unit) < 2 * 1024 * 1024  # 247 stations, no tables of their own
    assert ask(d, "06 0000 0005", unit=7) == H("06 0000 0005")  # unit 7's own registers now
    assert ask(d, "03 0000 0001", unit=7) == H("03 02 0005")
    assert ask(d, "03 0000 0001", unit=8) == H("03 02 0000")
    assert ask(d, "03 0001 0001", unit=0) is None  # a read broadcast does nothing
    assert ask(d, "06 0001 0009", unit=0) is None  # a broadcast write reaches them all
    for unit in (7, 8, 200):
        assert ask(d, "03 0000 0002", unit=unit) == H("03 04 0005 0009" if unit == 7 else "03 04 0000 0009")
    assert ask(d, "05 0003 FF00", unit=8) == H("05 0003 FF00")
    assert ask(d, "01 0003 0001", unit=8) == H("01 01 01")
    assert ask(d, "01 0003 0001", unit=9) == H("01 01 00")


def test_injected_exception_and_busy():
    d = dev()
    d.faults = Faults({3: 2}, 0.0)
    assert ask(d, "03 0000 0001") == H("83 02")
    assert ask(d, "04 0000 0001") == H("04 02 03E8")
    d.faults = Faults(None, time.monotonic() + 60)
    assert ask(d, "04 0000 0001") == H("84 06")
    assert ask(d, "08 0011 0000") == H("88 06")  # busy answers everything, polls too
    d.faults = Faults()
    assert counter(d, 0x11) == 2  # busy count


# --- data files ---------------------------------------------------------------------------


TOML = """
exception_status = 0x21
[holding_registers]
0 = [10, 20, 30]
100 = 0x41AC
[coils]
3 = [1, 0, 1]
[files.4]
7 = [1, 2]
[identity]
slave_id = 0x42
run = false
extra = [1, 2, 3]
vendor_name = "ACME"
[identity.objects]
0x80 = "serial 1234"
[units.17.input_registers]
0 = 99
"""


def test_load_toml(tmp_path):
    path = tmp_path / "plant.toml"
    path.write_text(TOML)
    model, per_unit = load_data(str(path), frozenset({1, 17}))
    d = Device(model, frozenset({1, 17}), per_unit)
    assert ask(d, "03 0000 0003") == H("03 06 000A 0014 001E")
    assert ask(d, "03 0064 0001") == H("03 02 41AC")
    assert ask(d, "01 0003 0003") == H("01 01 05")
    assert ask(d, "07") == H("07 21")
    assert ask(d, "11") == H("11 05 42 00 010203")
    assert ask(d, "14 07 06 0004 0007 0002") == H("14 06 05 06 0001 0002")
    assert ask(d, "2B 0E 04 00") == H("2B 0E 04 83 00 00 01 00 04") + b"ACME"
    assert ask(d, "2B 0E 04 80")[9:] == b"serial 1234"
    assert ask(d, "04 0000 0001", unit=17) == H("04 02 0063")
    assert ask(d, "04 0000 0001", unit=1) == H("04 02 0000")


def test_load_json(tmp_path):
    path = tmp_path / "plant.json"
    path.write_text(json.dumps({"input_registers": {"5": [7, 8]}, "discrete_inputs": {"0": 1}}))
    model, _ = load_data(str(path), frozenset({1}))
    assert list(model.input_registers[5:7]) == [7, 8]
    assert model.discrete_inputs[0] == 1


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ('{"holding_registers": {"0": [70000]}}', "out of range"),
        ('{"holding_registers": {"65535": [1, 2]}}', "run past"),
        ('{"coils": {"0": 2}}', "out of range"),
        ('{"tables": {}}', "unknown section"),
        ('{"units": {"9": {}}}', "not among the units"),
        ("[1, 2]", "top level"),
        ("{not json", "not valid JSON"),
        ('{"sparse": 1}', "sparse must be true or false"),
        ('{"units": {"1": {"sparse": true}}}', "unknown section sparse"),  # the top level only
    ],
)
def test_bad_data_files(tmp_path, text, message):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(UsageError, match=message):
        load_data(str(path), frozenset({1}))


def test_a_data_file_holds_at_most_max_files_a_unit(tmp_path):
    path = tmp_path / "files.json"
    path.write_text(json.dumps({"files": {str(n): {"0": 1} for n in range(1, MAX_FILES + 2)}}))
    with pytest.raises(UsageError, match=f"files: {MAX_FILES + 1} files: a unit holds at most {MAX_FILES}"):
        load_data(str(path), frozenset({1}))
    # The file's common files count for each unit too.
    common = {str(n): {"0": 1} for n in range(1, MAX_FILES)}
    path.write_text(
        json.dumps({"files": common, "units": {"2": {"files": {"60000": {"0": 1}, "60001": {}}}}})
    )
    with pytest.raises(UsageError, match=r"units\.2: files: .* at most"):
        load_data(str(path), frozenset({1, 2}))


def test_a_data_file_for_every_unit_costs_what_each_unit_changes(tmp_path):
    """A 40 KB data file of files and units.N sections took more than 4 GB: each unit copied
    every table and every file, whether its section changed it or not."""
    path = tmp_path / "units.json"
    units = range(1, 248)
    path.write_text(
        json.dumps(
            {
                "sparse": True,
                "files": {str(n): {"0": [1, 2, 3]} for n in range(1, MAX_FILES + 1)},
                "holding_registers": {"0": [1, 2, 3]},
                "units": {str(unit): {"coils": {"0": 1}} for unit in units},
            }
        )
    )
    grown = allocated(lambda: load_data(str(path), frozenset(units)))
    # Each unit: its own coils (64 KB) and their sparse mask (64 KB); the rest is shared.
    assert grown < len(units) * 150 * 1024, grown
    model, per_unit = load_data(str(path), frozenset(units))
    d = Device(model, frozenset(units), per_unit)
    assert ask(d, "01 0000 0001", unit=5) == H("01 01 01")
    assert ask(d, "01 0001 0001", unit=5) == H("81 02")  # sparse: coil 1 is not listed
    assert ask(d, "03 0000 0003", unit=5) == H("03 06 0001 0002 0003")
    assert ask(d, "14 07 06 0010 0000 0003", unit=5) == H("14 08 07 06 0001 0002 0003")
    assert ask(d, "06 0000 0009", unit=5) == H("06 0000 0009")
    assert ask(d, "03 0000 0001", unit=6) == H("03 02 0001")  # unit 6 keeps its own


def test_missing_data_file(tmp_path):
    with pytest.raises(UsageError, match="cannot read"):
        load_data(str(tmp_path / "nope.toml"), frozenset({1}))


# --- sim:// stays cheap ---------------------------------------------------------------------


def test_sim_answers_every_function_code_in_process():
    from mbtool.device.sim import SimTransport

    sim = SimTransport("rtu")
    framer = make_framer("rtu")
    for pdu in ["07", "0B", "0C", "11", "0800000102", "2B0E0100", "1800C8", "16000400F20025"]:
        sim.write(framer.build(1, H(pdu)))
        framer.feed(sim.read(0.1))
        frame = framer.next_event()
        assert frame.pdu[0] == H(pdu)[0], pdu


def test_sim_device_startup_is_cheap():
    """Building the demo device costs well under a millisecond or two: bytearray/array tables,
    not 65536 Python objects per table (a one-shot -p sim:// command pays this every run)."""
    best = float("inf")
    for _ in range(5):
        t0 = time.perf_counter()
        d = Device(demo_model())
        d.handle(1, H("0300000001"))
        best = min(best, time.perf_counter() - t0)
    assert best < 0.005, best


def test_readme_example_data_file_loads(tmp_path):
    """The TOML example of docs/simulator.md's "Simulating a device" is a working data file."""
    page = (REPO_ROOT / "docs" / "simulator.md").read_text(encoding="utf-8")
    section = page.split("## Simulating a device", 1)[1].split("\n## ", 1)[0]
    example = section.split("```toml\n", 1)[1].split("```", 1)[0]
    path = tmp_path / "plant.toml"
    path.write_text(example)
    model, per_unit = load_data(str(path), frozenset({1, 17}))
    d = Device(model, frozenset({1, 17}), per_unit)
    assert ask(d, "03 0000 0003") == H("03 06 00E6 00E7 00E5")
    assert ask(d, "18 00C8") == H("18 0006 0002 1111 2222")
    assert ask(d, "03 0000 0001", unit=17) == H("03 02 0011")
    assert ask(d, "11")[2:4] == H("42 FF")


def test_character_overrun_is_counted():
    from mbtool.codec.errors import FrameError
    from mbtool.codec.framer import Rejected

    d = dev()
    d.rejected(Rejected(b"\xff" * 300, FrameError("garbage", b"")))
    assert counter(d, 0x12) == 1
    assert ask(d, "08 0014 0000") == H("08 0014 0000")  # clear overrun counter and flag
    assert counter(d, 0x12) == 0


def test_tcp_unit_ff_is_the_device_itself():
    d = dev(units=(3,))
    framer = make_framer("tcp", responses=False)
    framer.feed(H("0007 0000 0006 FF 03 0000 0001"))
    assert d.answer_frame(framer.next_event(), framer) == H("0007 0000 0005 FF 03 02 0000")
