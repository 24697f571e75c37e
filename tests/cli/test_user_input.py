"""Every invalid input to every device command: exit 2, one stderr line, 0 bytes sent (issue 6).

The transport is replaced in-process by one that records every write and
answers like sim://, so a case that slipped past validation would show up as
bytes sent (and the valid controls prove the recorder sees what goes out).
"""

from __future__ import annotations

import shlex

import pytest
from helpers.run import run_cli

import mbtool.link.transport

SENT: list[bytes] = []


@pytest.fixture(autouse=True)
def recording_transport(monkeypatch):
    real = mbtool.link.transport.open_transport

    def open_recording(target, settings, timeout, framer, tls=None):
        inner = real("sim://", settings, timeout, framer)
        original = inner.write

        def write(data: bytes) -> None:
            SENT.append(bytes(data))
            original(data)

        inner.write = write
        return inner

    SENT.clear()
    monkeypatch.setattr(mbtool.link.transport, "open_transport", open_recording)
    yield


def run(line: str) -> tuple[int, str, str]:
    res = run_cli(*shlex.split(line), "-p", "/dev/ttyNOWHERE")
    return res.returncode, res.stdout, res.stderr


INVALID = [
    # addresses
    "read-coils -1 1",
    "read-coils 65536",
    "read-coils 0x10000 1",
    "read-coils abc",
    "read-holding-registers 65535 2",
    "write-coil 70000 on",
    "write-register -- -1 5",
    "mask-write-register 65536 0 0",
    "fifo 0x1FFFF",
    "read-write-registers 65536 1 0 5",
    "read-write-registers 0 1 65536 5",
    # quantities
    "read-coils 0 0",
    "read-coils 0 2001",
    "read-discrete-inputs 0 2001",
    "read-discrete-inputs 0 0",
    "read-holding-registers 0 126",
    "read-input-registers 0 0",
    "read-input-registers 0 126",
    "read-holding-registers 0 63 --type float32",
    "read-holding-registers 0 32 --type float64",
    "read-write-registers 0 126 0 5",
    "read-write-registers 0 0 0 5",
    "write-coils 0 " + " ".join(["1"] * 1969),
    "write-registers 0 " + " ".join(["1"] * 124),
    "write-registers 0 " + " ".join(["1.5"] * 62) + " --type float32",
    "read-write-registers 0 1 0 " + " ".join(["1"] * 122),
    "read-file-record 4 1 0",
    "read-file-record 4 10000 1",
    "read-file-record 0 1 1",
    "read-file-record 4 1",
    # unit ids
    "read-coils 0 1 -u 256",
    "read-coils 0 1 -u -1",
    "read-coils 0 1 -u x",
    "read-coils 0 1 -u 0",
    "read-holding-registers 0 1 -u 0",
    "read-exception-status -u 0",
    "event-counter -u 0",
    "event-log -u 0",
    "report-id -u 0",
    "diag return-query-data 0001 -u 0",
    "diag counters -u 0",
    "device-id -u 0",
    "fifo 0 -u 0",
    "read-file-record 4 1 1 -u 0",
    "read-write-registers 0 1 0 5 -u 0",
    # values
    "write-coil 0 maybe",
    "write-coil 0 2",
    "write-coils 0 1 0 x",
    "write-register 0 65536",
    "write-register 0 -32769",
    "write-register 0 1.5",
    "write-register 0 0x10000",
    "write-register 0 ten",
    "write-registers 0 1 x",
    "write-registers 0 70000",
    "write-registers 0 abc --type float32",
    "write-registers 0 40000 --type int16",
    "write-registers 0 5000000000 --type uint32",
    "write-registers 0 -1 --type uint32",
    "mask-write-register 0 0x10000 0",
    "mask-write-register 0 0 -1",
    "write-file-record 4 7",
    "write-file-record 4 7 70000",
    "write-file-record 4 10000 1",
    "write-file-record 0 7 1",
    "write-file-record 4 7 1 , 3",
    "read-write-registers 0 1 0 x",
    "device-id --object 256",
    "device-id --object x",
    # type/order combinations
    "read-holding-registers 0 1 --type float16",
    "read-holding-registers 0 1 --order XYZW",
    "write-register 0 1 --type float32",
    "write-register 0 1 --type string",
    "read-coils 0 1 --type float32",
    "write-coils 0 1 --order CDAB",
    # diagnostics
    "diag nonsense",
    "diag 0x10000",
    "diag return-query-data ZZZZ",
    "diag return-query-data 123",
    "diag change-ascii-delimiter ab",
    "diag diagnostic-register --controller 9999",
    "diag restart-comms maybe",
    # hex strings (raw)
    "raw zz",
    "raw 01",
    "raw 01 03 00 00 00 02 GG",
    "raw --adu 01 03",
    "raw --adu --framer tcp 00 01 00 00",
    "raw --adu --framer ascii :01",
    # option values
    "read-coils 0 1 --timeout 0",
    "read-coils 0 1 --timeout -1",
    "read-coils 0 1 --timeout nan",
    "read-coils 0 1 --timeout inf",
    "read-coils 0 1 --timeout x",
    "read-coils 0 1 --retries 101",
    "read-coils 0 1 --retries -1",
    "read-coils 0 1 --baud 0",
    "read-coils 0 1 --baud fast",
    "read-coils 0 1 --parity X",
    "read-coils 0 1 --bytesize 9",
    "read-coils 0 1 --stopbits 3",
    "read-coils 0 1 --framer udp",
    "read-coils 0 1 -o xml",
    "read-coils 0 1 --no-such-option",
    "device-id --level everything",
    "read-holding-registers",
    "write-coils 0",
    "read-coils 0 1 2",
]


@pytest.mark.parametrize("line", INVALID)
def test_invalid_input_exits_2_with_one_line_and_sends_nothing(line):
    code, out, err = run(line)
    assert code == 2, (code, err)
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("mbtool: "), err
    assert "Traceback" not in err
    assert SENT == []


@pytest.mark.parametrize(
    "line",
    ["read-coils 0 1", "write-register 0 -5", "raw 01 03 00 00 00 01", "diag counters", "device-id"],
)
def test_valid_controls_are_recorded(line):
    """The recorder does see frames: the cases above sent nothing because they were refused."""
    code, _, err = run(line)
    assert code == 0, err
    assert SENT
