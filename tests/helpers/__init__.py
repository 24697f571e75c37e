"""The helpers the tests share, one module a kind:

* ``helpers.run``: running mbtool: a process, or in this process;
* ``helpers.checks``: the assertions and waits in common;
* ``helpers.frames``: frames written without mbtool's codec; a framer's events drained;
* ``helpers.devices``: pymodbus's device as a subprocess, a libmodbus peer;
* ``helpers.ptys``: pseudo-terminal pairs as serial lines;
* ``helpers.sockets``: misbehaving loopback servers, free ports;
* ``helpers.served``: ``mbtool serve`` and ``mbtool bridge`` as a user runs them, pymodbus's client before them;
* ``helpers.exporter``: ``mbtool exporter`` and a GET of it;
* ``helpers.monitor``: ``mbtool monitor`` on a pty, and the frames put on its bus;
* ``helpers.prometheus``: promtool's check, expositions cut apart;
* ``helpers.fakes``: a fake clock, a scripted link, a device's ``execute`` for the unit tests.

A test imports what it uses from the module of its kind (``from helpers.served import serve``;
pyproject's ``pythonpath = ["tests"]``); tests/conftest.py holds the fixtures built on them.
Every wait has a deadline.  The names are also here, as they were when this was one module,
for a test written against that.
"""

from __future__ import annotations

from helpers.checks import (
    HexLine,
    assert_one_error_line,
    closed_by_peer,
    expect_ok,
    json_lines,
    parse_hex_lines,
    plain_pairs,
    wait_until,
)
from helpers.devices import (
    COILS,
    DEVICE_SCRIPT,
    DISCRETE,
    HOLDING,
    INPUT,
    READY_DEADLINE,
    Device,
    build_libmodbus,
    start_device,
    stop_device,
)
from helpers.exporter import (
    METER_DATA,
    METER_MAP,
    Running,
    exporting,
    http_get,
)
from helpers.fakes import (
    FakeClock,
    ScriptedLink,
    device_executor,
)
from helpers.frames import (
    ascii_frame,
    bad_crc,
    crc16,
    drain_events,
    lrc,
    mbap,
    read_mbap,
    rtu,
    settle_events,
)
from helpers.monitor import (
    COILS_REQ,
    DAMAGED_REQ,
    EXCEPTION_RSP,
    GARBAGE,
    INPUT_REQ,
    MONITOR_DEADLINE,
    READ_REQ,
    READ_RSP,
    WRITE_REQ,
    Line,
    finish,
    start_monitor,
)
from helpers.prometheus import (
    expositions,
    promtool_check,
)
from helpers.ptys import (
    PTY_SERIAL_OPTS,
    PtyPair,
)
from helpers.run import (
    MBTOOL_TIMEOUT,
    REPO_ROOT,
    TESTS_DIR,
    Result,
    first_line,
    interrupt_after,
    mbtool_env,
    run_cli,
    run_mbtool,
    signals_as_from_a_shell,
    start_mbtool,
)
from helpers.served import (
    PROMPT,
    SERVE_READY,
    Bridge,
    Served,
    bridge,
    host_and_port,
    pymodbus_tcp,
    serve,
    serving_line,
    start_serve,
    stop_serve,
    timed_read,
)
from helpers.sockets import (
    CLOSE,
    RawResponder,
    SilentServer,
    free_port,
    free_udp_port,
)

__all__ = [
    "TESTS_DIR",
    "REPO_ROOT",
    "MBTOOL_TIMEOUT",
    "Result",
    "mbtool_env",
    "run_mbtool",
    "start_mbtool",
    "run_cli",
    "signals_as_from_a_shell",
    "interrupt_after",
    "first_line",
    "assert_one_error_line",
    "HexLine",
    "parse_hex_lines",
    "plain_pairs",
    "expect_ok",
    "wait_until",
    "closed_by_peer",
    "json_lines",
    "crc16",
    "lrc",
    "rtu",
    "mbap",
    "read_mbap",
    "ascii_frame",
    "bad_crc",
    "drain_events",
    "settle_events",
    "DEVICE_SCRIPT",
    "READY_DEADLINE",
    "HOLDING",
    "INPUT",
    "COILS",
    "DISCRETE",
    "Device",
    "stop_device",
    "start_device",
    "build_libmodbus",
    "PTY_SERIAL_OPTS",
    "PtyPair",
    "free_port",
    "free_udp_port",
    "CLOSE",
    "SilentServer",
    "RawResponder",
    "SERVE_READY",
    "PROMPT",
    "host_and_port",
    "Served",
    "start_serve",
    "serving_line",
    "stop_serve",
    "serve",
    "Bridge",
    "bridge",
    "pymodbus_tcp",
    "timed_read",
    "METER_DATA",
    "METER_MAP",
    "Running",
    "exporting",
    "http_get",
    "READ_REQ",
    "READ_RSP",
    "WRITE_REQ",
    "COILS_REQ",
    "INPUT_REQ",
    "EXCEPTION_RSP",
    "DAMAGED_REQ",
    "GARBAGE",
    "MONITOR_DEADLINE",
    "Line",
    "start_monitor",
    "finish",
    "promtool_check",
    "expositions",
    "FakeClock",
    "ScriptedLink",
    "device_executor",
]
