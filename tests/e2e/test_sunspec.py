"""``mbtool sunspec`` against the SunSpec twin and the quirks of real devices, each served by
``mbtool serve --data``; pysunspec2's own client (the SunSpec Alliance's) is the
independent reader whose every point mbtool must agree with (issue 34).  The definitions
themselves are tests/sunspec/test_models.py's.
"""

from __future__ import annotations

import json
import re
import resource
import signal
import subprocess
import sys

import pytest
from helpers.checks import assert_one_error_line, wait_until
from helpers.ptys import PtyPair
from helpers.run import REPO_ROOT, mbtool_env, run_cli, signals_as_from_a_shell, start_mbtool
from helpers.served import serve

from mbtool.errors import ExitCode
from mbtool.registermap.load import load_map
from mbtool.sunspec.discover import MAX_MODELS, MAX_REGISTERS_READ
from mbtool.sunspec.models import definition

TWIN = REPO_ROOT / "examples" / "sunspec-twin.toml"
QUIRKS = REPO_ROOT / "tests" / "data" / "sunspec"
TWIN_MODELS = [1, 103, 120, 121, 122, 123, 160, 203]


def sunspec(target: str, *args: str):
    res = run_cli("sunspec", "-p", target, "-o", "json", *args)
    assert "Traceback" not in res.stderr, res
    return res


def tree_of(res) -> dict:
    assert res.returncode == 0, res
    return json.loads(res.stdout)


def warnings_of(res) -> list[str]:
    return [line.removeprefix("mbtool: warning: ") for line in res.stderr.splitlines() if "warning" in line]


# --- the twin: every point agrees with pysunspec2's client ----------------------------------------


def _pysunspec2_tcp(server):
    from sunspec2.modbus.client import SunSpecModbusClientDeviceTCP

    device = SunSpecModbusClientDeviceTCP(slave_id=1, ipaddr=server.host, ipport=server.port, timeout=5)
    try:
        device.scan()
        return _models_of(device)
    finally:
        device.close()


def _models_of(device) -> list[dict]:
    out = []
    for model in device.model_list:
        assert not model.error_info, model.error_info
        out.append(
            {"id": model.model_id, "address": model.model_addr, "length": model.model_len}
            | model.get_dict(computed=True)
        )
    return out


def _agree(theirs: list[dict], tree: dict) -> int:
    """Every point pysunspec2 read agrees with mbtool's tree: the value with its scale factor
    applied, None for not implemented alike; an enum's symbol stands for its number.  The
    count of points compared."""
    assert [(m["id"], m["address"], m["length"]) for m in theirs] == [
        (m["id"], m["address"], m["length"]) for m in tree["models"]
    ]
    return sum(
        _agree_group(model, ours, definition(model["id"]), top=True)
        for model, ours in zip(theirs, tree["models"], strict=True)
    )


def _agree_group(theirs: dict, ours: dict, group: dict, top: bool = False) -> int:
    compared = 0
    for point in group.get("points", ()):
        name = point["name"]
        if top and name in ("ID", "L") or point["type"] == "pad":  # the chain's, and no data
            continue
        mine = ours["points"][name]
        value = mine["value"]
        if isinstance(value, str) and point["type"].startswith("enum"):
            value = next(s["value"] for s in point["symbols"] if s["name"] == value)
        assert value == theirs[name], (ours.get("name"), name, value, theirs[name])
        assert type(value) is type(theirs[name]) or isinstance(theirs[name], float), name
        compared += 1
    for sub in group.get("groups", ()):
        mine, theirs_sub = ours.get("groups", {}).get(sub["name"]), theirs.get(sub["name"])
        if sub.get("count") is None:
            compared += _agree_group(theirs_sub, mine, sub)
            continue
        assert len(mine or []) == len(theirs_sub or []), sub["name"]
        for each_theirs, each_mine in zip(theirs_sub or [], mine or [], strict=True):
            compared += _agree_group(each_theirs, each_mine, sub)
    return compared


@pytest.fixture(scope="module")
def twin():
    with serve("--data", str(TWIN)) as server:
        yield server


