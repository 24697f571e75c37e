#!/usr/bin/env python3
"""``mbtool poll --mqtt``: what publishing a plant to a broker costs (issue 42's benchmark).

A plant of 50 TCP devices of 20 registers each (one asyncio server listening on every port,
as bench/plant.py's, its registers counting up with every reply), polled every second for
``--seconds`` (600 by default), three times side by side, each run on devices of its own:
with ``-o json`` to /dev/null; the same with ``--mqtt`` to Debian's mosquitto as well
(started here on a free loopback port; a paho-mqtt subscriber counts what reaches it); and
``--mqtt`` with stdout's default (plain lines) to /dev/null, MQTT in the JSON lines' place.
The runs go at the same time so that the machine's other load weighs on them alike.  Each
run's CPU a poll is measured in its steady state (from once every link is open to two
seconds before the end, /proc/PID/stat), and its RSS at both ends.

Targets: CPU a poll with MQTT at most 1.3 x -o json's; RSS growth under 5 MB; every poll
published (the subscriber's count).

Run by hand:  python bench/mqtt.py [--seconds 600]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion
from plant import ROOT, cpu_seconds, free_ports, mbtool, rss_kb, tcp_inventory, tcp_server

DEVICES, POINTS, INTERVAL = 50, 20, 1.0


def start(plant: Path, seconds: float, *extra: str) -> subprocess.Popen:
    """One poll run of ``plant``, its records to /dev/null, its statistics (JSON) on stderr."""
    return subprocess.Popen(
        mbtool("poll", str(plant), "--duration", str(seconds), "--stats", "json", *extra),
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def sample(proc: subprocess.Popen) -> tuple[float, float, int]:
    return time.monotonic(), cpu_seconds(proc.pid), rss_kb(proc.pid)


def result(proc: subprocess.Popen, seconds: float, first: tuple, last: tuple) -> dict:
    """A run's CPU a poll in its steady state (between the samples ``first`` and ``last``),
    its RSS at both, and its statistics."""
    err = proc.stderr.read()
    proc.wait()
    if proc.returncode != 0 or not err.strip():
        sys.exit(f"bench: poll failed ({proc.returncode}): {err[-500:]}")
    stats = json.loads(err.strip().splitlines()[-2])
    polls = sum(device["polls"] for device in stats["devices"].values())
    steady_polls = polls * (last[0] - first[0]) / seconds  # the polls come evenly, a round a second
    return {
        "cpu_a_poll": (last[1] - first[1]) / steady_polls,
        "rss": (first[2], last[2]),
        "polls": polls,
        "stats": stats,
    }


def side_by_side(runs: dict[str, tuple], seconds: float) -> dict[str, dict]:
    """The runs at the same time, each on devices of its own: the machine's other load
    weighs on them alike, so their ratio holds where each one's figure alone moves with it."""
    procs = {name: start(plant, seconds, *extra) for name, (plant, extra) in runs.items()}
    settle = min(10, seconds / 3)
    time.sleep(settle)
    first = {name: sample(proc) for name, proc in procs.items()}
    time.sleep(max(1, seconds - settle - 2))
    last = {name: sample(proc) for name, proc in procs.items()}
    return {name: result(proc, seconds, first[name], last[name]) for name, proc in procs.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=600)
    parser.add_argument("--qos", type=int, choices=(0, 1), default=1)
    parser.add_argument("--serve-tcp", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.serve_tcp:
        ready = threading.Event()
        ports = [int(p) for p in args.serve_tcp.split(",")]
        threading.Thread(target=tcp_server, args=(ports, ready, POINTS), daemon=True).start()
        ready.wait(30)
        print("ready", flush=True)
        threading.Event().wait()
    broker_program = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    ports = free_ports(3 * DEVICES + 1)
    broker_port, ports = ports[0], ports[1:]
    server = subprocess.Popen(
        [sys.executable, __file__, "--serve-tcp", ",".join(map(str, ports))],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
    url = f"mqtt://127.0.0.1:{broker_port}"
    with tempfile.TemporaryDirectory(prefix="mbtool-mqtt-bench-") as where:
        folder = Path(where)
        (folder / "mosquitto.conf").write_text(
            f"listener {broker_port} 127.0.0.1\nallow_anonymous true\npersistence false\n"
        )
        broker = subprocess.Popen(
            [broker_program, "-c", str(folder / "mosquitto.conf")],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        received = {"beside": 0, "alone": 0}  # device messages, by the run that published them

        def count(client, userdata, message) -> None:
            if not message.topic.endswith("/status"):
                received[message.topic.split("/")[1]] += 1

        subscriber = paho.Client(CallbackAPIVersion.VERSION2)
        subscriber.on_connect = lambda c, u, f, r, p: c.subscribe("bench/#", qos=1)
        subscriber.on_message = count
        try:
            if server.stdout.readline().strip() != "ready":
                sys.exit("bench: the TCP server did not start")
            time.sleep(0.5)
            subscriber.connect("127.0.0.1", broker_port)
            subscriber.loop_start()
            plants = {}
            for index, name in enumerate(("json", "beside", "alone")):
                mqtt = f'[mqtt]\ntopic = "bench/{name}/{{device}}"\nqos = {args.qos}\n' if index else ""
                plants[name] = folder / f"{name}.toml"
                plants[name].write_text(
                    tcp_inventory(ports[index * DEVICES : (index + 1) * DEVICES], INTERVAL, POINTS) + mqtt
                )
            runs = side_by_side(
                {
                    "json": (plants["json"], ("-o", "json")),
                    "beside": (plants["beside"], ("-o", "json", "--mqtt", url)),
                    "alone": (plants["alone"], ("--mqtt", url)),
                },
                args.seconds,
            )
            time.sleep(1)
        finally:
            subscriber.loop_stop()
            broker.terminate()
            server.terminate()
            broker.wait(timeout=10)
            server.wait(timeout=10)
    names = {
        "json": "-o json to /dev/null",
        "beside": "the same with --mqtt (beside the JSON lines)",
        "alone": "--mqtt alone (stdout's default plain lines to /dev/null)",
    }
    for name, run in runs.items():
        begin, end = run["rss"]
        print(
            f"{names[name]}: {run['polls']} polls of {DEVICES} devices x {POINTS} points in {args.seconds:g} s; "
            f"CPU {run['cpu_a_poll'] * 1e6:.0f} us a poll; RSS {begin} -> {end} kB (+{(end - begin) / 1024:.1f} MB)"
        )
    for name in ("beside", "alone"):
        mqtt = runs[name]["stats"]["mqtt"]
        print(
            f"{name}: mqtt {mqtt['published']} published, {mqtt['dropped']} dropped, {mqtt['spooled']} spooled; "
            f"the subscriber received {received[name]} device messages of {runs[name]['polls']} polls"
        )
    reference = runs["json"]["cpu_a_poll"]
    print(
        f"CPU a poll / -o json's: with MQTT beside the JSON lines {runs['beside']['cpu_a_poll'] / reference:.2f} x, "
        f"MQTT in their place {runs['alone']['cpu_a_poll'] / reference:.2f} x (target <= 1.3); "
        "RSS growth target < 5 MB"
    )


if __name__ == "__main__":
    main()
