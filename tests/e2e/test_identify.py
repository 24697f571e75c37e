"""The device library on the wire (issue 43): `mbtool serve` of every library twin, read
whole by `read -m NAME` and judged by `check -m NAME`; and `mbtool identify` against every
twin, the SunSpec twin and pymodbus's device: the right map named first, "unknown device"
with what was seen when nothing fits, and nothing but reads on the wire (serve's log of
every frame)."""

from __future__ import annotations

import json
import re
import socket
import threading
import tomllib

import pytest
from helpers.ptys import PTY_SERIAL_OPTS, PtyPair
from helpers.run import REPO_ROOT, run_cli
from helpers.served import serve

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
def test_every_twin_reads_through_its_map_polls_and_is_identified_by_reads_alone(name, tmp_path):
    with serve("--data", str(twin_path(name)), quiet=False) as server:
        read = run_cli("read", "-m", name, "-o", "json", "-p", server.target)
        numbers = [p.name for p in load_named_map(name).points.values() if p.type not in ("hex", "string")]
        checked = run_cli("check", "-m", name, *numbers, "-p", server.target)  # check judges numbers
        plant = tmp_path / "plant.toml"  # a plant's map = "NAME", as an inventory names it
        plant.write_text(
            f'[links.l]\ntarget = "{server.target}"\n[devices.d]\nlink = "l"\nunit = 1\nmap = "{name}"\n'
        )
        polled = run_cli("poll", plant, "--once", "-o", "json")
        found = identify(server.target)
        log = server.log()
    assert read.returncode == 0, read
    points = json.loads(read.stdout)["points"]
    expected = {
        key: float(value) if hasattr(value, "as_tuple") else value for key, value in held_values(name).items()
    }
    assert {p["name"]: p["value"] for p in points} == expected
    assert polled.returncode == 0, polled
    (record,) = [json.loads(line) for line in polled.stdout.splitlines()]
    assert {p["name"]: p["value"] for p in record["points"]} == expected, record
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


# What each request identify may send is, as an RTU frame: unit, function, then its fixed
# length: the reads 8 bytes, FC 17 4, FC 43/14 7 (unit, 2B, 0E, read code, object id, CRC).
RTU_REQUEST_SIZES = {0x01: 8, 0x02: 8, 0x03: 8, 0x04: 8, 0x11: 4, 0x2B: 7}


def rtu_functions(sent: bytes) -> list[int]:
    """The function code of each request in the bytes mbtool sent; a function that is not
    a read fails the test at once (its length is unknown: the walk cannot go on)."""
    codes, at = [], 0
    while at < len(sent):
        code = sent[at + 1]
        assert code in RTU_REQUEST_SIZES, f"function {code:#04x} on the wire: {sent[at : at + 12].hex(' ')}"
        codes.append(code)
        at += RTU_REQUEST_SIZES[code]
    return codes


def bus_of_twins(folder, names: list[str]):
    """A serve --data file answering as each twin at its own unit: units 1, 2, ..."""
    sections = ["sparse = true"]
    for unit, name in enumerate(names, 1):
        text = twin_path(name).read_text().replace("sparse = true\n", "")
        sections.append(re.sub(r"^\[(\w+)\]$", rf"[units.{unit}.\1]", text, flags=re.M))
    path = folder / "bus.toml"
    path.write_text("\n".join(sections))
    return path