def test_pysunspec2_and_mbtool_agree_on_every_point_of_the_twin_over_tcp(twin):
    theirs = _pysunspec2_tcp(twin)
    res = sunspec(twin.target)
    tree = tree_of(res)
    assert warnings_of(res) == []
    assert [m["id"] for m in tree["models"]] == TWIN_MODELS
    assert _agree(theirs, tree) == 247
    inverter = tree["models"][1]["points"]
    # Implemented and unimplemented alike, the scale factors applied.
    assert inverter["W"] | {"registers": None} == {
        "name": "inverter_three_phase.W",
        "value": 8600,
        "unit": "W",
        "type": "int16",
        "address": 40084,
        "registers": None,
        "implemented": True,
        "sf": 0,
    }
    assert (inverter["A"]["value"], inverter["PhVphA"]["value"], inverter["WH"]["value"]) == (
        12.5,
        230.1,
        15342700,
    )
    assert inverter["VAr"]["value"] is None and inverter["VAr"]["implemented"] is False
    assert inverter["St"]["value"] == "MPPT" and inverter["Evt1"]["bits"] == ["DC_DISCONNECT", "OVER_TEMP"]
    modules = tree["models"][6]["groups"]["module"]
    assert [(m["index"], m["points"]["IDStr"]["value"], m["points"]["DCA"]["value"]) for m in modules] == [
        (1, "PV1 east", 12.6),
        (2, "PV2 west", 12.5),
    ]


def test_pysunspec2_and_mbtool_agree_on_every_point_of_the_twin_over_rtu():
    """The twin on a serial line (a pseudo-terminal pair): pysunspec2's RTU client, then mbtool."""
    from sunspec2.modbus.client import SunSpecModbusClientDeviceRTU

    line = PtyPair()
    try:
        with serve("--data", str(TWIN), "-b", "9600", "--parity", "N", target=line.device_path):
            device = SunSpecModbusClientDeviceRTU(1, line.mbtool_path, baudrate=9600, parity="N", timeout=5)
            try:
                device.scan()
                theirs = _models_of(device)
            finally:
                device.close()
                from sunspec2.modbus.modbus import modbus_rtu_client_remove

                modbus_rtu_client_remove(line.mbtool_path)
            res = sunspec(line.mbtool_path, "-b", "9600", "--parity", "N", "--timeout", "3")
    finally:
        line.close()
    assert _agree(theirs, tree_of(res)) == 247


def test_groups_counted_by_points_one_inside_the_other_agree_with_pysunspec2():
    """Model 705: NCrv curves, each with NPt points, a group inside each curve."""
    with serve("--data", str(QUIRKS / "nested-groups.toml")) as device:
        theirs = _pysunspec2_tcp(device)
        res = sunspec(device.target)
        plain = run_cli("sunspec", "-p", device.target, "--model", "705")
    tree = tree_of(res)
    assert _agree(theirs, tree) == 6 + 11 + 2 * (9 + 2 * 2)
    curves = tree["models"][1]["groups"]["Crv"]
    assert [[p["points"]["V"]["value"] for p in curve["groups"]["Pt"]] for curve in curves] == [
        [92, 108],
        [90, 110],
    ]
    assert "  Crv 2: ActPt 2, DeptRef VAR_MAX_PCT, Pri not implemented" in plain.stdout
    assert "    Pt 2: V 110 VNomPct, Var -200 DeptRef" in plain.stdout


def test_the_plain_output_names_each_model_and_a_module_a_line(twin):
    res = run_cli("sunspec", "-p", twin.target)
    assert res.returncode == 0, res
    lines = res.stdout.splitlines()
    assert lines[0] == "SunSpec at 40000, unit 1: 8 models"
    assert "model 103 inverter_three_phase (Inverter (Three Phase)) at 40070, 50 registers" in lines
    assert "  VAr not implemented" in lines and "  W 8600 W" in lines and "  St MPPT" in lines
    assert "  Evt1 136 (DC_DISCONNECT, OVER_TEMP)" in lines
    assert not [line for line in lines if "_SF " in line]  # scale factors are applied, not shown
    modules = [line for line in lines if line.startswith("  module ")]
    assert len(modules) == 2 and modules[0].startswith(
        "  module 1: ID 1, IDStr PV1 east, DCA 12.6 A, DCV 350.2 V"
    )


def test_model_shows_one_model_and_an_absent_one_is_exit_2(twin):
    tree = tree_of(sunspec(twin.target, "--model", "160"))
    assert [m["id"] for m in tree["models"]] == [160]
    absent = sunspec(twin.target, "--model", "701")
    assert absent.returncode == 2
    assert "no model 701 in the chain (its models: 1, 103, 120, 121, 122, 123, 160, 203)" in absent.stderr


