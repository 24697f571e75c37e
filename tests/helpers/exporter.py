"""``mbtool exporter`` on a free loopback port, the example meter it serves, and a GET of it."""

from __future__ import annotations

import contextlib
import re
import signal
import subprocess
import urllib.error
import urllib.request
from dataclasses import dataclass
from pathlib import Path

import pytest

from helpers.run import REPO_ROOT, first_line, start_mbtool

METER_DATA = REPO_ROOT / "examples" / "energy-meter-data.toml"
METER_MAP = REPO_ROOT / "examples" / "energy-meter.toml"


@dataclass
class Running:
    proc: subprocess.Popen
    url: str  # http://127.0.0.1:PORT
    line: str  # the first line it printed
    stderr: Path

    def get(self, path: str, headers: dict[str, str] | None = None, timeout: float = 30.0):
        return http_get(self.url + path, headers, timeout)


@contextlib.contextmanager
def exporting(*args: str, tmp_path: Path, **popen):
    """mbtool exporter ARGS on a free loopback port; stopped by SIGTERM, which must end it with
    exit 0 and no traceback.  ``popen``: more of start_mbtool's arguments."""
    stderr = tmp_path / f"exporter-{len(list(tmp_path.glob('exporter-*')))}.err"
    with open(stderr, "w") as err:
        proc = start_mbtool("exporter", "--listen", "127.0.0.1:0", *args, stderr=err, text=False, **popen)
    try:
        line = first_line(proc, "exporting on ")
        yield Running(proc, re.search(r"http://[^ ]+", line)[0], line, stderr)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
        try:
            proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate(timeout=5)
            pytest.fail("the exporter did not stop on SIGTERM within 10 s")
        assert proc.returncode == 0, stderr.read_text()
        assert "Traceback" not in stderr.read_text()


def http_get(url: str, headers: dict[str, str] | None = None, timeout: float = 30.0) -> tuple[int, str, str]:
    """(status, content type, body) of a GET, whatever the status."""
    opener = urllib.request.build_opener(urllib.request.ProxyHandler({}))  # loopback, never a proxy
    try:
        with opener.open(urllib.request.Request(url, headers=headers or {}), timeout=timeout) as response:
            return response.status, response.headers["Content-Type"], response.read().decode()
    except urllib.error.HTTPError as error:
        return error.code, error.headers["Content-Type"], error.read().decode()
