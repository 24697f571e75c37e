"""decode of a real socat -x dump (issue 28): mbtool reads serve through socat, and decode reads what
socat saw, in both of its dump formats."""

from __future__ import annotations

import json
import subprocess
import time

import pytest
from helpers.run import run_cli, run_mbtool
from helpers.served import serve
from helpers.sockets import free_port


def _socat_x(tmp_path, *flags: str) -> str:
    """A real socat -x dump of a read through it: mbtool -> socat -> serve (RTU over TCP)."""
    import shutil
    import signal

    if shutil.which("socat") is None:
        pytest.skip("socat is not installed")
    port = free_port()
    log = tmp_path / "socat.log"
    with serve("--framer", "rtu") as server, open(log, "w") as err:
        socat = subprocess.Popen(
            ["socat", *flags, f"TCP-LISTEN:{port},bind=127.0.0.1,reuseaddr", f"TCP:127.0.0.1:{server.port}"],
            stderr=err,
        )
        try:
            deadline = time.monotonic() + 10
            while True:
                res = run_cli("read-holding-registers", "0", "2", "-p", f"socket://127.0.0.1:{port}")
                if res.returncode == 0 or time.monotonic() > deadline:
                    break
                time.sleep(0.1)  # socat not listening yet
            assert res.returncode == 0, str(res)
        finally:
            socat.send_signal(signal.SIGTERM)
            socat.wait(timeout=5)
    return log.read_text()


@pytest.mark.parametrize("flags", [["-x"], ["-x", "-v"]], ids=["x", "xv"])
def test_a_socat_dump_decodes(tmp_path, flags):
    dump = _socat_x(tmp_path, *flags)
    assert dump.startswith("> ") and "length=8" in dump
    res = run_mbtool("decode", "-o", "json", input=dump)
    assert res.returncode == 0, str(res)
    records = [json.loads(line) for line in res.stdout.splitlines()]
    assert [r["kind"] for r in records] == ["request", "response"]
    assert records[0]["raw"] == "01 03 00 00 00 02 C4 0B" and records[1]["error"] is None
