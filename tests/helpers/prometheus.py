"""Prometheus text checked by Prometheus's own ``promtool``, and a stream of expositions cut
into them.
"""

from __future__ import annotations

import shutil
import subprocess

import pytest

from helpers.run import MBTOOL_TIMEOUT


def promtool_check(text: str) -> None:
    """Prometheus's own checker on an exposition (``promtool check metrics``: the parse and
    the lint); skips the test when Debian's prometheus, which ships promtool, is missing."""
    promtool = shutil.which("promtool")
    if promtool is None:
        pytest.skip("promtool is not installed (Debian's prometheus ships it)")
    check = subprocess.run(
        [promtool, "check", "metrics"], input=text, capture_output=True, text=True, timeout=MBTOOL_TIMEOUT
    )
    assert check.returncode == 0, (check.stdout + check.stderr, text)


def expositions(stream: str) -> list[str]:
    """A stream of whole expositions (poll -o prom, a round each) cut into them: each starts
    with modbus_up's HELP line."""
    head = "# HELP modbus_up "
    return [head + part for part in stream.split(head)[1:]]