def test_csv_has_a_row_a_point_read_back_by_the_csv_module(twin):
    import csv
    import io

    res = run_cli("sunspec", "-p", twin.target, "-o", "csv", "--model", "103")
    rows = list(csv.DictReader(io.StringIO(res.stdout)))
    by_name = {row["name"]: row for row in rows}
    assert by_name["inverter_three_phase.Hz"]["value"] == "50.01"
    assert by_name["inverter_three_phase.VAr"] | {} == {
        "model": "103",
        "name": "inverter_three_phase.VAr",
        "value": "",
        "unit": "var",
        "address": "40090",
        "registers": "32768",
        "implemented": "0",
    }


# --- the quirks of real devices ---------------------------------------------------------------------


def test_a_chain_without_its_end_model_ends_where_the_device_refuses():
    with serve("--data", str(QUIRKS / "no-end-model.toml")) as device:
        res = sunspec(device.target)
    assert [m["id"] for m in tree_of(res)["models"]] == [1, 103]
    assert warnings_of(res) == [
        "no end model: register 40122, after model 103, answers exception 02; the chain ends there"
    ]


def test_a_chain_ended_by_0x0000_alone_ends_there():
    with serve("--data", str(QUIRKS / "end-0000.toml")) as device:
        res = sunspec(device.target)
    tree = tree_of(res)
    assert [m["id"] for m in tree["models"]] == [1, 103]
    assert warnings_of(res) == [
        "the chain ends with 0x0000 at 40122, after model 103: the end model is 0xFFFF"
    ]
    assert tree["warnings"] == warnings_of(res)


def test_the_length_on_the_wire_wins_with_a_warning_naming_the_model():
    with serve("--data", str(QUIRKS / "model-lengths.toml")) as device:
        res = sunspec(device.target)
        with_map = run_cli("sunspec", "-p", device.target, "--map", "/dev/null/x.toml")
    tree = tree_of(res)
    common, longer, shorter = tree["models"]
    assert (common["length"], common["points"]["DA"]["value"], "Pad" in common["points"]) == (65, 1, False)
    assert longer["raw"] == {"address": 40121, "registers": [0x1234, 0x5678]}
    assert longer["points"]["W"]["value"] == 8600
    assert "EvtVnd3" not in shorter["points"] and shorter["points"]["Evt1"]["value"] == 136
    assert shorter["points"]["W"]["name"] == "inverter_three_phase_2.W"
    assert warnings_of(res) == [
        "model 103 at 40069 (inverter_three_phase): 52 registers on the wire, 50 in its definition; the length "
        "on the wire is used: the 2 registers past the definition are shown raw",
        "model 103 at 40123 (inverter_three_phase): 44 registers on the wire, 50 in its definition; the length "
        "on the wire is used: EvtVnd2, EvtVnd3, EvtVnd4 past its end left out",
    ]
    assert with_map.returncode == 7 and "cannot write to /dev/null/x.toml" in with_map.stderr


def test_a_repeating_group_that_does_not_fit_shows_what_fits_and_the_rest_raw():
    with serve("--data", str(QUIRKS / "group-count.toml")) as device:
        res = sunspec(device.target)
    mppt = tree_of(res)["models"][1]
    assert [m["points"]["ID"]["value"] for m in mppt["groups"]["module"]] == [1, 2]
    assert mppt["raw"] == {"address": 40120, "registers": [0, 0, 0]}
    assert warnings_of(res) == [
        "model 160 (mppt) at 40070: 3 registers after 2 module groups (20 registers each) do not make another: "
        "shown raw"
    ]


def test_a_repeating_group_counted_by_a_point_that_does_not_fit_is_left_raw():
    """ha-sunspec #62: an E3DC's model 803 says one string (32 registers) and has 6 registers."""
    with serve("--data", str(QUIRKS / "battery-string.toml")) as device:
        res = sunspec(device.target)
    bank = tree_of(res)["models"][1]
    assert bank["points"]["NStr"]["value"] == 1 and "groups" not in bank
    assert bank["raw"] == {"address": 40098, "registers": [0] * 6}
    assert warnings_of(res) == [
        "model 803 (lithium_ion_bank) at 40070: 1 string group of 32 registers (its NStr) does not fit in its "
        "length: 0 shown, the registers left raw"
    ]


