"""No round trip shorter than the device's (issue 39.2): against ``mbtool serve --delay 0.02``,
a device that holds every reply back 20 ms, every round-trip time mbtool shows -- ``read
--interval``'s and ``poll``'s ``--stats json``, ``ping``'s lines and summary, the exporter's
histogram, the client's own figure -- is at least those 20 ms, also while mbtool's output goes
to a pipe read slowly (the poll's lines on stdout, the --hex trace on stderr).

A round trip runs from the request's last byte written to the reply's last byte read.  A reply
that came while mbtool was busy with something else (the output blocked on the pipe) has no
known arrival: it is left out of the figures and counted as untimed, never timed from the end
of that work (which made it the time the reply sat in the buffer: 7 us against serve).
"""

from __future__ import annotations

import fcntl
import json
import os
import re
import subprocess
import threading
import time
from contextlib import nullcontext
from pathlib import Path

import pytest
from helpers.exporter import exporting
from helpers.run import start_mbtool
from helpers.served import serve
from prometheus_client.parser import text_string_to_metric_families

from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.errors import NoResponse
from mbtool.link.connection import Connection, open_client
from mbtool.link.managed import Backoff, ManagedLink
from mbtool.link.stats import Stats

pytestmark = pytest.mark.timeout(90)

DELAY = 0.02  # seconds serve holds every reply back: no round trip can be shorter
F_SETPIPE_SZ = 1031  # Linux: set a pipe's buffer size (fcntl.F_SETPIPE_SZ, Python 3.10 on)
PIPE_PAGE = 4096  # the smallest a pipe's buffer can be
# Longer than any round trip of the delayed device, shorter than a blocked write lasts (about a
# second): a round trip timed across mbtool's wait for the pipe is caught.
CEILING = DELAY + 0.2


class SlowReader:
    """The reading end of a child's pipe, left unread at first and then read now and then: the
    pipe's buffer (one page, as small as the kernel allows) fills, and the child's next write
    blocks until the reader comes back, as it does behind a slow consumer (ssh, a busy log
    shipper).  ``start`` 0: read as it comes."""

    def __init__(self, pipe, start: float = 2.0, pause: float = 0.5) -> None:
        fcntl.fcntl(pipe.fileno(), F_SETPIPE_SZ, PIPE_PAGE)
        self.pipe, self.start, self.pause = pipe, start, pause if start else 0.0
        self.data = bytearray()
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        time.sleep(self.start)  # the pipe fills meanwhile
        while block := os.read(self.pipe.fileno(), 65536):
            self.data += block
            time.sleep(self.pause)

    def text(self, deadline: float = 60.0) -> str:
        self.thread.join(deadline)
        assert not self.thread.is_alive(), "the pipe did not end"
        return self.data.decode()


def run_slowly(*args: str, slow: str) -> tuple[int, str, str]:
    """mbtool ARGS, its ``slow`` stream ("stdout" or "stderr") a pipe read slowly, the other read
    at once: (exit code, stdout, stderr)."""
    proc = start_mbtool(*args, text=False)
    readers = {
        "stdout": SlowReader(proc.stdout) if slow == "stdout" else SlowReader(proc.stdout, 0),
        "stderr": SlowReader(proc.stderr) if slow == "stderr" else SlowReader(proc.stderr, 0),
    }
    try:
        proc.wait(timeout=60)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=5)
        pytest.fail(f"mbtool {' '.join(args)} did not finish")
    return proc.returncode, readers["stdout"].text(), readers["stderr"].text()


def stats_json(stderr: str) -> dict:
    """--stats json's object: the one line of stderr that is JSON."""
    objects = [json.loads(line) for line in stderr.splitlines() if line.startswith("{")]
    assert len(objects) == 1, stderr[-2000:]
    return objects[0]


