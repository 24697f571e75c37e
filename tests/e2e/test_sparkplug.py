"""poll publishing Sparkplug B (issue 42, ``payload = "sparkplug_b"``) to mosquitto, read by a
paho subscriber and decoded by an independent decoder: the Sparkplug B ``Payload`` as its
published schema numbers its fields, written here in protobuf's own language and compiled at
run time by protoc (grpcio-tools) into a temporary folder -- not mbtool's descriptor.

The device is pymodbus's (tests/peers/pymodbus_device.py): 40001.. hold 100, 101, ...
"""

from __future__ import annotations

import importlib.util
import signal
import subprocess
import sys
import time

import pytest
from helpers.mqtt import plant_on_broker
from peers.broker import needs_mosquitto

pytestmark = [pytest.mark.timeout(60), needs_mosquitto]

# The schema's Payload and Metric, their fields as Sparkplug B 3.0 numbers them.
SCHEMA = """
syntax = "proto2";
package org.eclipse.tahu.protobuf;
message Payload {
  message Metric {
    optional string name = 1;
    optional uint64 alias = 2;
    optional uint64 timestamp = 3;
    optional uint32 datatype = 4;
    optional bool is_historical = 5;
    optional bool is_transient = 6;
    optional bool is_null = 7;
    oneof value {
      uint32 int_value = 10;
      uint64 long_value = 11;
      float float_value = 12;
      double double_value = 13;
      bool boolean_value = 14;
      string string_value = 15;
      bytes bytes_value = 16;
    }
  }
  optional uint64 timestamp = 1;
  repeated Metric metrics = 2;
  optional uint64 seq = 3;
  optional string uuid = 4;
  optional bytes body = 5;
}
"""
UINT16, INT16, UINT64, DOUBLE, BOOLEAN, STRING = 6, 2, 8, 10, 11, 12

MAP = """\
[points.count]
ref = 40001
[points.level]
ref = 40002
scale = 0.1
unit = "m"
[points.delta]
ref = 40003
type = "int16"
[points.mode]
ref = 40006
enum = { 105 = "auto", 106 = "manual" }
[points.alarm]
ref = 40007
bit = 0
[points.setpoint]
ref = 40010
scale = 0.1
access = "rw"
"""


