#!/usr/bin/env python3
"""``mbtool exporter``: a multi-target scrape beside ``read -m``, and inventory scrapes of 50
slow devices (issue 32's benchmarks).

Targets, each measured against its reference in the same run:

* **multi-target**: a scrape of /modbus reading a 100-point map (made here, with the data
  ``mbtool serve`` holds for it) costs at most 1.2 x ``mbtool read -m`` of the same map
  from the same server, each timed from the request to the whole answer.  That compares
  what a user pays for one reading either way: the exporter is a service, already running
  when Prometheus asks, while a one-shot read starts a process (bench/oneshot.py has that
  part alone).  So that the start-up does not hide what the scrape adds, the same read -m
  is also timed in this process (cli.main called again and again, its imports done): the
  map read and its Prometheus text without the start-up, beside the scrape's HTTP and
  prometheus_client's rendering;
* **inventory**: /metrics of a plant of 50 devices, each on a link of its own to a server
  that holds every reply 0.5 s (``serve --delay 0.5``), so polls are under way all the
  time: a scrape answers in under 5 ms, median and max over 100 scrapes, 0.1 s apart while
  the polls of several rounds are reported.  Beside each, the exporter's index page (a
  few bytes, nothing of the plant): what the machine and the HTTP server cost alone;
* **polling**: the plant's polls a second, 10, 1,000 and 3,000 devices on one sim:// link
  (every one due all along), their reports going to the exporter's PlantMetrics, beside
  the same plant whose reports go nowhere (poll's scheduler alone): at least 0.9 x at
  each size (issue 40.18: 459, 171, 58 against some 464);
* **slow connections**: /metrics with 500 connections held that never finish their
  request's head: a scrape still answers in under 50 ms, median and max over 20.

Scrapes go over one kept-alive HTTP connection, as Prometheus keeps its own.

Run by hand:  python bench/exporter.py [-n 50] [--scrapes 100] [--devices 50] [--delay 0.5]
"""

from __future__ import annotations

import argparse
import contextlib
import http.client
import io
import random
import re
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))


def mbtool(*args: str) -> list[str]:
    return [sys.executable, "-m", "mbtool", *map(str, args)]


def make_map(rng: random.Random) -> tuple[str, str]:
    """A 100-point map of a meter-like device and the data file serve holds for it: 40 holding
    registers (uint16, some scaled), 40 float32 input registers, 20 coils; read in three
    requests, as a meter's map is."""
    points = ["[device]", "max_gap = 4", ""]
    holding, inputs, coils = {}, {}, {}
    for n in range(40):
        address = 3 * n
        holding[address] = [rng.randrange(65536)]
        points += [f"[points.setting_{n}]", f"ref = {40001 + address}"]
        if n % 4 == 0:
            points += ["scale = 0.1", 'unit = "V"']
        points.append("")
    for n in range(40):
        address = 3 * n
        high, low = struct.unpack(">HH", struct.pack(">f", rng.uniform(0, 1000)))
        inputs[address] = [high, low]
        points += [f"[points.reading_{n}]", f"ref = {30001 + address}", 'type = "float32"', 'unit = "kW"', ""]
    for n in range(20):
        coils[n] = [rng.random() < 0.5]
        points += [f"[points.relay_{n}]", f'ref = "{n + 1:05d}"', ""]
    data = []
    for table, values in (("holding_registers", holding), ("input_registers", inputs), ("coils", coils)):
        data.append(f"[{table}]")
        data += [f"{address} = {str(value).lower()}" for address, value in values.items()]
        data.append("")
    return "\n".join(points), "\n".join(data)


@contextlib.contextmanager
def running(argv: list[str], starts: str):
    """A long-running mbtool; yields its first line."""
    proc = subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        line = proc.stdout.readline()
        if not line.startswith(starts):
            sys.exit(f"bench: {' '.join(argv[2:4])} did not start: {line!r}")
        yield line
    finally:
        proc.terminate()
        proc.wait(10)


class Scraper:
    """GETs over one kept-alive connection, each timed to the last byte of the answer."""

    def __init__(self, url: str) -> None:
        host, port = re.match(r"http://([^:]+):(\d+)", url).groups()
        self.connection = http.client.HTTPConnection(host, int(port), timeout=30)

    def get(self, path: str) -> tuple[float, bytes]:
        began = time.perf_counter()
        self.connection.request("GET", path, headers={"X-Prometheus-Scrape-Timeout-Seconds": "10"})
        response = self.connection.getresponse()
        body = response.read()
        took = time.perf_counter() - began
        if response.status != 200:
            sys.exit(f"bench: {path}: HTTP {response.status}: {body[:200]!r}")
        return took, body


