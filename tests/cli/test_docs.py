"""The man page and shell completions are generated from the click tree and kept current;
the README and the pages of docs/ link to one another and their sim:// examples run.

If a test here fails after a command or option changed: run python scripts/gen_docs.py
(and commit man/mbtool.1 and completions/*).
"""

from __future__ import annotations

import importlib.util
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import click
import pytest
from helpers.run import REPO_ROOT, run_cli

from mbtool.cli import cli

GEN_DOCS = REPO_ROOT / "scripts" / "gen_docs.py"
REGENERATE = "run python scripts/gen_docs.py"
MAN_PAGE = "man/mbtool.1"
BASH = "completions/mbtool.bash"
COMPLETIONS = ("completions/mbtool.bash", "completions/mbtool.zsh", "completions/mbtool.fish")


def _load_gen_docs():
    spec = importlib.util.spec_from_file_location("gen_docs", GEN_DOCS)
    module = importlib.util.module_from_spec(spec)
    sys.modules["gen_docs"] = module  # dataclasses look their module up
    spec.loader.exec_module(module)
    return module


gen_docs = _load_gen_docs()


def _commands(group: click.Group = cli) -> dict[str, click.Command]:
    """The visible commands of the tree, walked with click itself (not with the generator)."""
    ctx = click.Context(group, info_name="mbtool", **group.context_settings)
    commands = {}
    for name in group.list_commands(ctx):
        command = group.get_command(ctx, name)
        if command is not None and not command.hidden:
            commands[name] = command
    return commands


def _option_names(group: click.Group, name: str, command: click.Command) -> list[str]:
    root = click.Context(group, info_name="mbtool", **group.context_settings)
    ctx = click.Context(command, info_name=name, parent=root, **command.context_settings)
    return [
        opt
        for param in command.get_params(ctx)
        if isinstance(param, click.Option) and not param.hidden
        for opt in param.opts + param.secondary_opts
    ]


COMMANDS = _commands()
OPTIONS = sorted(
    {(name, opt) for name, command in COMMANDS.items() for opt in _option_names(cli, name, command)}
)


def _read(path: str) -> str:
    return (REPO_ROOT / path).read_text(encoding="utf-8")


def _has_word(text: str, word: str) -> bool:
    """``word`` as a whole word: read-coils must not be found inside read-coils-x, nor --hex in --hexdump."""
    return re.search(r"(?<![\w-])" + re.escape(word) + r"(?![\w-])", text) is not None


def _man_text() -> str:
    """The man page source with roff's escapes for hyphens and no-hyphenation undone."""
    return re.sub(r"\\f[BIRP]", " ", _read(MAN_PAGE)).replace("\\%", "").replace("\\-", "-")


# --- (a) the committed files are what the generator makes now ---------------------------------


def test_generated_files_are_current():
    outputs = gen_docs.generate(cli)
    assert set(outputs) == {MAN_PAGE, *COMPLETIONS, "README.md", "docs/plant.md"}
    stale = gen_docs.stale(outputs, REPO_ROOT)
    assert not stale, f"out of date: {', '.join(stale)}: {REGENERATE}"


def test_the_live_view_captures_are_the_tools_own():
    """README.md's and docs/plant.md's screens of poll's live view are what LiveView draws
    (issue 39.11: they showed a change of state as the tool never wrote it)."""
    capture = gen_docs.live_view_capture()
    # The event line as poll writes it on stderr: a colon before the reason, the next try after.
    assert "meter9 offline: no response from unit 9 within 0.3 s; next try in 4 s" in capture
    assert capture.splitlines()[0] == "mbtool poll plant.toml: 5 devices, 4 online, 1 offline"
    width, height = gen_docs.CAPTURE_SIZE
    assert len(capture.splitlines()) <= height and max(map(len, capture.splitlines())) <= width
    for path in gen_docs.CAPTURED_IN:
        shown = _read(path).split(gen_docs.CAPTURE_MARK + "\n```text\n", 1)
        assert len(shown) == 2, f"{path} has no generated capture of the live view: {REGENERATE}"
        assert shown[1].split("```\n", 1)[0] == capture, f"{path}'s capture is stale: {REGENERATE}"