def test_a_model_sunspec_does_not_define_is_shown_raw_and_the_walk_goes_on():
    with serve("--data", str(QUIRKS / "unknown-model.toml")) as device:
        res = sunspec(device.target)
        plain = run_cli("sunspec", "-p", device.target)
    tree = tree_of(res)
    assert [m["id"] for m in tree["models"]] == [1, 64999, 103]
    assert tree["models"][1]["raw"] == {"address": 40072, "registers": [1, 2, 3, 4]}
    assert tree["models"][2]["points"]["W"]["value"] == 8600
    assert warnings_of(res) == [
        "model 64999 at 40070: SunSpec defines no model 64999: its 4 registers are shown raw"
    ]
    assert "model 64999 (SunSpec defines no such model) at 40070, 4 registers" in plain.stdout
    assert "  raw at 40072: 0001 0002 0003 0004" in plain.stdout


def test_without_u_a_device_that_answers_only_on_unit_126_is_found_there(twin):
    """SMA inverters answer SunSpec on unit 126: asked on unit 1, nothing answers."""
    with serve("--data", str(TWIN), "-u", "126") as sma:
        found = sunspec(sma.target, "--timeout", "0.5")
        told = sunspec(sma.target, "--timeout", "0.5", "-u", "1")
    tree = tree_of(found)
    assert tree["unit"] == 126 and len(tree["models"]) == 8
    assert warnings_of(found) == [
        "unit 1: no response; unit 126 (SMA's SunSpec unit) has it: -u 126 goes there at once"
    ]
    assert told.returncode == 3  # a unit given is the only one asked


def test_a_device_without_the_marker_says_what_each_base_holds_and_which_exit():
    with serve() as plain_device:  # the demo data: 0 at 40000 and 50000, 0 and 1 at 0
        res = sunspec(plain_device.target)
    assert res.returncode == 5
    assert (
        "no SunSpec marker (SunS) at holding register 40000, 0, 50000: 40000: holds 0x0000 0x0000; "
        "0: holds 0x0000 0x0001; 50000: holds 0x0000 0x0000" in res.stderr
    )


def test_base_looks_only_there_and_every_refusal_is_exit_4(twin):
    res = sunspec(twin.target, "--base", "50000")
    assert res.returncode == 4
    assert (
        "no SunSpec marker (SunS) at holding register 50000: 50000: exception 02 Illegal Data Address"
        in res.stderr
    )


def test_a_model_the_device_refuses_is_named_the_others_shown_and_exit_8(tmp_path):
    data = tmp_path / "refusing.toml"
    data.write_text(
        "sparse = true\n[holding_registers]\n"
        "40000 = [0x5375, 0x6E53, 1, 66]\n"  # common model 1 whose registers are not there
        "40070 = [64999, 2, 7, 8, 0xFFFF, 0]\n"
    )
    with serve("--data", str(data)) as device:
        res = sunspec(device.target)
        no_map = sunspec(device.target, "--map", tmp_path / "none.toml", "--model", "64999")
    assert no_map.returncode == 8 and not (tmp_path / "none.toml").exists()
    assert (
        f"no map written to {tmp_path / 'none.toml'}: no point of a model SunSpec defines was read"
        in no_map.stderr
    )
    assert json.loads(no_map.stdout)["models"][0]["raw"]["registers"] == [7, 8]
    assert res.returncode == 8
    models = json.loads(res.stdout)["models"]
    assert models[0]["error"].startswith("exception 02 Illegal Data Address")
    assert models[1]["raw"]["registers"] == [7, 8]
    assert re.search(r"model 1 \(common\) at 40002: exception 02 .*; 1 of 2 models read", res.stderr)


# --- the map it writes: read -m, check -m, poll and write -m, beside pysunspec2 ---------------------------


@pytest.fixture(scope="module")
def twin_map(twin, tmp_path_factory):
    path = tmp_path_factory.mktemp("sunspec") / "inverter.toml"
    res = run_cli("sunspec", "-p", twin.target, "--map", path, "-o", "json")
    assert res.returncode == 0, res
    assert f"wrote {path}: 247 points of 8 models" in res.stderr
    return path


def _pysunspec2_points(twin) -> dict[str, object]:
    """pysunspec2's values by mbtool's names for them (an enum by its symbol)."""
    out = {}
    for model in _pysunspec2_tcp(twin):
        key = definition(model["id"])["name"]
        _flatten(model, definition(model["id"]), key, out)
    return out