@pytest.fixture(scope="module")
def Payload(tmp_path_factory):
    pytest.importorskip("grpc_tools", reason="grpcio-tools (the test extra) compiles the decoder")
    folder = tmp_path_factory.mktemp("sparkplug")
    (folder / "sparkplug_b.proto").write_text(SCHEMA)
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "grpc_tools.protoc",
            f"-I{folder}",
            f"--python_out={folder}",
            "sparkplug_b.proto",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    spec = importlib.util.spec_from_file_location("sparkplug_b_pb2", folder / "sparkplug_b_pb2.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.Payload


def _value(metric):
    which = metric.WhichOneof("value")
    return None if which is None else getattr(metric, which)


def test_sparkplug_b_births_data_deaths_rebirth_and_a_dcmd_write(tmp_path, Payload):
    base = "spBv1.0/east"
    (tmp_path / "pump.toml").write_text(MAP)
    inventory = (
        '[poll]\ninterval = 0.2\noffline_after = 1\nmax_backoff = 0.4\n[links.l]\ntarget = "{target}"\n'
        'timeout = 0.3\n[devices.pump]\nlink = "l"\nmap = "pump.toml"\ntags = { site = "east" }\n'
        '[mqtt]\nurl = "{url}"\npayload = "sparkplug_b"\nwrites = true\non_change = true\n'
    )
    with plant_on_broker(tmp_path, inventory, "-o", "json", topics="spBv1.0/#") as plant:
        subscriber = plant.subscriber

        def decoded(kind, device=""):
            topic = f"{base}/{kind}/plant" + (f"/{device}" if device else "")
            return [Payload.FromString(payload) for payload in subscriber.on(topic)]

        assert subscriber.wait_for(lambda m: decoded("DBIRTH", "pump"), 10)
        (nbirth,) = decoded("NBIRTH")
        assert nbirth.seq == 0
        node = {m.name: (m.datatype, _value(m)) for m in nbirth.metrics}
        bdseq = node["bdSeq"][1]
        assert node == {"bdSeq": (UINT64, bdseq), "Node Control/Rebirth": (BOOLEAN, False)}
        (dbirth,) = decoded("DBIRTH", "pump")
        assert dbirth.seq == 1
        metrics = {m.name: (m.datatype, _value(m)) for m in dbirth.metrics}
        assert metrics == {
            "count": (UINT16, 100),
            "level": (DOUBLE, 10.1),
            "delta": (INT16, 102),
            "mode": (STRING, "auto"),
            "alarm": (BOOLEAN, False),
            "setpoint": (DOUBLE, 10.9),
        }
        alias = {m.name: m.alias for m in dbirth.metrics}
        assert len(set(alias.values())) == len(alias) and all(alias.values())

        # A DCMD to no point, or no payload, is refused and never sent (no DDATA follows).
        wrong = Payload(timestamp=int(time.time() * 1000))
        wrong.metrics.add(name="nope", datatype=DOUBLE, double_value=1.0)
        subscriber.client.publish(f"{base}/DCMD/plant/pump", wrong.SerializeToString(), qos=0)
        subscriber.client.publish(f"{base}/DCMD/plant/pump", b"\xff\xff\xff", qos=0)
        # DCMD: a write by the /set path; the value read back comes as DDATA, by alias alone.
        command = Payload(timestamp=int(time.time() * 1000))
        command.metrics.add(name="setpoint", datatype=DOUBLE, double_value=12.5)
        subscriber.client.publish(f"{base}/DCMD/plant/pump", command.SerializeToString(), qos=0)
        assert subscriber.wait_for(lambda m: decoded("DDATA", "pump"), 10)
        (ddata,) = decoded("DDATA", "pump")
        assert [(m.alias, m.name, _value(m)) for m in ddata.metrics] == [(alias["setpoint"], "", 12.5)]

        # NCMD Rebirth: NBIRTH (seq 0 again, the same bdSeq) and DBIRTH anew.
        rebirth = Payload(timestamp=int(time.time() * 1000))
        rebirth.metrics.add(name="Node Control/Rebirth", datatype=BOOLEAN, boolean_value=True)
        subscriber.client.publish(f"{base}/NCMD/plant", rebirth.SerializeToString(), qos=0)
        assert subscriber.wait_for(lambda m: len(decoded("DBIRTH", "pump")) == 2, 10)
        again = decoded("NBIRTH")[-1]
        assert again.seq == 0 and {m.name: _value(m) for m in again.metrics}["bdSeq"] == bdseq
        assert decoded("DBIRTH", "pump")[-1].seq == 1

        # The device dies: DDEATH; it comes back: DBIRTH.
        plant.kill_device()
        assert subscriber.wait_for(lambda m: decoded("DDEATH", "pump"), 5)
        plant.device_back()
        assert subscriber.wait_for(lambda m: len(decoded("DBIRTH", "pump")) == 3, 15)

        # seq: every message but NDEATH, one more each (mod 256), from each NBIRTH's 0.
        seqs = [
            Payload.FromString(payload).seq
            for topic, payload, _ in subscriber.messages
            if "/NDEATH/" not in topic and "CMD/" not in topic
        ]
        assert seqs[0] == 0 and all(b in (0, (a + 1) % 256) for a, b in zip(seqs, seqs[1:], strict=False)), (
            seqs
        )

        plant.poll.send_signal(signal.SIGKILL)  # no goodbye: the broker says the will, NDEATH
        plant.poll.wait(5)
        assert subscriber.wait_for(lambda m: decoded("NDEATH"), 10)
        (ndeath,) = decoded("NDEATH")
        assert [(m.name, m.datatype, _value(m)) for m in ndeath.metrics] == [("bdSeq", UINT64, bdseq)]
    err = plant.err
    assert "mbtool: mqtt: write pump nope: refused: pump reads no point nope" in err
    assert "mbtool: mqtt: write pump DCMD: refused: not a Sparkplug B payload" in err
    assert "mbtool: mqtt: write pump setpoint: written" in err


def test_with_a_primary_host_the_node_is_born_only_while_its_state_says_online(tmp_path, Payload):
    base = "spBv1.0/plant"
    inventory = (
        '[poll]\ninterval = 0.2\n[links.l]\ntarget = "{target}"\ntimeout = 0.3\n'
        '[devices.pm]\nlink = "l"\nread = ["40001 2"]\n'
        '[mqtt]\nurl = "{url}"\npayload = "sparkplug_b"\nprimary_host = "scada"\n'
    )
    state = "spBv1.0/STATE/scada"
    with plant_on_broker(tmp_path, inventory, "-o", "json", topics="spBv1.0/#") as plant:
        subscriber = plant.subscriber

        def births():
            return [Payload.FromString(p) for p in subscriber.on(f"{base}/NBIRTH/plant")]

        # No STATE yet: polled, but not born.
        assert not subscriber.wait_for(lambda m: births(), 1.5)
        subscriber.client.publish(state, b'{"online": true, "timestamp": 1}', qos=1, retain=True)
        assert subscriber.wait_for(lambda m: subscriber.on(f"{base}/DBIRTH/plant/pm"), 10)
        (first,) = births()
        bdseq = {m.name: _value(m) for m in first.metrics}["bdSeq"]
        # The host goes away: NDEATH, and no birth until it is back.
        subscriber.client.publish(state, b'{"online": false, "timestamp": 2}', qos=1, retain=True)
        assert subscriber.wait_for(lambda m: subscriber.on(f"{base}/NDEATH/plant"), 10)
        (ndeath,) = [Payload.FromString(p) for p in subscriber.on(f"{base}/NDEATH/plant")]
        assert {m.name: _value(m) for m in ndeath.metrics} == {"bdSeq": bdseq}
        assert not subscriber.wait_for(lambda m: len(births()) > 1, 1.5)
        subscriber.client.publish(state, b'{"online": true, "timestamp": 3}', qos=1, retain=True)
        assert subscriber.wait_for(lambda m: len(births()) == 2, 10)
        again = births()[-1]
        assert again.seq == 0 and {m.name: _value(m) for m in again.metrics}["bdSeq"] == (bdseq + 1) % 256
    err = plant.err
    assert "Traceback" not in err
    assert "primary host scada offline" in err