def test_check_mode_passes():
    assert gen_docs.main(["--check"]) == 0, f"gen_docs.py --check failed: {REGENERATE}"


def test_output_is_deterministic():
    assert gen_docs.generate(cli) == gen_docs.generate(cli)


# --- (b) every command and option of the tree is in the files ----------------------------------


def test_the_tree_has_commands():
    assert len(COMMANDS) >= 8  # the eight data-access commands at least


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_command_in_man_page(name):
    man = _man_text()
    assert re.search(r"^\.SS " + re.escape(name) + "$", man, re.M), (
        f"command {name} has no section in {MAN_PAGE}: {REGENERATE}"
    )


@pytest.mark.parametrize("option", sorted({option for _, option in OPTIONS}))
def test_option_in_man_page(option):
    assert _has_word(_man_text(), option), f"option {option} is missing from {MAN_PAGE}: {REGENERATE}"


def test_man_page_sections():
    man = _read(MAN_PAGE)
    sections = re.findall(r"^\.SH (.*)$", man, re.M)
    assert sections == [
        "NAME",
        "SYNOPSIS",
        "DESCRIPTION",
        "COMMANDS",
        "OPTIONS",
        "ENVIRONMENT",
        "FILES",
        "EXIT STATUS",
        "EXAMPLES",
        "SEE ALSO",
    ]
    environment = man.split(".SH ENVIRONMENT", 1)[1].split(".SH ", 1)[0]
    for name in ("MBTOOL_PORT", "MBTOOL_UNIT", "NO_COLOR", "MBTOOL_DEBUG"):
        assert name in environment
    exit_status = man.split(".SH EXIT STATUS", 1)[1].split(".SH ", 1)[0]
    for code in (0, 1, 2, 3, 4, 5, 6, 130):
        assert f"\\fB\\%{code}\\fR" in exit_status


def test_man_page_is_valid_roff():
    for number, row in enumerate(_read(MAN_PAGE).splitlines(), 1):
        # A text line must not start a request by accident, nor carry a lone backslash.
        if row.startswith((".", "'")):
            assert re.match(r'^\.(\\"|(TH|SH|SS|PP|TP|IP|RS|RE|nf|fi|br|BR)\b)', row), (
                f"line {number}: {row!r}"
            )
        assert not re.search(r"\\(?![-e&%fBIR\"(\[])", row), f"line {number}: stray backslash in {row!r}"


@pytest.mark.parametrize("example", gen_docs.EXAMPLES, ids=lambda example: example.argv[0])
def test_man_page_examples_parse(example, monkeypatch):
    """The examples are real command lines: the command exists and click accepts the arguments."""
    for name in ("MBTOOL_PORT", "MBTOOL_UNIT"):
        monkeypatch.delenv(name, raising=False)
    for name, value in example.env:
        monkeypatch.setenv(name, value)
    name, *args = example.argv
    assert name in COMMANDS, f"example uses unknown command {name}"
    root = cli.make_context("mbtool", [name], resilient_parsing=True)
    with COMMANDS[name].make_context(name, list(args), parent=root) as ctx:
        assert ctx.params["port"]


# --- (c) completion: Click's scripts, answered by mbtool from the same tree ----------------------


def _complete(line: str, env: dict | None = None) -> list[str]:
    """What mbtool answers a shell for the last word of ``line`` (Click's bash protocol)."""
    words = line.split()
    cword = len(words) if line.endswith(" ") else len(words) - 1
    result = subprocess.run(
        [sys.executable, "-m", "mbtool"],
        env={
            **os.environ,
            **(env or {}),
            "_MBTOOL_COMPLETE": "bash_complete",
            "COMP_WORDS": line,
            "COMP_CWORD": str(cword),
        },
        capture_output=True,
        text=True,
        timeout=30,
        cwd=REPO_ROOT,
    )
    assert result.returncode == 0 and not result.stderr, result.stderr
    return [row for row in result.stdout.split("\n") if row]