def assert_floor(stats: dict, answered: int) -> None:
    """A link.stats record (as_dict): every round trip at least DELAY (none below it in the
    histogram) and none as long as a blocked write, and every answer either timed or counted as
    untimed."""
    assert stats["answered"] == answered, stats
    rtt = stats["rtt_seconds"]
    assert rtt is not None and DELAY <= rtt["min"] and rtt["max"] < CEILING, rtt
    buckets = dict((bound, count) for bound, count in stats["rtt_buckets"] if bound is not None)
    assert buckets[0.01] == 0, stats["rtt_buckets"]
    timed = stats["rtt_buckets"][-1][1]
    assert timed + stats["rtt_untimed"] == answered, stats


@pytest.fixture(scope="module")
def slow_device():
    with serve("--delay", str(DELAY)) as server:
        yield server


def test_polling_stats_never_beat_the_device_while_stdout_is_read_slowly(slow_device):
    code, _, err = run_slowly(
        "read-holding-registers", "0", "20", "-p", slow_device.target,
        "--interval", "0", "--polls", "40", "-o", "json", "--stats", "json",
        slow="stdout",
    )  # fmt: skip
    assert code == 0, err[-2000:]
    stats = stats_json(err)
    assert_floor(stats, 40)
    latency = stats["latency_ms"]
    assert latency["per_request"]["min"] >= DELAY * 1000, latency
    assert latency["per_poll"]["min"] >= DELAY * 1000, latency


def test_a_maps_poll_is_timed_from_its_first_request_or_not_at_all(slow_device, tmp_path):
    # Two requests a poll (two blocks of a map): the poll's latency is at least two delays.
    (tmp_path / "map.toml").write_text(
        "[device]\nmax_gap = 0\n[points.a]\nref = 40001\n[points.b]\nref = 40101\n"
    )
    code, _, err = run_slowly(
        "read", "-m", str(tmp_path / "map.toml"), "-p", slow_device.target,
        "--interval", "0", "--polls", "30", "-o", "json", "--stats", "json",
        slow="stdout",
    )  # fmt: skip
    assert code == 0, err[-2000:]
    stats = stats_json(err)
    assert_floor(stats, 60)
    assert stats["latency_ms"]["per_poll"]["min"] >= 2 * DELAY * 1000, stats["latency_ms"]


def test_ping_times_never_beat_the_device_while_its_trace_is_read_slowly(slow_device):
    code, out, err = run_slowly(
        "ping", "-c", "50", "-i", "0", "--hex", "-p", slow_device.target, slow="stderr"
    )
    assert code == 0, err[-2000:]
    times = [float(m[1]) for m in re.finditer(r"seq=\d+ time=([\d.]+) ms", out)]
    untimed = re.findall(r"seq=\d+ untimed", out)
    assert len(times) + len(untimed) == 50, out
    assert DELAY * 1000 <= min(times) and max(times) < CEILING * 1000, out
    summary = err.strip().splitlines()[-1]
    figures = re.search(r"rtt min/avg/max/mdev ([\d.]+)/[\d.]+/([\d.]+)/", summary)
    assert figures and DELAY * 1000 <= float(figures[1]) and float(figures[2]) < CEILING * 1000, summary
    assert (f"({len(untimed)} untimed)" in summary) == bool(untimed), summary


def plant(tmp_path: Path, target: str, interval: float = 0.001) -> Path:
    inventory = tmp_path / "plant.toml"
    inventory.write_text(
        f'[poll]\ninterval = {interval}\n[links.a]\ntarget = "{target}"\n'
        '[devices.d]\nlink = "a"\nunit = 1\nread = ["40001 4"]\n'
    )
    return inventory


def test_the_plants_stats_never_beat_the_device_while_its_trace_is_read_slowly(slow_device, tmp_path):
    code, _, err = run_slowly(
        "poll", plant(tmp_path, slow_device.target), "--rounds", "50", "-o", "json", "--hex",
        "--stats", "json",
        slow="stderr",
    )  # fmt: skip
    assert code == 0, err[-2000:]
    stats = stats_json(err)
    assert_floor(stats["devices"]["d"], 50)
    assert_floor(stats["links"]["a"], 50)


