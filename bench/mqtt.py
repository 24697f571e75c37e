#!/usr/bin/env python3
"""``mbtool poll --mqtt``: what publishing a plant to a broker costs (issue 42's benchmark).

50 TCP devices of 20 registers each (one asyncio server listening on all 50 ports, as
bench/plant.py's), polled every second for ``--seconds`` (600 by default), twice: with
``-o json`` to /dev/null alone, and the same with ``--mqtt`` to Debian's mosquitto, started
here on a free loopback port (a paho-mqtt subscriber counts what reaches it).  Each run's
CPU a poll is measured in its steady state (from once every link is open to two seconds
before the end, /proc/PID/stat), and its RSS at both ends.

Targets: CPU a poll with MQTT at most 1.3 x without; RSS growth under 5 MB; every poll
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
from plant import ROOT, cpu_seconds, free_ports, mbtool, rss_kb, tcp_server

DEVICES, POINTS, INTERVAL = 50, 20, 1.0


def run(plant: Path, seconds: float, *extra: str) -> dict:
    """One poll run: its steady-state CPU a poll, RSS at both ends, its statistics."""
    proc = subprocess.Popen(
        mbtool("poll", str(plant), "-o", "json", "--duration", str(seconds), "--stats", "json", *extra),
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    settle = min(10, seconds / 3)
    time.sleep(settle)
    first = (time.monotonic(), cpu_seconds(proc.pid), rss_kb(proc.pid))
    time.sleep(max(1, seconds - settle - 2))
    last = (time.monotonic(), cpu_seconds(proc.pid), rss_kb(proc.pid))
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
    ports = free_ports(DEVICES + 1)
    broker_port, ports = ports[0], ports[1:]
    server = subprocess.Popen(
        [sys.executable, __file__, "--serve-tcp", ",".join(map(str, ports))],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        text=True,
    )
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
        received = [0]
        subscriber = paho.Client(CallbackAPIVersion.VERSION2)
        subscriber.on_connect = lambda c, u, f, r, p: c.subscribe("bench/#", qos=1)
        subscriber.on_message = lambda c, u, m: received.__setitem__(
            0, received[0] + (not m.topic.endswith("/status"))
        )
        try:
            if server.stdout.readline().strip() != "ready":
                sys.exit("bench: the TCP server did not start")
            time.sleep(0.5)
            subscriber.connect("127.0.0.1", broker_port)
            subscriber.loop_start()
            text = f"[poll]\ninterval = {INTERVAL}\n"
            for index, port in enumerate(ports):
                text += f'[links.l{index}]\ntarget = "tcp://127.0.0.1:{port}"\n'
                text += f'[devices.d{index}]\nlink = "l{index}"\nread = ["40001 {POINTS}"]\n'
            plant = folder / "plant.toml"
            plant.write_text(text)
            (folder / "published.toml").write_text(
                text + f'[mqtt]\ntopic = "bench/{{device}}"\nqos = {args.qos}\n'
            )
            alone = run(plant, args.seconds)
            published = run(
                folder / "published.toml", args.seconds, "--mqtt", f"mqtt://127.0.0.1:{broker_port}"
            )
            time.sleep(1)
        finally:
            subscriber.loop_stop()
            broker.terminate()
            server.terminate()
            broker.wait(timeout=10)
            server.wait(timeout=10)
    for name, result in (("-o json to /dev/null", alone), ("the same with --mqtt", published)):
        start, end = result["rss"]
        print(
            f"{name}: {result['polls']} polls of {DEVICES} devices x {POINTS} points in {args.seconds:g} s; "
            f"CPU {result['cpu_a_poll'] * 1e6:.0f} us a poll; RSS {start} -> {end} kB (+{(end - start) / 1024:.1f} MB)"
        )
    mqtt = published["stats"]["mqtt"]
    print(
        f"mqtt: {mqtt['published']} published, {mqtt['dropped']} dropped, {mqtt['spooled']} spooled; "
        f"the subscriber received {received[0]} device messages of {published['polls']} polls"
    )
    ratio = published["cpu_a_poll"] / alone["cpu_a_poll"]
    print(f"CPU a poll, with MQTT / without: {ratio:.2f} x (target <= 1.3); RSS growth target < 5 MB")


if __name__ == "__main__":
    main()
