"""One command-line convention (issue 14): choices in any case, "did you mean", and options
that came before the command are told where they go."""

from __future__ import annotations

import pytest
from helpers.checks import assert_one_error_line
from helpers.run import run_cli


def test_choices_take_any_case_and_mean_the_same():
    lower = run_cli(
        "read-holding-registers", "100", "1", "-p", "sim://", "--type", "float32", "--order", "abcd"
    )
    upper = run_cli(
        "read-holding-registers", "100", "1", "-p", "sim://", "--type", "FLOAT32", "--order", "ABCD"
    )
    assert lower.returncode == upper.returncode == 0, str(lower) + str(upper)
    assert lower.stdout == upper.stdout and "21.5" in upper.stdout
    res = run_cli("read-coils", "0", "-p", "sim://", "--framer", "RTU", "-o", "JSON")
    assert res.returncode == 0 and res.stdout.startswith("{"), str(res)


@pytest.mark.parametrize("word", ["none", "NONE", "n", "N"])
def test_parity_none_is_n_on_the_command_line(word):
    res = run_cli("read-coils", "0", "-p", "sim://", "--parity", word, "--dry-run")
    assert res.returncode == 0, str(res)


def test_parity_none_is_n_in_a_profile(tmp_path):
    config = tmp_path / "config.toml"
    config.write_text('[profiles.s]\nport = "sim://"\nparity = "none"\n')
    res = run_cli("read-coils", "0", "-P", "s", env={"MBTOOL_CONFIG": str(config)})
    assert res.returncode == 0, str(res)
    config.write_text('[profiles.s]\nport = "sim://"\nparity = "space"\n')
    line = assert_one_error_line(run_cli("read-coils", "0", "-P", "s", env={"MBTOOL_CONFIG": str(config)}), 2)
    assert "profiles.s.parity" in line


def test_a_mistyped_command_gets_the_close_ones():
    line = assert_one_error_line(run_cli("read-holding-register", "0", "-p", "sim://"), 2)
    assert line.startswith(
        "mbtool: no such command read-holding-register; did you mean read-holding-registers"
    )
    line = assert_one_error_line(run_cli("frobnicate"), 2)
    assert "no such command frobnicate" in line and "did you mean" not in line


def test_a_mistyped_option_gets_the_close_ones():
    line = assert_one_error_line(run_cli("read-coils", "0", "-p", "sim://", "--framr", "rtu"), 2)
    assert "no such option --framr; did you mean --framer" in line


def test_options_before_the_command_are_told_where_they_go():
    res = run_cli("-p", "sim://", "-u", "1", "read-holding-registers", "0", "2")
    line = assert_one_error_line(res, 2)
    assert "options follow the command: mbtool read-holding-registers 0 2 -p sim:// -u 1" in line
    assert res.stdout == ""
    # What it suggests works.
    assert run_cli("read-holding-registers", "0", "2", "-p", "sim://", "-u", "1").returncode == 0


# --- no command takes an option it ignores (issue 28) ----------------------------------------


def _command_tree() -> dict:
    import click

    from mbtool.cli import COMMANDS, cli

    ctx = click.Context(cli)
    return {name: cli.get_command(ctx, name) for name in COMMANDS}


def _option_names(command) -> set[str]:
    return {name for param in command.params for name in param.opts + param.secondary_opts}


def test_no_command_takes_an_option_it_ignores():
    commands = _command_tree()
    for name, command in commands.items():
        names = _option_names(command)
        # --reconnect-each reopens the link every poll: only a command that polls takes it
        # (ping's --interval is ping(8)'s, between its requests).
        assert ("--reconnect-each" in names) == ("--polls" in names), name
        # --no-header leaves out CSV's header row: only where -o offers csv.
        fmt = next((param for param in command.params if "-o" in param.opts), None)
        offers_csv = fmt is not None and "csv" in fmt.type.choices
        assert ("--no-header" in names) == offers_csv, name
    # A dump writes a data file and check a plugin's line: neither has a format to choose.
    for name in ("dump", "check"):
        assert not {"-o", "--no-header", "--reconnect-each"} & _option_names(commands[name]), name
    # raw sends the unit as the first byte of HEX.
    assert not {"-u", "--unit"} & _option_names(commands["raw"])


@pytest.mark.parametrize("option", [["-o", "json"], ["-o", "csv"], ["--no-header"], ["--reconnect-each"]])
def test_dump_refuses_the_options_it_has_no_use_for(tmp_path, option):
    line = assert_one_error_line(run_cli("dump", tmp_path / "d.toml", *option, "-p", "sim://"), 2)
    assert f"no such option {option[0]}" in line
    assert not (tmp_path / "d.toml").exists()


def test_diff_csv_without_its_header(tmp_path):
    (tmp_path / "a.toml").write_text("sparse = true\n[holding_registers]\n5 = [5]\n")
    (tmp_path / "b.toml").write_text("sparse = true\n[holding_registers]\n5 = [99]\n")
    both = (tmp_path / "a.toml", tmp_path / "b.toml")
    assert run_cli("diff", *both, "-o", "csv").stdout.splitlines()[0].startswith("table,address")
    res = run_cli("diff", *both, "-o", "csv", "--no-header")
    assert res.returncode == 1 and res.stdout.splitlines() == ["holding,5,40006,,5,99,"]


@pytest.mark.parametrize(
    "args, words",
    [
        (("serve", "--seed", "7"), "--seed picks which replies --drop and --corrupt spoil"),
        (("bridge", "-p", "sim://", "-q", "-o", "json"), "-q shows no transaction: -o would have nothing"),
        (("bridge", "-p", "sim://", "-q", "--hex"), "-q shows no transaction: --hex would have nothing"),
    ],
    ids=["serve-seed", "bridge-quiet-o", "bridge-quiet-hex"],
)
def test_an_option_another_makes_pointless_is_refused(args, words):
    """serve --seed spoils nothing without --drop or --corrupt, and bridge -q shows nothing
    that -o or --hex would shape: refused, rather than accepted and ignored (issue 28)."""
    res = run_cli(*args, "--listen" if args[0] == "bridge" else "-p", "tcp://127.0.0.1:0")
    assert words in assert_one_error_line(res, 2)
