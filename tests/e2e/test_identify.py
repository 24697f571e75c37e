"""The device library on the wire (issue 43): `mbtool serve` of every library twin, read
whole by `read -m NAME` and judged by `check -m NAME`; and `mbtool identify` against every
twin, the SunSpec twin and pymodbus's device: the right map named first, "unknown device"
with what was seen when nothing fits, and nothing but reads on the wire (serve's log of
every frame)."""

from __future__ import annotations

import json

import pytest
from helpers import REPO_ROOT, run_cli, serve

from mbtool.device.datafile import load_data
from mbtool.library import library_names, load_named_map, twin_path

# What identify may send: reads of the four tables, FC 17 and FC 43/14.
READS = {0x01, 0x02, 0x03, 0x04, 0x11, 0x2B}


def requests_of(log: str) -> list[int]:
    """The function code of every request serve received (its RX lines: an MBAP frame)."""
    codes = []
    for line in log.splitlines():
        parts = line.split()
        if len(parts) > 3 and parts[2] == "RX":
            codes.append(int(parts[3 + 7], 16))
    return codes


def identify(target: str, *args: str) -> dict:
    res = run_cli("identify", "-p", target, "-o", "json", "--timeout", "0.5", *args)
    assert res.returncode == 0, res
    return json.loads(res.stdout)


def held_values(name: str) -> dict:
    """Every point's value as the twin holds it, scaled: what a read of it must print."""
    register_map = load_named_map(name)
    model, _ = load_data(str(twin_path(name)), frozenset({1}))
    tables = {
        "coils": "coils",
        "discrete": "discrete_inputs",
        "input": "input_registers",
        "holding": "holding_registers",
    }
    out = {}
    for point in register_map.points.values():
        table = getattr(model, tables[point.table.name])
        out[point.name] = point.value_of(
            [table[point.address]]
            if point.table.bits
            else list(table[point.address : point.address + point.size])
        )
    return out


@pytest.mark.parametrize("name", library_names())
def test_every_twin_reads_through_its_map_and_is_identified_by_reads_alone(name):
    with serve("--data", str(twin_path(name)), quiet=False) as server:
        read = run_cli("read", "-m", name, "-o", "json", "-p", server.target)
        numbers = [p.name for p in load_named_map(name).points.values() if p.type not in ("hex", "string")]
        checked = run_cli("check", "-m", name, *numbers, "-p", server.target)  # check judges numbers
        found = identify(server.target)
        log = server.log()
    assert read.returncode == 0, read
    points = json.loads(read.stdout)["points"]
    expected = held_values(name)
    assert {p["name"]: p["value"] for p in points} == {
        key: float(value) if hasattr(value, "as_tuple") else value for key, value in expected.items()
    }
    assert checked.returncode == 0 and checked.stdout.startswith("MODBUS OK"), checked
    assert found["map"] == name, found["candidates"]
    assert found["identified"] and found["candidates"][0]["complete"]
    assert found["candidates"][0]["evidence"][0].startswith("signature: ")
    codes = requests_of(log)
    assert codes and set(codes) <= READS, sorted(set(codes) - READS)


def test_identify_names_a_sunspec_device():
    with serve("--data", str(REPO_ROOT / "examples" / "sunspec-twin.toml")) as server:
        found = identify(server.target)
    assert found["identified"] and found["map"] is None
    assert found["sunspec"]["ref"] == "440001" and found["sunspec"]["manufacturer"] == "mbtool"


def test_a_device_that_fits_no_map_is_an_unknown_device_with_what_was_seen(tcp_device):
    res = run_cli("identify", "-p", tcp_device.target, "--timeout", "0.5")
    assert res.returncode == 0, res
    assert res.lines[0] == "unit 1: unknown device"
    seen = [line.strip() for line in res.lines if line.strip().startswith("seen: ")]
    assert [line.split(":")[1].strip() for line in seen] == ["FC 43/14", "FC 17", "SunSpec"]
    found = identify(tcp_device.target)
    assert not found["identified"] and found["map"] is None
    assert not any(candidate["complete"] for candidate in found["candidates"])


def test_of_two_eastron_meters_the_right_one_ranks_first():
    """The SDM72 and the SDM630 share the vendor and most registers: the SDM630's import
    kvarh register (30077) tells them apart, both ways."""
    with serve("--data", str(twin_path("sdm72"))) as server:
        found = identify(server.target)
    names = [c["map"] for c in found["candidates"]]
    assert names[0] == "sdm72" and "sdm630" in names[1:]
    sdm630 = next(c for c in found["candidates"] if c["map"] == "sdm630")
    assert (
        not sdm630["complete"]
        and "not: 30077 answers: exception 02 Illegal Data Address" in sdm630["evidence"]
    )


def test_a_silent_unit_is_no_response_within_the_budget(silent_server):
    res = run_cli(
        "identify",
        "-p",
        silent_server.socket_target.replace("socket", "tcp"),
        "--timeout",
        "0.1",
        "--budget",
        "1",
    )
    assert res.returncode == 3, res
    assert "no response from unit 1" in res.stderr
    assert res.elapsed < 5