def _plain(line: str, env: dict | None = None) -> list[str]:
    return [row.split(",", 1)[1] for row in _complete(line, env) if row.startswith("plain,")]


def test_completes_commands_options_and_choices():
    assert _plain("mbtool ") == list(COMMANDS)
    assert _plain("mbtool read-holding-registers --fo") == ["--format"]
    assert _plain("mbtool read-coils --framer ") == ["rtu", "ascii", "tcp"]
    assert _plain("mbtool read-coils --parity ") == ["N", "E", "O"]
    assert _plain("mbtool write-registers 0 1 --order c") == ["CDAB"]  # any case, as parsing takes it


def test_completes_port_schemes_and_serial_devices():
    offered = _plain("mbtool read-coils -p ")
    assert offered[:7] == ["tcp://", "tls://", "udp://", "rtu+udp://", "socket://", "rfc2217://", "sim://"]
    assert _plain("mbtool read-coils -p so") == ["socket://"]
    assert _plain("mbtool read-coils -p t") == ["tcp://", "tls://"]
    assert _plain("mbtool serve -p r") == ["rtu+udp://", "rfc2217://"]
    assert _plain("mbtool bridge --listen u") == ["udp://"]
    devices = sorted(
        {str(p) for pattern in ("ttyUSB*", "ttyACM*", "ttyAMA*", "ttyS*") for p in Path("/dev").glob(pattern)}
    )
    assert [word for word in offered if word.startswith("/dev/tty")] == devices
    assert _complete("mbtool read-coils -p ./my") == ["file,./my"]  # a path typed by hand: the shell's files


def test_completes_diag_sub_functions_profiles_and_files(tmp_path):
    assert _plain("mbtool diag re") == ["return-query-data", "restart-comms"]
    assert "counters" in _plain("mbtool diag ")
    config = tmp_path / "config.toml"
    config.write_text('[profiles.boiler]\nport = "sim://"\n[profiles.pump]\nunit = 3\n')
    assert _plain("mbtool read-coils -P ", {"MBTOOL_CONFIG": str(config)}) == ["boiler", "pump"]
    assert _plain("mbtool read-coils -P ", {"MBTOOL_CONFIG": str(tmp_path / "none.toml")}) == []
    assert _complete("mbtool serve --data ") == ["file,"]
    assert _complete("mbtool monitor --capture ") == ["file,"]


def test_help_and_man_page_spell_choices_as_the_docs_do():
    """Any case is accepted, but --help, the man page and errors show the listed spelling
    (Click 8.2 and later show case-insensitive choices in lower case)."""
    from click.testing import CliRunner

    help_text = CliRunner().invoke(cli, ["read-coils", "--help"], terminal_width=200).output
    assert "[N|E|O]" in help_text and "[n|e|o]" not in help_text
    write_help = CliRunner().invoke(cli, ["write-registers", "--help"], terminal_width=200).output
    assert "[ABCD|CDAB|BADC|DCBA]" in write_help
    assert "\\fI\\%N\\fR|\\fI\\%E\\fR|\\fI\\%O\\fR" in _read(MAN_PAGE)
    refused = CliRunner().invoke(cli, ["read-coils", "0", "--parity", "x", "-p", "sim://"])
    assert refused.exit_code == 2 and "'N', 'E', 'O'" in refused.output


def _shell_env(tmp_path: Path) -> dict[str, str]:
    """An environment whose PATH has an ``mbtool`` that runs this checkout."""
    wrapper = tmp_path / "mbtool"
    wrapper.write_text(f'#!/bin/sh\nexec {sys.executable} -m mbtool "$@"\n')
    wrapper.chmod(0o755)
    return {**os.environ, "PATH": f"{tmp_path}:{os.environ['PATH']}", "PYTHONPATH": str(REPO_ROOT)}


