"""The reliability campaigns' judges (scripts/campaigns/, issue 29): each must tell a broken
output from a whole one, or a campaign run after a fix would report nothing found for the
wrong reason.  The campaigns themselves are too slow for the suite and are run by hand."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "scripts" / "campaigns"))

import dump_kills  # noqa: E402
import exporter_fuzz  # noqa: E402
import hostile_names  # noqa: E402
import signals_and_streams  # noqa: E402
import textfile_kills  # noqa: E402

pytestmark = pytest.mark.timeout(20)


def case_of(points: list[dict], measurement: str | None = None, profile: str | None = None):
    case = hostile_names.Case.__new__(hostile_names.Case)
    case.points, case.measurement, case.profile = points, measurement, profile
    return case


def kinds(faults: list[tuple[str, str]]) -> set[str]:
    return {kind for kind, _ in faults}


def test_influx_judge_takes_a_line_escaped_by_the_reference_and_catches_a_split_one():
    case = case_of(
        [{"name": "a,b=c d\\", "ref": "40001"}, {"name": "flow", "ref": "40002"}], profile="east x"
    )
    whole = "modbus,device=east\\ x,unit=1 a\\,b\\=c\\ d\\\\=1i,flow=2i 1795661495366210454\n"
    assert hostile_names.judge_influx(case, whole) == []
    # A newline in a name written as it is: the line splits, the rest reads as another line.
    case = case_of([{"name": "flow\nmodbus_injected x=1i", "ref": "40001"}])
    split = "modbus,unit=1 flow\nmodbus_injected x=1i=1i 1795661495366210454\n"
    assert kinds(hostile_names.judge_influx(case, split)) & {"injected", "parse failure"}
    # '=' and ',' left unescaped make two fields of one name.
    case = case_of([{"name": "x=1i,y", "ref": "40001"}])
    assert kinds(hostile_names.judge_influx(case, "modbus,unit=1 x=1i,y=2i 1\n")) == {"injected"}


def test_prom_judge_takes_a_whole_exposition_and_catches_an_injected_metric():
    case = case_of([{"name": "flow", "ref": "40001", "description": 'Outlet "main"\nflow', "unit": "m3/h"}])
    whole = (
        '# HELP modbus_flow Outlet "main"\\nflow (m3/h), 40001\n# TYPE modbus_flow gauge\n'
        'modbus_flow{unit="1",ref="40001"} 1\n'
    )
    assert hostile_names.judge_prom(case, whole, status_families=0) == []
    injected = whole.replace("\\nflow", "\nmodbus_injected 1\n# HELP modbus_flow flow")
    assert "injected" in kinds(hostile_names.judge_prom(case, injected, status_families=0))
    assert "mangled" in kinds(hostile_names.judge_prom(case, whole.replace("Outlet", "Inlet"), 0))


def test_textfile_reader_calls_a_truncated_file_partial():
    _, refs = textfile_kills.make_map(3)
    assert refs == {"40001", "40002", "40003"}
    reader = textfile_kills.Reader(Path("unused"), refs, report=None)
    whole = "".join(
        f'# HELP modbus_p{i} p, {ref}\n# TYPE modbus_p{i} gauge\nmodbus_p{i}{{unit="1",ref="{ref}"}} {i}\n'
        for i, ref in enumerate(["40001", "40002", "40003"])
    )
    assert reader.judge(whole) == ""
    assert reader.judge(whole[: whole.index("modbus_p2{")]) != ""  # the last sample cut off
    assert reader.judge(whole[:-8]) != ""  # cut inside a sample


def test_dump_state_tells_a_kept_previous_dump_from_a_new_a_partial_and_an_empty_one(tmp_path):
    path = tmp_path / "pump.toml"
    previous = b"sparse = true\n[holding_registers]\n0 = [1, 2]\n# the previous dump\n"
    assert dump_kills.state_of(path, previous) == "missing"
    path.write_bytes(previous)
    assert dump_kills.state_of(path, previous) == "previous kept"
    path.write_bytes(b"sparse = true\ncomplete = false\n[holding_registers]\n0 = [1]\n")
    assert dump_kills.state_of(path, previous) == "new, complete = false"
    path.write_bytes(b"sparse = true\n[holding_registers]\n0 = [1, 2]\n")
    assert dump_kills.state_of(path, previous) == "new, complete"
    path.write_bytes(b"sparse = true\n[holding_registers]\n0 = [1, ")
    assert dump_kills.state_of(path, previous) == "partial"
    path.write_bytes(b"")
    assert dump_kills.state_of(path, previous) == "0 bytes"


def test_exporter_fuzz_reads_answers_whole_and_catches_a_cut_or_an_extra_one():
    ok = b"HTTP/1.1 200 OK\r\nContent-Length: 3\r\n\r\nabc"
    assert [s for s, _, _ in exporter_fuzz.Exchange.of(ok + ok, [b"GET", b"GET"]).answers] == [200, 200]
    assert exporter_fuzz.Exchange.of(ok[:-1], [b"GET"]).error  # the body cut short
    assert exporter_fuzz.Exchange.of(ok[:20], [b"GET"]).error  # the head cut short
    assert exporter_fuzz.Exchange.of(b"garbage\r\n\r\n", [b"GET"]).error
    # A HEAD's answer has no body: what follows it is the next answer.
    head = b"HTTP/1.1 200 OK\r\nContent-Length: 3\r\n\r\n"
    assert len(exporter_fuzz.Exchange.of(head + ok, [b"HEAD", b"GET"]).answers) == 2
    # The deadline the exporter reads from the header, clamped as it clamps it.
    assert exporter_fuzz.effective_timeout("9.3e9") == 300.0
    assert exporter_fuzz.effective_timeout("nan") == exporter_fuzz.effective_timeout(None) == 10.0
    assert exporter_fuzz.effective_timeout("0.5") == 0.5


def test_signals_judge_calls_a_cut_line_or_a_human_line_on_stdout_a_fault():
    judge = signals_and_streams.judge_output
    assert judge("json", '{"a": 1}\n{"b": 2}\n') == ""
    assert judge("json", '{"a": 1}\n{"b": ') != ""  # cut mid-line
    assert judge("json", '{"a": 1}\nmbtool: 1 of 2 devices answered\n') != ""  # stderr's line in stdout
    assert judge("csv", "time,device,name\n1,a,b\n") == ""
    assert judge("csv", "time,device,name\n1,a\n") != ""  # a row cut short
    assert judge("influx", "modbus,unit=1 a=1i 1\n") == ""
    assert judge("influx", "modbus,unit=1 a=\n") != ""
    whole = '# HELP modbus_up up\n# TYPE modbus_up gauge\nmodbus_up{device="a"} 1\n'
    assert judge("prom", whole) == ""
    assert judge("prom", whole + 'modbus_up{device="b\n') != ""
