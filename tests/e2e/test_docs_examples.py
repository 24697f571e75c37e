"""What the pages of docs/ state, done as they state it against a real peer: the mask-write
formula and its example (issue 39.13) and the TLS pages' openssl recipe (issue 39.14)."""

from __future__ import annotations

import re

from helpers import REPO_ROOT, run_cli, serve


def _page(name: str) -> str:
    return " ".join((REPO_ROOT / "docs" / name).read_text(encoding="utf-8").split())


def test_the_mask_write_formula_is_stated_and_its_example_is_what_a_device_does():
    """docs/reading-and-writing.md states the formula (it pointed at 'seed 002', which a reader
    does not have), and its example, run against mbtool serve, leaves what it says."""
    page = _page("reading-and-writing.md")
    assert "seed" not in page
    assert "(current AND and_mask) OR (or_mask AND NOT and_mask)" in page
    example = re.search(
        r"(0x[0-9A-F]+) with and_mask (0x[0-9A-F]+) and or_mask (0x[0-9A-F]+) becomes (0x[0-9A-F]+)", page
    )
    assert example, "the page gives no worked example of the formula"
    current, and_mask, or_mask, result = (int(number, 16) for number in example.groups())
    assert (current & and_mask) | (or_mask & ~and_mask & 0xFFFF) == result  # the formula as written
    with serve() as device:
        assert run_cli("write-register", "4", str(current), "-p", device.target).returncode == 0
        done = run_cli("mask-write-register", "4", hex(and_mask), hex(or_mask), "-p", device.target)
        assert done.returncode == 0, done
        read = run_cli("read-holding-registers", "4", "1", "-o", "plain", "-p", device.target)
    assert read.stdout.split() == ["4", str(result)], read