def _run_shell(argv: list[str], tmp_path: Path) -> str:
    if shutil.which(argv[0]) is None:
        pytest.skip(f"{argv[0]} is not installed (.ci/run installs it)")
    result = subprocess.run(
        argv, env=_shell_env(tmp_path), capture_output=True, text=True, timeout=30, cwd=REPO_ROOT
    )
    assert result.returncode == 0, result.stderr
    return result.stdout


def test_the_bash_script_completes_through_mbtool(tmp_path):
    """The script, sourced in bash, loads Click's, which asks the mbtool on PATH and fills COMPREPLY."""
    script = (
        f"source {BASH}\n"
        "COMP_WORDS=(mbtool read-coils --framer a); COMP_CWORD=3\n"
        "_mbtool_completion mbtool\n"
        'printf "%s\\n" "${COMPREPLY[@]}"\n'
        "COMP_WORDS=(mbtool read-coils --parity); COMP_CWORD=3\n"
        "COMPREPLY=(); _mbtool_completion mbtool\n"
        'printf "%s\\n" "${COMPREPLY[@]}"\n'
    )
    assert _run_shell(["bash", "--norc", "--noprofile", "-c", script], tmp_path).split() == [
        "ascii",
        "N",
        "E",
        "O",
    ]


def test_the_fish_script_completes_through_mbtool(tmp_path):
    script = (
        "source completions/mbtool.fish\n"
        "complete -C 'mbtool read-coils --framer a'\n"
        "complete -C 'mbtool read-coils --parity '\n"
        "complete -C 'mbtool write-registers 0 1 --order c'\n"
    )
    offered = _run_shell(["fish", "--no-config", "-c", script], tmp_path).split()
    assert sorted(offered) == sorted(["ascii", "N", "E", "O", "CDAB"])  # fish sorts what it offers


def test_the_zsh_script_completes_through_mbtool(tmp_path):
    """Autoloaded from fpath as _mbtool at the first TAB, as the README installs it: that TAB
    is completed, and later TABs go to the function it registered (compadd and compdef are
    zsh's completion builtins, stood in for by functions that print what they are given)."""
    folder = tmp_path / "zfunc"
    folder.mkdir()
    (folder / "_mbtool").write_text((REPO_ROOT / "completions" / "mbtool.zsh").read_text())
    script = (
        f"fpath=({folder} $fpath); autoload -U _mbtool\n"
        "compdef() { print -r -- compdef $@ }\n"
        "compadd() { print -r -- ${(P)${@[-1]}} }\n"
        "words=(mbtool read-coils --framer a); CURRENT=4; _mbtool\n"
        "words=(mbtool read-coils --parity ''); CURRENT=4; _mbtool_completion\n"
    )
    assert _run_shell(["zsh", "-f", "-c", script], tmp_path).splitlines() == [
        "compdef _mbtool_completion mbtool",
        "ascii",
        "N E O",
    ]


# --- (d) the check fails when the tree changes ---------------------------------------------


def _tree_with_extra_command() -> click.Group:
    extra = click.Command(
        "frobnicate-registers",
        help="Frobnicate registers (FC 99).",
        params=[
            click.Argument(["address"]),
            click.Option(["--zap-level"], type=click.Choice(["low", "high"])),
        ],
    )
    return click.Group(
        "mbtool",
        commands={**_commands(cli), "frobnicate-registers": extra},
        params=list(cli.params),
        help=cli.help,
        context_settings=dict(cli.context_settings),
    )


def test_check_reports_stale_files_when_a_command_is_added():
    outputs = gen_docs.generate(_tree_with_extra_command())
    # The completion scripts have mbtool answer at each TAB: a new command changes the man page only.
    assert gen_docs.stale(outputs, REPO_ROOT) == [MAN_PAGE]
    assert "frobnicate-registers" in outputs[MAN_PAGE].replace("\\-", "-")
    assert _has_word(outputs[MAN_PAGE].replace("\\-", "-"), "--zap-level")


def test_check_reports_a_changed_file(monkeypatch):
    outputs = gen_docs.generate(cli)
    outputs[BASH] += "# edited by hand\n"
    assert gen_docs.stale(outputs, REPO_ROOT) == [BASH]


