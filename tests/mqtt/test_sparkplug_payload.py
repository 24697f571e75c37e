"""Sparkplug B's payloads sans-IO (mbtool/mqtt/sparkplug.py): each map type's datatype and
value field, read back by protoc's own --decode_raw (grpcio-tools), which knows no schema:
every field by its number as the published schema numbers it."""

from __future__ import annotations

import subprocess
import sys
from types import SimpleNamespace

import pytest

from mbtool.registermap.load import load_map

pytest.importorskip("grpc_tools", reason="grpcio-tools (the test extra) decodes the payloads")
sparkplug = pytest.importorskip(
    "mbtool.mqtt.sparkplug", reason="protobuf (payload = sparkplug_b) is not installed"
)

MAP = """\
[points.i16]
ref = 40001
type = "int16"
[points.u32]
ref = 40002
type = "uint32"
[points.i64]
ref = 40004
type = "int64"
[points.f32]
ref = 40008
type = "float32"
[points.f64]
ref = 40010
type = "float64"
[points.scaled]
ref = 40014
scale = 0.1
[points.text]
ref = 40015
type = "string"
count = 2
[points.bit]
ref = 40017
bit = 3
[points.nodata]
ref = 40018
"""


def decode_raw(data: bytes) -> str:
    done = subprocess.run(
        [sys.executable, "-m", "grpc_tools.protoc", "--decode_raw"],
        input=data,
        capture_output=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.decode()


def metrics(text: str) -> list[list[str]]:
    """The field lines of each metric (field 2) of a decoded Payload."""
    found, current = [], None
    for line in text.splitlines():
        if line == "2 {":
            current = []
        elif line == "}" and current is not None:
            found.append(current)
            current = None
        elif current is not None:
            current.append(line.strip())
    return found


def test_each_type_is_its_datatype_in_its_value_field_negatives_as_twos_complement(tmp_path):
    (tmp_path / "m.toml").write_text(MAP)
    points = load_map(tmp_path / "m.toml").select(())
    device = SimpleNamespace(name="d", reader=SimpleNamespace(points=points))
    settings = SimpleNamespace(group="g", edge_node="n", primary_host=None)
    node = sparkplug.EdgeNode(settings, [device])
    values = {"i16": -100, "u32": 4_000_000_000, "i64": -2, "f32": 21.5, "f64": 0.25, "scaled": 12.5,
              "text": "ab", "bit": True, "nodata": None}  # fmt: skip
    decoded = decode_raw(node.device_birth("d", values, 1.0))
    assert decoded.splitlines()[0] == "1: 1000" and "3: 0" in decoded.splitlines()  # timestamp ms, seq
    fields = {lines[0].removeprefix('1: "').removesuffix('"'): lines[1:] for lines in metrics(decoded)}
    expected = {
        "i16": ("4: 2", "10: 4294967196"),  # Int16, in int_value as 32-bit two's complement
        "u32": ("4: 7", "10: 4000000000"),
        "i64": ("4: 4", "11: 18446744073709551614"),  # Int64, long_value
        "f32": ("4: 9", "12: 0x41ac0000"),  # Float: 21.5's bits
        "f64": ("4: 10", "13: 0x3fd0000000000000"),  # Double: 0.25's
        "scaled": ("4: 10", "13: 0x4029000000000000"),  # a scaled uint16 is Double: 12.5
        "text": ("4: 12", '15: "ab"'),
        "bit": ("4: 11", "14: 1"),
        "nodata": ("4: 6", "7: 1"),  # UInt16, is_null
    }
    assert set(fields) == set(expected)
    aliases = set()
    for name, (datatype, value) in expected.items():
        assert datatype in fields[name] and value in fields[name], (name, fields[name])
        aliases.add(next(line for line in fields[name] if line.startswith("2: ")))
    assert len(aliases) == len(expected)  # an alias each


def test_seq_runs_0_to_255_and_round_again_from_each_nbirth():
    device = SimpleNamespace(name="d", reader=SimpleNamespace(points=[]))
    node = sparkplug.EdgeNode(SimpleNamespace(group="g", edge_node="n", primary_host=None), [device])
    node.node_birth(0, 0.0)
    seqs = [sparkplug.Payload.FromString(node.device_death(0.0)).seq for _ in range(300)]
    assert seqs[:3] == [1, 2, 3] and seqs[254:257] == [255, 0, 1]
    assert sparkplug.Payload.FromString(node.node_birth(1, 0.0)).seq == 0
