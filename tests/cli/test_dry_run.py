"""--dry-run: every device command prints its frame decoded and opens nothing (issue 6);
every write to unit 0 says on stderr that no device confirms it."""

from __future__ import annotations

import shlex

import pytest
from helpers.run import run_cli

import mbtool.link.transport
from mbtool.cli import COMMANDS

# One valid invocation of every command that talks to a device.
EXAMPLES = {
    "read-coils": "read-coils 0 16",
    "read-discrete-inputs": "read-discrete-inputs 0 8",
    "read-holding-registers": "read-holding-registers 100 1 --type float32",
    "read-input-registers": "read-input-registers 0x10 4",
    "write-coil": "write-coil 173 on",
    "write-register": "write-register 100 -5",
    "write-coils": "write-coils 20 1 0 1 1",
    "write-registers": "write-registers 0 1.5 --type float32 --order CDAB",
    "read": "read 40108 2 --type float32",
    "write": "write 40108 1.5 --type float32",
    "write-bit": "write-bit 40001 3 on",
    "dump": "dump - --range holding:0-99",
    "check": "check 40011 -w 10 -c 20",
    "diff": "diff tests/data/diff-example.toml",
    "read-exception-status": "read-exception-status",
    "diag": "diag return-query-data A537",
    "event-counter": "event-counter",
    "event-log": "event-log",
    "report-id": "report-id",
    "read-file-record": "read-file-record 4 1 2",
    "write-file-record": "write-file-record 4 7 0x6AF 0x4BE",
    "mask-write-register": "mask-write-register 4 0xF2 0x25",
    "read-write-registers": "read-write-registers 0 3 10 7 8",
    "fifo": "fifo 200",
    "device-id": "device-id",
    "raw": "raw 01 03 00 00 00 02",
    "scan": "scan -u 1-5",
    "sunspec": "sunspec",
    "ping": "ping -c 1",
    "identify": "identify",
}
# Commands that never send a request of their own: offline tools, the simulator, the gateway
# (it forwards its clients' requests), the passive monitor and the map library.
OFFLINE = {"decode", "crc", "lrc", "serve", "bridge", "monitor", "maps"}
# poll takes its links and units from its inventory file, not from -p and -u; the exporter
# too, or from each scrape's target.
INVENTORY = {"poll", "exporter"}


def run(line: str) -> tuple[int, str, str]:
    res = run_cli(*shlex.split(line))
    return res.returncode, res.stdout, res.stderr


@pytest.fixture
def no_port(monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("a dry run opened the port")

    monkeypatch.setattr(mbtool.link.transport, "open_transport", refuse)


# restore's dry run reads the device (it shows only the writes that differ), so it opens
# the port; tests/test_dump.py checks that it sends no write.
READS_FIRST = {"restore"}
NO_FORMAT = {"dump", "check", "ping"}  # a data file, a plugin's line, ping(8)'s lines: no -o


def test_every_device_command_has_an_example():
    assert set(EXAMPLES) == set(COMMANDS) - OFFLINE - READS_FIRST - INVENTORY


@pytest.mark.parametrize("framing", ["rtu", "ascii", "tcp"])
@pytest.mark.parametrize("command", sorted(EXAMPLES))
def test_dry_run_prints_the_frame_and_opens_nothing(no_port, command, framing):
    plain = "" if command in NO_FORMAT else " -o plain"  # captured: plain anyway
    code, out, err = run(f"{EXAMPLES[command]} --dry-run -p /dev/ttyUSB0 --framer {framing}{plain}")
    assert code == 0, err
    raw, out = out.split("\n", 1)
    assert raw.startswith("raw ")
    assert out.startswith(f"frame {framing} request") or command == "raw" and framing == "tcp"
    assert "function" in out
    verdict = {"rtu": "crc", "ascii": "lrc", "tcp": "mbap"}[framing]
    assert f"\n{verdict} " in out and " ok" in out.rsplit(verdict, 1)[1]
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("mbtool: dry run: nothing sent"), err


def test_dry_run_shows_the_exact_rtu_frame(no_port):
    code, out, _ = run("read-holding-registers 107 3 -u 17 --dry-run -p /dev/ttyUSB0 -o json")
    assert code == 0
    assert '"frame": "11 03 00 6B 00 03 76 87"' in out


def test_dry_run_needs_no_port(no_port, monkeypatch):
    monkeypatch.delenv("MBTOOL_PORT", raising=False)
    code, out, _ = run("write-coil 0 on --dry-run -o plain")
    assert code == 0 and "crc" in out


def test_dry_run_of_multi_request_commands_says_what_follows(no_port):
    code, out, err = run("device-id --level regular --dry-run -p /dev/ttyUSB0 -o plain")
    assert code == 0 and out.count("frame rtu request") == 1
    assert "further request depends on the reply" in err
    code, out, err = run("diag counters --dry-run -p /dev/ttyUSB0 -o plain")
    assert code == 0 and out.count("frame rtu request") == 8  # FC08 0B..12, all known in advance


def test_dry_run_keeps_the_checksum_typed_by_the_user(no_port):
    code, out, _ = run("raw --adu 01 03 00 00 00 02 00 00 --dry-run -p /dev/ttyUSB0 -o plain")
    assert code == 0 and "crc 00 00 BAD, expected C4 0B" in out


def test_dry_run_still_refuses_bad_input(no_port):
    code, _, err = run("read-coils 0 1 -u 0 --dry-run -p /dev/ttyUSB0")
    assert code == 2 and "broadcast" in err


def test_dry_run_of_a_broadcast_says_nobody_confirms(no_port):
    code, _, err = run("write-register 5 0 -u 0 --dry-run -p /dev/ttyUSB0")
    assert code == 0 and "no device would confirm" in err


@pytest.mark.parametrize(
    "line",
    [
        "write-coil 1 on",
        "write-register 1 5",
        "write-coils 1 1 0",
        "write-registers 1 5 6",
        "mask-write-register 4 0xF2 0x25",
        "write-file-record 4 7 0x6AF 0x4BE",
        "raw 00 06 00 01 00 03",
    ],
)
def test_every_broadcast_write_says_nobody_confirms_it(line):
    unit = "" if line.startswith("raw ") else " -u 0"  # raw's unit is its first byte
    code, _, err = run(f"{line}{unit} -p sim://")
    assert code == 0, err
    assert err.splitlines() == ["mbtool: broadcast: no device confirms a write to unit 0"]


# --- the frame's exact bytes in every format (issue 12.4) ---------------------------------------


@pytest.mark.parametrize(
    "framing, raw",
    [
        (("-p", "sim://"), "01 06 00 0A 00 05 69 CB"),
        (("-p", "tcp://192.0.2.1"), "00 01 00 00 00 06 01 06 00 0A 00 05"),
        (("--framer", "ascii"), ":0106000A0005EA"),
    ],
    ids=["rtu", "tcp", "ascii"],
)
def test_dry_run_shows_the_exact_bytes_in_every_format(framing, raw):
    import json

    args = ("write-register", "10", "5", *framing, "--dry-run")
    assert f"raw {raw}\n" in run_cli(*args, "-o", "plain").stdout
    data = json.loads(run_cli(*args, "-o", "json").stdout)
    assert data["raw"] == raw + ("\r\n" if raw.startswith(":") else "")
    assert f"raw,{raw}" in run_cli(*args, "-o", "csv").stdout
    assert raw in run_cli(*args, "-o", "table").stdout
    assert run_cli(*args, "--hex").stdout.startswith(f"raw {raw}\n")
