"""What the pages of docs/ state, done as they state it against a real peer: the mask-write
formula and its example (issue 39.13), the TLS pages' openssl recipe (issue 39.14), and what
Ctrl-C ends poll and read --interval with (issue 39.15)."""

from __future__ import annotations

import re
import shlex
import shutil
import signal
import subprocess

import pytest
from helpers.checks import wait_until
from helpers.run import REPO_ROOT, interrupt_after, run_cli
from helpers.served import serve


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


def _recipe() -> tuple[str, list[list[str]]]:
    """The openssl recipe of docs/connecting.md as the page shows it, and the mbtool command
    lines of the block after it, each split as a shell splits it."""
    text = (REPO_ROOT / "docs" / "connecting.md").read_text(encoding="utf-8")
    section = text.split("#### Making the certificates with openssl", 1)
    assert len(section) == 2, "docs/connecting.md has no openssl recipe for the TLS certificates"
    blocks = [block.split("```", 1)[0] for block in section[1].split("```sh\n")[1:3]]
    return blocks[0], [shlex.split(line)[1:] for line in blocks[1].splitlines() if line.startswith("mbtool ")]


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is not installed")
def test_the_tls_pages_openssl_recipe_makes_certificates_serve_and_mbtool_use(tmp_path):
    """docs/connecting.md's recipe, run verbatim, makes the CA, the device's certificate (for
    its name and for 127.0.0.1) and mbtool's client certificate with its role; the page's own
    command lines then use them: serve on tls:// with --write-roles operator, a write (the
    recipe's role may write) and a read by the device's name (issue 39.14)."""
    recipe, commands = _recipe()
    done = subprocess.run(
        ["bash", "-e", "-c", recipe], cwd=tmp_path, capture_output=True, text=True, timeout=60
    )
    assert done.returncode == 0, done.stderr
    (serve_line, *client_lines) = commands
    assert serve_line[:3] == ["serve", "-p", "tls://127.0.0.1:8802"] and len(client_lines) == 2, commands

    def here(args: list[str]) -> list[str]:  # the files the recipe made, where it made them
        return [str(tmp_path / arg) if (tmp_path / arg).is_file() else arg for arg in args]

    with serve(*here(serve_line[3:]), target="tls://127.0.0.1:0", quiet=False) as server:
        results = [
            run_cli(*here([server.target if arg == "tls://127.0.0.1:8802" else arg for arg in line]))
            for line in client_lines
        ]
        assert wait_until(lambda: "role operator" in server.log(), 5), server.log()
        wrong_name = run_cli(
            "read-holding-registers", "10", "1", "-p", server.target, "--server-name", "plc7.plant.example",
            *here(client_lines[1][client_lines[1].index("--cert"):]),
        )  # fmt: skip
    wrote, read = results
    assert wrote.returncode == 0, wrote  # the role is the recipe's: operator may write
    assert read.returncode == 0 and read.lines[0].split() == ["0", "1"], read  # by its name
    assert wrong_name.returncode == 6, wrong_name  # and the name is checked: the SAN is what it says


def test_ctrl_c_ends_poll_and_read_interval_by_their_verdict_as_the_pages_say(tmp_path):
    """130 is "interrupted", but poll and read --interval end on Ctrl-C as their way to stop:
    statistics, then the verdict's status (issue 39.15). The exit-code table, the man page
    and docs/plant.md say so where 130 is, and the commands do it."""
    plant = tmp_path / "plant.toml"
    plant.write_text(
        '[poll]\ninterval = 0.2\n[links.bus]\ntarget = "sim://"\ntimeout = 0.2\n'
        '[devices.meter]\nlink = "bus"\nread = ["40001 2"]\n'
        '[devices.dead]\nlink = "bus"\nunit = 9\nread = ["40001 1"]\n'
    )
    code, _, err = interrupt_after(["poll", str(plant), "-o", "plain"], 4, sig=signal.SIGINT)
    assert code == 8 and "device  meter" in err and "interrupted; 1 of 2 devices answered" in err, err
    code, _, err = interrupt_after(
        ["read-holding-registers", "0", "2", "--interval", "0.1", "-p", "sim://"], 4, sig=signal.SIGINT
    )
    assert code == 0 and err.startswith("mbtool: interrupted; polls "), err

    row = next(line for line in _page_lines("exit-codes.md") if line.startswith("| 130 |"))
    for said in ("`poll`", "`read --interval`", "statistics", "verdict"):
        assert said in row, f"docs/exit-codes.md's 130 row does not say {said}: {row}"
    man = (REPO_ROOT / "man" / "mbtool.1").read_text(encoding="utf-8").replace("\\-", "-")
    assert "poll and read --interval" in " ".join(man.split()), "the man page's 130 does not name them"
    plant_page = _page("plant.md")
    assert (
        "Ctrl-C ends it cleanly, with the statistics on stderr, and the exit status of the verdict below"
        in plant_page
    )


def _page_lines(name: str) -> list[str]:
    return (REPO_ROOT / "docs" / name).read_text(encoding="utf-8").splitlines()