def test_the_exporters_histogram_never_beats_the_device(slow_device, tmp_path):
    with exporting(plant(tmp_path, slow_device.target, 0.05), tmp_path=tmp_path) as running:
        end = time.monotonic() + 30
        while True:
            status, _, body = running.get("/metrics")
            assert status == 200, body
            samples = {
                (sample.name, sample.labels.get("le")): sample.value
                for family in text_string_to_metric_families(body)
                if family.name == "modbus_request_duration_seconds"
                for sample in family.samples
            }
            if (
                samples.get(("modbus_request_duration_seconds_count", None), 0) >= 10
                or time.monotonic() > end
            ):
                break
            time.sleep(0.1)
    assert samples[("modbus_request_duration_seconds_count", None)] >= 10, samples
    assert samples[("modbus_request_duration_seconds_bucket", "0.01")] == 0, samples
    # Every reply is in the histogram or counted as untimed, beside it.
    answered = [
        sample.value
        for family in text_string_to_metric_families(body)
        for sample in family.samples
        if sample.name == "modbus_transactions_total"
        and sample.labels["outcome"] in ("answered", "exception")
    ]
    untimed = [
        sample.value
        for family in text_string_to_metric_families(body)
        for sample in family.samples
        if sample.name == "modbus_untimed_replies_total"
    ]
    assert untimed and samples[("modbus_request_duration_seconds_count", None)] + untimed[0] == sum(answered)


READ = ReadHoldingRegisters(0, 1)


def test_a_reply_that_came_while_mbtool_worked_is_untimed_not_timed_from_the_work(slow_device):
    stats = Stats()
    with open_client(Connection(port=slow_device.target)) as client:
        counted = ManagedLink(lambda: nullcontext(client), Backoff(0.0), stats).execute
        for work in (0.0, 3 * DELAY, 0.0):
            client.while_waiting = (lambda w=work: time.sleep(w)) if work else None
            counted(1, READ)
            if work:
                assert client.rtt is None  # the reply sat waiting for mbtool: its arrival is unknown
            else:
                assert client.rtt >= DELAY
    assert stats.outcomes["answered"] == 3
    assert stats.rtt.count == 2 and stats.untimed == 1
    assert stats.rtt_figures()["min"] >= DELAY


def test_a_late_reply_to_an_earlier_attempt_is_timed_from_that_attempt():
    # serve holds each reply 0.3 s; the client gives up on the first request at 0.2 s and sends
    # it again: the first reply then comes 0.1 s after the second request.  Over MBAP its
    # transaction id names the attempt it answers, so its round trip is the whole 0.3 s.
    with serve("--delay", "0.3") as server:
        stats = Stats()
        with open_client(Connection(port=server.target, timeout=0.2, retries=1)) as client:
            ManagedLink(lambda: nullcontext(client), Backoff(0.0), stats).execute(1, READ)
            assert client.attempts == 2
            assert client.rtt >= 0.3
    assert stats.rtt_figures()["min"] >= 0.3


def test_without_transaction_ids_a_reply_after_a_retry_is_untimed():
    # RTU frames carry no transaction id: the reply after a retry may be the first request's,
    # late, or the second's, prompt.  Which is not known, so neither is its round trip.
    with serve("--delay", "0.3", "--framer", "rtu") as server:
        stats = Stats()
        with open_client(Connection(port=server.socket_target, timeout=0.2, retries=1)) as client:
            ManagedLink(lambda: nullcontext(client), Backoff(0.0), stats).execute(1, READ)
            assert client.attempts == 2
            assert client.rtt is None
    assert stats.outcomes["answered"] == 1 and stats.untimed == 1 and stats.rtt.count == 0


def test_silence_is_neither_timed_nor_untimed(slow_device):
    stats = Stats()
    with open_client(Connection(port=slow_device.target, timeout=DELAY / 4)) as client:
        with pytest.raises(NoResponse):
            ManagedLink(lambda: nullcontext(client), Backoff(0.0), stats).execute(1, READ)
    assert stats.outcomes["timeout"] == 1 and stats.untimed == 0 and stats.rtt.count == 0