def test_all_units_on_a_serial_bus_writes_an_inventory_that_poll_reads_whole(tmp_path):
    names = ["sdm630", "em24", "abb-b23", "dtsu666"]
    pair = PtyPair()
    try:
        with serve(
            "--data",
            str(bus_of_twins(tmp_path, names)),
            "-u",
            "1-4",
            *PTY_SERIAL_OPTS,
            target=pair.device_path,
        ):
            plant = tmp_path / "plant.toml"
            res = run_cli(
                "identify", "-p", pair.mbtool_path, *PTY_SERIAL_OPTS, "-t", "0.3",
                "--all-units", "--units", "1-5", "--inventory", plant,
            )  # fmt: skip
            assert res.returncode == 0, res
            assert [line for line in res.lines if line.startswith("unit ")] == [
                "unit 1: Eastron SDM630-Modbus V2, map sdm630",
                "unit 2: Carlo Gavazzi EM24-DIN, map em24",
                "unit 3: ABB B23 / B24, map abb-b23",
                "unit 4: Chint DTSU666, map dtsu666",
            ]
            functions = rtu_functions(pair.sent_by_mbtool(settle=0.05))
            assert set(functions) <= READS and 0x03 in functions
            inventory = tomllib.loads(plant.read_text())
            assert {name: device["map"] for name, device in inventory["devices"].items()} == {
                f"{name}-{unit}": name for unit, name in enumerate(names, 1)
            }
            assert inventory["links"]["bus"]["parity"] == "N"
            polled = run_cli("poll", plant, "--once", "-o", "json")
        assert polled.returncode == 0, polled
        polls = {poll["device"]: poll for poll in map(json.loads, polled.lines)}
        for unit, name in enumerate(names, 1):
            poll = polls[f"{name}-{unit}"]
            assert not poll.get("failed") and [p["name"] for p in poll["points"]] == list(
                load_named_map(name).points
            )
    finally:
        pair.close()


def test_the_inventory_line_counts_one_device_in_the_singular(tmp_path):
    """A new user's walk of docs/maps-library.md: one meter found said `1 devices`."""
    plant = tmp_path / "plant.toml"
    with serve("--data", str(twin_path("sdm630"))) as server:
        args = ("-t", "0.2", "--all-units", "--units", "1-2", "--inventory", plant)
        res = run_cli("identify", "-p", server.target, *args)
    assert res.returncode == 0, res
    assert f"mbtool: wrote {plant}: 1 device, 0 not identified" in res.stderr.splitlines(), res


def test_a_device_that_names_itself_in_fc43_ranks_first_with_that_evidence(tmp_path):
    """A B23 that answers FC 43/14 with its vendor and product code: that is the first
    evidence, before the signature's."""
    twin = tmp_path / "b23.toml"
    twin.write_text(
        twin_path("abb-b23")
        .read_text()
        .replace("refused = [17, 43]", 'vendor_name = "ABB"\nproduct_code = "B23 312-100"\nrevision = "1.0"')
    )
    with serve("--data", str(twin)) as server:
        found = identify(server.target)
    best = found["candidates"][0]
    assert found["map"] == "abb-b23" and best["complete"]
    assert best["evidence"][0] == 'FC 43/14 VendorName "ABB", ProductCode "B23 312-100"'
    assert found["seen"]["FC 43/14"].startswith('VendorName "ABB", ProductCode "B23 312-100"')


def test_an_inventory_that_cannot_be_written_is_one_line_and_exit_7(tmp_path):
    # Found by mypy (issue 41 point 7): OutputFailed was raised with one argument of its two,
    # so a folder that is not there ended in a TypeError's traceback.
    plant = tmp_path / "no-such-folder" / "plant.toml"
    with serve("--data", str(twin_path("sdm72"))) as server:
        res = run_cli(
            "identify", "-p", server.target, "-t", "0.3", "--all-units", "--units", "1", "--inventory", plant
        )
    assert res.returncode == 7, res
    assert res.stderr.splitlines()[-1] == f"mbtool: cannot write to {plant}: No such file or directory", res
    assert "Traceback" not in res.stderr


def test_a_walk_whose_link_is_lost_and_refused_ends_in_words_not_an_internal_error():
    # Found by mypy (issue 41 point 7): the walk's quiet progress took no step count, so a
    # link lost mid-walk that could not be opened again ended in a TypeError.
    listener = socket.create_server(("127.0.0.1", 0))
    port = listener.getsockname()[1]

    def hang_up_once():
        with listener:
            conn, _ = listener.accept()
        with conn:  # the listener is closed: the walk's reopen is refused
            conn.settimeout(5)
            conn.recv(260)  # the first probe, then the hang-up

    peer = threading.Thread(target=hang_up_once, daemon=True)
    peer.start()
    res = run_cli("identify", "-p", f"tcp://127.0.0.1:{port}", "-t", "0.3", "--all-units", "--units", "1-3")
    peer.join(5)
    assert res.returncode == 3, res
    assert res.stderr == f"mbtool: no unit of 1-3 answered on tcp://127.0.0.1:{port}\n", res