def test_man_page_names_the_config_file_and_every_exit_status():
    from mbtool.errors import ExitCode

    page = (REPO_ROOT / "man" / "mbtool.1").read_text()
    files = page.split(".SH FILES", 1)[1].split(".SH ", 1)[0]
    assert "config.toml" in files and "MBTOOL_CONFIG" in files and "profiles.NAME" in files
    status = page.split(".SH EXIT STATUS", 1)[1].split(".SH ", 1)[0]
    for code in ExitCode:
        assert f"\\fB\\%{int(code)}\\fR" in status, code


def test_man_page_lists_every_profile_key_and_map_key():
    """The FILES section names each key the config and map loaders accept (pause, lenient,
    warn and crit were missing once)."""
    from mbtool.cli.profiles import KEYS
    from mbtool.registermap.load import DEVICE_KEYS, POINT_KEYS

    files = _man_text().split(".SH FILES", 1)[1].split(".SH ", 1)[0]
    config, register_map = files.split("MAP (", 1)
    for key in KEYS:
        assert _has_word(config, key), f"profile key {key} is not in the man page's FILES"
    for key in (*POINT_KEYS, *DEVICE_KEYS):
        assert _has_word(register_map, key), f"map key {key} is not in the man page's FILES"


def test_the_overview_shows_each_commands_summary_whole():
    """mbtool --help at 80 columns: no summary cut short with "..." (read, write, dump, diff,
    restore and check were)."""
    from click.testing import CliRunner

    overview = CliRunner().invoke(cli, ["--help"], terminal_width=80).output
    listing = " ".join(overview.split("Commands:", 1)[1].split())
    for name, command in COMMANDS.items():
        summary = " ".join(command.get_short_help_str(limit=1000).split())
        assert f"{name} {summary}" in listing, f"{name}'s summary is cut in mbtool --help"
    assert "..." not in listing


# --- (e) the README is the front door, docs/ has a page for each job ----------------------------

README = REPO_ROOT / "README.md"
DOCS_INDEX = REPO_ROOT / "docs" / "README.md"
ARCHITECTURE = REPO_ROOT / "ARCHITECTURE.md"
DOC_PAGES = sorted((REPO_ROOT / "docs").glob("*.md"))
MARKDOWN = [README, *DOC_PAGES]
SET_UP = [  # what a newcomer types first; .ci/run runs the second
    "pip install -e . && mbtool read-holding-registers 0 10 -p sim://",
    "pip install -e '.[test]' && python3 -m pytest",
]


def _prose(text: str) -> str:
    """Markdown without its fenced code blocks (a '# HELP' line in an example is no heading)."""
    return re.sub(r"^```.*?^```", "", text, flags=re.M | re.S)


def _links(path: Path) -> list[str]:
    return re.findall(r"\]\(([^)\s]+)\)", _prose(path.read_text(encoding="utf-8")))


def _linked_files(path: Path) -> set[Path]:
    return {(path.parent / link.partition("#")[0]).resolve() for link in _links(path)}