def _flatten(values: dict, group: dict, prefix: str, out: dict) -> None:
    for point in group.get("points", ()):
        if point["name"] in ("ID", "L") and prefix.count(".") == 0 or point["type"] == "pad":
            continue
        value = values[point["name"]]
        if value is not None and point["type"].startswith("enum"):
            value = next((s["name"] for s in point.get("symbols", ()) if s["value"] == value), value)
        out[f"{prefix}.{point['name']}"] = value
    for sub in group.get("groups", ()):
        repeats = values.get(sub["name"])
        if sub.get("count") is None:
            _flatten(repeats, sub, f"{prefix}.{sub['name']}", out)
            continue
        for index, each in enumerate(repeats or [], 1):
            _flatten(each, sub, f"{prefix}.{sub['name']}{index}", out)


def test_read_m_of_the_map_sunspec_wrote_reads_what_pysunspec2_reads(twin, twin_map):
    theirs = _pysunspec2_points(twin)
    res = run_cli("read", "-m", twin_map, "-p", twin.target, "-o", "json", "--hex")
    assert res.returncode == 0, res
    ours = {point["name"]: point["value"] for point in json.loads(res.stdout)["points"]}
    assert ours == theirs
    assert len(ours) == 247
    # 404 registers of eight models, gaps of 8 or fewer bridged: four reads.
    assert len([line for line in res.stderr.splitlines() if line.startswith("TX")]) == 4
    plain = run_cli(
        "read", "-m", twin_map, "inverter_three_phase.VAr", "inverter_three_phase.W", "-p", twin.target
    )
    assert plain.stdout == "inverter_three_phase.VAr invalid\ninverter_three_phase.W 8600 W\n"


def test_check_m_and_poll_with_the_map_give_pysunspec2s_values(twin, twin_map, tmp_path):
    theirs = _pysunspec2_points(twin)
    names = [
        "inverter_three_phase.W",
        "inverter_three_phase.Hz",
        "mppt.module2.DCV",
        "ac_meter_abcn.TotWhExp",
    ]
    check = run_cli("check", "-m", twin_map, *names, "-p", twin.target)
    assert check.returncode == 0, check
    perfdata = dict(item.replace("'", "").split("=") for item in check.stdout.split(" | ")[1].split())
    assert {name: float(re.match(r"-?[\d.]+", perfdata[name]).group()) for name in names} == {
        name: theirs[name] for name in names
    }
    status = run_cli(
        "check", "-m", twin_map, "inverter_three_phase.St", "-w", "4:4", "-c", "2:6", "-p", twin.target
    )
    assert status.returncode == 0 and status.stdout.startswith("MODBUS OK - inverter_three_phase.St=MPPT"), (
        status
    )

    plant = tmp_path / "plant.toml"
    plant.write_text(
        f'[links.roof]\ntarget = "{twin.target}"\n[devices.inverter]\nlink = "roof"\nmap = "{twin_map}"\n'
    )
    poll = run_cli("poll", plant, "--once", "-o", "json")
    assert poll.returncode == 0, poll
    (record,) = map(json.loads, poll.stdout.splitlines())
    ours = {point["name"]: point["value"] for point in record["points"]}
    assert ours == theirs


def test_a_scaled_control_written_through_the_map_is_read_back_by_pysunspec2(twin_map, tmp_path):
    """WMaxLimPct (model 123) in its scale factor's steps of 0.1 %: 55.5 % is 555 on the wire."""
    with serve("--data", str(TWIN)) as device:
        res = run_cli("write", "-m", twin_map, "controls.WMaxLimPct=55.5", "-p", device.target, "-o", "json")
        assert res.returncode == 0, res
        assert json.loads(res.stdout)["points"][0] | {} == {
            "name": "controls.WMaxLimPct",
            "value": 55.5,
            "unit": "% WMax",
            "ref": "440234",
            "registers": [555],
        }
        theirs = _pysunspec2_tcp(device)
        refused = run_cli("write", "-m", twin_map, "controls.WMaxLimPct=55.55", "-p", device.target)
    controls = next(model for model in theirs if model["id"] == 123)
    assert controls["WMaxLimPct"] == 55.5
    assert refused.returncode == 2
    assert "controls.WMaxLimPct: 55.55 is not a whole number of steps of 0.1" in refused.stderr