def timed_process(argv: list[str]) -> float:
    began = time.perf_counter()
    done = subprocess.run(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    took = time.perf_counter() - began
    if done.returncode:
        sys.exit(f"bench: {' '.join(argv[2:4])} failed: {done.stderr.strip()}")
    return took


def timed_in_process(args: list[str]) -> float:
    """read -m through the CLI's own main, in this process: its imports already done."""
    from mbtool.cli import main

    out = io.StringIO()
    began = time.perf_counter()
    with contextlib.redirect_stdout(out):
        try:
            main(args)
        except SystemExit as end:
            if end.code:
                sys.exit(f"bench: read -m in process exited {end.code}")
    took = time.perf_counter() - began
    if "modbus_reading_0" not in out.getvalue():
        sys.exit("bench: read -m in process wrote no Prometheus text")
    return took


def polls_in(body: bytes) -> float:
    return sum(float(x) for x in re.findall(rb"^modbus_polls_total\{[^}]*\} (\S+)$", body, re.M))


def ms(seconds: float) -> str:
    return f"{seconds * 1000:7.2f} ms"


def bench_multi_target(args, folder: Path) -> None:
    map_text, data_text = make_map(random.Random(args.seed))
    maps = folder / "maps"
    maps.mkdir()
    (maps / "meter100.toml").write_text(map_text)
    (folder / "data.toml").write_text(data_text)
    with running(
        mbtool("serve", "-p", "tcp://127.0.0.1:0", "-q", "--data", folder / "data.toml"), "serving"
    ) as line:
        target = line.split()[1]
        exporter = mbtool("exporter", "--listen", "127.0.0.1:0", "--maps", maps, "--allow-target", target)
        with running(exporter, "exporting") as first:
            scraper = Scraper(re.search(r"http://\S+", first)[0])
            path = f"/modbus?target={target}&module=meter100&unit=1"
            read_m = ["read", "-m", str(maps / "meter100.toml"), "-p", target, "-o", "prom"]
            _, body = scraper.get(path)  # warm: the map loaded, the modules imported
            if body.count(b"\nmodbus_") < 100 or b'modbus_up{unit="1"} 1.0' not in body:
                sys.exit(f"bench: the scrape did not read the map: {body[:300]!r}")
            timed_process(mbtool(*read_m))
            timed_in_process(read_m)
            runs: dict[str, list[float]] = {"scrape": [], "read -m": [], "read -m in process": []}
            for _ in range(args.n):  # interleaved: the machine's load falls on each alike
                runs["scrape"].append(scraper.get(path)[0])
                runs["read -m"].append(timed_process(mbtool(*read_m)))
                runs["read -m in process"].append(timed_in_process(read_m))
    medians = {label: statistics.median(values) for label, values in runs.items()}
    print(f"multi-target: a 100-point map (3 requests) from mbtool serve over TCP, {args.n} runs each")
    for label, values in runs.items():
        print(f"  {label:20} median {ms(medians[label])}  min {ms(min(values))}")
    ratio = medians["scrape"] / medians["read -m"]
    print(
        f"  scrape / read -m            {ratio:.3f}  (target <= 1.2): {'met' if ratio <= 1.2 else 'NOT MET'}"
    )
    print(f"  scrape / read -m in process {medians['scrape'] / medians['read -m in process']:.3f}")


def bench_inventory(args, folder: Path) -> None:
    shutil_map = (ROOT / "examples" / "energy-meter.toml").read_text()
    (folder / "meter.toml").write_text(shutil_map)
    serve = mbtool(
        "serve", "-p", "tcp://127.0.0.1:0", "-q", "-u", f"1-{args.devices}", "--delay", args.delay,
        "--data", ROOT / "examples" / "energy-meter-data.toml", "--max-clients", args.devices + 10,
    )  # fmt: skip
    with running(serve, "serving") as line:
        target = line.split()[1]
        plant = ["[poll]", "interval = 1", ""]
        for n in range(1, args.devices + 1):
            plant += [f"[links.link{n}]", f'target = "{target}"', f"timeout = {float(args.delay) * 4}", ""]
            plant += [f"[devices.meter{n}]", f'link = "link{n}"', f"unit = {n}", 'map = "meter.toml"']
            plant += [f'tags = {{ site = "north", panel = "{n % 5}" }}', ""]
        (folder / "plant.toml").write_text("\n".join(plant))
        with running(
            mbtool("exporter", folder / "plant.toml", "--listen", "127.0.0.1:0"), "exporting"
        ) as first:
            scraper = Scraper(re.search(r"http://\S+", first)[0])
            end = time.monotonic() + 60
            while True:  # every device polled once: each has its values
                _, body = scraper.get("/metrics")
                if body.count(b"modbus_voltage_l1{") == args.devices:
                    break
                if time.monotonic() > end:
                    sys.exit("bench: the devices were not all polled within 60 s")
                time.sleep(0.2)
            before = polls_in(body)
            took, floor = [], []
            for _ in range(args.scrapes):  # 0.1 s apart: across several rounds of polls
                seconds, body = scraper.get("/metrics")
                took.append(seconds)
                floor.append(scraper.get("/")[0])
                time.sleep(0.1)
            polls = polls_in(body) - before
    samples = sum(1 for row in body.splitlines() if row and not row.startswith(b"#"))
    print(
        f"inventory: {args.devices} devices, a link each, every reply held {args.delay} s by the server; "
        f"/metrics {len(body)} bytes, {samples} samples; {polls:.0f} polls reported while it was scraped"
    )
    for label, values in (
        (f"{args.scrapes} scrapes of /metrics", took),
        ("the index page after each", floor),
    ):
        p95 = sorted(values)[int(0.95 * len(values)) - 1]
        print(f"  {label:28} median {ms(statistics.median(values))}  p95 {ms(p95)}  max {ms(max(values))}")
    verdict = "met" if max(took) < 0.005 else "NOT MET"
    print(f"  target: /metrics under 5 ms, median and max: {verdict}")


def polls_a_second(folder: Path, devices: int, exporting: bool, seconds: float) -> float:
    from mbtool.plant.inventory import load_inventory
    from mbtool.cli.plant_text import PlantMetrics
    from mbtool.cli.program import register_schemes
    from mbtool.plant.schedule import Plant

    register_schemes()
    path = folder / f"plant-{devices}.toml"
    path.write_text(
        '[poll]\ninterval = 0.001\n[links.a]\ntarget = "sim://"\n'
        + "".join(f'[devices.d{n}]\nlink = "a"\nread = ["40001 1"]\n' for n in range(devices))
    )
    plant = load_inventory(str(path))
    metrics = PlantMetrics() if exporting else None
    runner = Plant(plant.links, plant.devices, metrics.report if metrics else lambda item: None)
    if metrics is not None:
        metrics.watch(runner)
    began = time.monotonic()
    runner.run(seconds)
    return sum(state.polls for state in runner.devices.values()) / (time.monotonic() - began)


def bench_polling(args, folder: Path) -> None:
    print("polling: devices on one sim:// link, polls a second, the exporter's reports beside none")

    def rate(devices: int, exporting: bool) -> float:
        # Each run in a process of its own: what one run leaves for the collector would slow the next.
        argv = [sys.executable, __file__, "--one-plant", str(devices), "--seconds", str(args.seconds)]
        done = subprocess.run(
            argv + (["--exporting"] if exporting else []) + ["--folder", str(folder)],
            capture_output=True, text=True, check=True, timeout=120 + 2 * args.seconds,
        )  # fmt: skip
        return float(done.stdout)

    for devices in (10, 1000, 3000):
        alone = rate(devices, False)
        exporting = rate(devices, True)
        verdict = "met" if exporting >= 0.9 * alone else "NOT MET"
        print(
            f"  {devices:5} devices  exporter {exporting:6.0f}  alone {alone:6.0f}  ratio "
            f"{exporting / alone:.2f} (target >= 0.9): {verdict}"
        )


def bench_slow_connections(args, folder: Path) -> None:
    maps = folder / "maps"
    maps.mkdir()
    exporter = mbtool("exporter", "--listen", "127.0.0.1:0", "--maps", maps, "--allow-target", "tcp://x")
    with running(exporter, "exporting on ") as first:
        url = re.search(r"http://\S+", first)[0]
        host, port = url.removeprefix("http://").rsplit(":", 1)
        held = []
        try:
            for _ in range(500):
                sock = socket.create_connection((host, int(port)), timeout=5)
                sock.sendall(b"GET /metrics HTTP/1.1\r\nHost: x\r\nX-Slow: ")
                held.append(sock)
            scraper = Scraper(url)
            scraper.get("/metrics")  # the first imports prometheus_client
            took = [scraper.get("/metrics")[0] for _ in range(20)]
        finally:
            for sock in held:
                sock.close()
    verdict = "met" if max(took) < 0.05 else "NOT MET"
    print("slow connections: /metrics beside 500 connections that never finish their request's head")
    print(
        f"  20 scrapes  median {ms(statistics.median(took))}  max {ms(max(took))}  "
        f"target under 50 ms: {verdict}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("-n", type=int, default=50, help="runs of the scrape and of each read -m")
    parser.add_argument("--scrapes", type=int, default=100, help="inventory scrapes")
    parser.add_argument("--devices", type=int, default=50)
    parser.add_argument("--delay", default="0.5", help="seconds the server holds each reply (inventory)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=3.0, help="polling: seconds of each run")
    parser.add_argument("--only", choices=["multi-target", "inventory", "polling", "slow-connections"])
    parser.add_argument("--one-plant", type=int, help=argparse.SUPPRESS)  # polling's runs
    parser.add_argument("--exporting", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--folder", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.one_plant:
        print(polls_a_second(args.folder, args.one_plant, args.exporting, args.seconds))
        return
    subprocess.run([sys.executable, "-m", "compileall", "-q", str(ROOT / "mbtool")], check=True)
    with tempfile.TemporaryDirectory() as tmp:
        if args.only in (None, "multi-target"):
            (Path(tmp) / "multi").mkdir()
            bench_multi_target(args, Path(tmp) / "multi")
        for name, bench in (
            ("inventory", bench_inventory),
            ("polling", bench_polling),
            ("slow-connections", bench_slow_connections),
        ):
            if args.only in (None, name):
                (Path(tmp) / name).mkdir()
                bench(args, Path(tmp) / name)


if __name__ == "__main__":
    main()