def _slug(heading: str) -> str:
    """The id GitHub gives a heading: lower case, punctuation dropped, spaces as hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    return {
        _slug(heading) for heading in re.findall(r"^#+ (.+)$", _prose(path.read_text(encoding="utf-8")), re.M)
    }


def _code_lines(path: Path) -> list[str]:
    blocks = re.findall(r"^```[^\n]*\n(.*?)^```", path.read_text(encoding="utf-8"), re.M | re.S)
    return [row for block in blocks for row in block.splitlines()]


@pytest.mark.parametrize("path", MARKDOWN, ids=lambda path: str(path.relative_to(REPO_ROOT)))
def test_every_relative_link_leads_to_a_file_and_heading_there_are(path):
    for link in _links(path):
        if re.match(r"[a-z]+:", link):
            continue  # https: and the like lead out of the repository
        name, _, anchor = link.partition("#")
        target = (path.parent / name).resolve() if name else path
        assert target.exists(), f"{path.name}: {link} leads to no file"
        if anchor and target.suffix == ".md":
            assert anchor in _anchors(target), f"{path.name}: {link}: {target.name} has no such heading"


def test_every_docs_page_is_linked_from_the_readme_or_the_docs_index():
    assert {DOCS_INDEX, ARCHITECTURE} <= _linked_files(README)
    assert ARCHITECTURE in _linked_files(DOCS_INDEX)
    linked = _linked_files(README) | _linked_files(DOCS_INDEX)
    for page in DOC_PAGES:
        assert page in linked, f"docs/{page.name} is linked from neither README.md nor docs/README.md"


def test_the_readme_is_a_front_door_with_a_table_of_contents():
    """At most ~15 KB (it had grown to 65 KB: issue 30), and its contents link every section."""
    text = README.read_text(encoding="utf-8")
    assert len(text.encode()) <= 15 * 1024, "the README is the front door: move the detail into docs/"
    contents = text.split("## Contents", 1)[1].split("\n## ", 1)[0]
    linked = set(re.findall(r"\]\(#([^)]+)\)", contents))
    for section in re.findall(r"^## (.+)$", _prose(text), re.M):
        assert section == "Contents" or _slug(section) in linked, f"the contents do not link {section!r}"


def test_the_readme_sets_up_with_its_two_commands():
    set_up = README.read_text(encoding="utf-8").split("## Set up", 1)[1].split("\n## ", 1)[0]
    (block,) = re.findall(r"^```sh\n(.*?)^```", set_up, re.M | re.S)
    assert block.splitlines() == SET_UP


def _runs_alone_on_sim(row: str) -> bool:
    """A command line against sim:// that needs no pipe, redirection, other program or
    other terminal (serve and bridge run until they are stopped)."""
    argv = shlex.split(row.removeprefix("$ "), comments=True)
    return (
        argv[:1] == ["mbtool"]
        and "sim://" in argv
        and argv[1] not in ("serve", "bridge")
        and not {"|", "<", ">", "&"} & set("".join(argv))
    )


SIM_EXAMPLES = sorted(
    {
        (str(path.relative_to(REPO_ROOT)), shlex.join(shlex.split(row.removeprefix("$ "), comments=True)))
        for path in MARKDOWN
        for row in _code_lines(path)
        if row.removeprefix("$ ").startswith("mbtool ") and _runs_alone_on_sim(row)
    }
)


@pytest.mark.parametrize("page, example", SIM_EXAMPLES, ids=[f"{page}: {row}" for page, row in SIM_EXAMPLES])
def test_the_sim_examples_run(page, example):
    """Each example the README and docs/ show against sim:// works as typed, on files the
    repository has."""
    result = run_cli(*shlex.split(example)[1:])
    assert result.returncode == 0, f"{page}: {result}"


def test_the_plant_pages_inventory_loads_where_the_page_says_to_save_it(tmp_path):
    """docs/plant.md's end-to-end inventory names its map relative to itself: the page says
    where to save it, and saved there it loads (issue 39.12: saved anywhere else it is exit 2,
    'cannot read map')."""
    from mbtool.errors import UsageError
    from mbtool.plant.inventory import load_inventory

    section = _read("docs/plant.md").split("## A plant end to end", 1)[1].split("\n## ", 1)[0]
    where = "save the inventory below as `plant.toml` in the root of mbtool's source tree"
    assert where in " ".join(section.split()), "docs/plant.md does not say where to save its inventory"
    inventory = section.split("```toml\n", 1)[1].split("```", 1)[0]
    saved = REPO_ROOT / f"plant-test-{os.getpid()}.toml"  # in the root, under a name of its own
    saved.write_text(inventory)
    try:
        plant = load_inventory(str(saved))
    finally:
        saved.unlink()
    assert [device.name for device in plant.devices] == ["meter1", "meter2", "meter9", "pump", "boiler"]
    elsewhere = tmp_path / "plant.toml"
    elsewhere.write_text(inventory)
    with pytest.raises(UsageError, match="cannot read map"):
        load_inventory(str(elsewhere))