def test_a_map_write_that_fails_part_way_leaves_the_previous_map_whole(twin, tmp_path):
    """Issue 40 item 9: --map replaces FILE whole or not at all.  A file-size limit
    (RLIMIT_FSIZE) makes the write fail after a few kilobytes, as a full disk would: the map
    written before is still there, byte for byte, and loads; no temporary is left beside it."""
    path = tmp_path / "inverter.toml"
    res = run_cli("sunspec", "-p", twin.target, "--model", "1", "--map", path, "-o", "json")
    assert res.returncode == 0, res
    good = path.read_bytes()
    assert len(good) > 1024 and load_map(str(path)).points

    def limited() -> None:
        signals_as_from_a_shell()
        resource.setrlimit(resource.RLIMIT_FSIZE, (len(good) // 2, len(good) // 2))

    done = subprocess.run(
        [sys.executable, "-m", "mbtool", "sunspec", "-p", twin.target, "--map", str(path), "-o", "json"],
        env=mbtool_env(),
        preexec_fn=limited,
        capture_output=True,
        text=True,
        timeout=60,
        stdin=subprocess.DEVNULL,
    )
    res = type(res)(["sunspec"], done.returncode, done.stdout, done.stderr, 0.0)
    line = assert_one_error_line(res, ExitCode.OUTPUT)
    assert line.startswith(f"mbtool: cannot write to {path}: "), line
    assert path.read_bytes() == good
    assert load_map(str(path)).points
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


# --- a hostile chain: the walk is bounded, and an interrupted walk shows what it found (40.13) -----


def test_a_chain_of_zero_length_models_is_walked_to_the_bound_of_models_and_no_further():
    with serve("--data", str(QUIRKS / "zero-length-models.toml"), quiet=False) as device:
        res = sunspec(device.target)
        served = device.stop()[1]
    assert res.returncode == ExitCode.PARTIAL, res
    tree = json.loads(res.stdout)
    assert [m["id"] for m in tree["models"]] == [1] + [64998] * (MAX_MODELS - 1)
    where = 40002 + 68 + 2 * (MAX_MODELS - 1)
    said = f"the walk stopped after {MAX_MODELS} models, at register {where}: a chain holds no more"
    assert tree["stopped"] == said
    assert res.stderr.splitlines()[-1] == f"mbtool: {said}; the models found are shown"
    assert served.count("\n") < 2 * (MAX_MODELS + 10)  # the serve's log: a line a frame, no more


def test_a_model_past_the_register_budget_stops_the_walk_before_it_is_read(tmp_path):
    length = MAX_REGISTERS_READ  # with the common model's, past the budget
    data = tmp_path / "long-model.toml"
    data.write_text(
        (QUIRKS / "unknown-model.toml").read_text().split("# model 64999")[0]
        + f"40070 = [64999, {length}]\n40072 = {{ value = 1, count = {length} }}\n"
        + f"{40072 + length} = [0xFFFF, 0]\n"
    )
    with serve("--data", str(data), quiet=False) as device:
        res = sunspec(device.target)
        served = device.stop()[1]
    assert res.returncode == ExitCode.PARTIAL, res
    assert [m["id"] for m in json.loads(res.stdout)["models"]] == [1]
    assert res.stderr.splitlines()[-1] == (
        f"mbtool: the walk stopped at model 64999 at 40070: its {length} registers would take it past "
        f"{MAX_REGISTERS_READ} registers read; the models found are shown"
    )
    assert served.count("\n") < 20  # not the 80 reads the model would take


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_an_interrupted_walk_shows_the_models_it_found(sig):
    with serve("--data", str(QUIRKS / "zero-length-models.toml"), "--delay", "0.02", quiet=False) as device:
        proc = start_mbtool("sunspec", "-p", device.target)
        try:
            # The serve logs a line a frame: the walk is well past the common model.
            assert wait_until(lambda: device.log().count("\n") > 30, 20), device.log()
            proc.send_signal(sig)
            out, err = proc.communicate(timeout=10)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate(timeout=5)
    assert proc.returncode == ExitCode.INTERRUPTED, err
    assert "Traceback" not in err
    lines = out.splitlines()
    assert lines[0].startswith("SunSpec at 40000, unit 1: ") and "model 1 common (Common) at 40002" in out, (
        out
    )
    found = [line for line in lines if line.startswith("model ")]
    assert 2 <= len(found) < MAX_MODELS, out
    last = err.splitlines()[-1]
    assert last.startswith(
        f"mbtool: interrupted; the walk stopped after {len(found)} models, at register "
    ), err
