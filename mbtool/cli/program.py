"""The main program: the command group, the commands' names, and ``main``.

Commands live in ``mbtool.cli.commands.*`` and are imported only when named, so a
one-shot read from cron pays for its own command and nothing else.  Every
error reaches ``main``, which prints one line on stderr and exits with the
code of ``errors.ExitCode``.
"""

from __future__ import annotations

import _signal  # the signal module's functions, without the IntEnums it makes (mbtool.errors)
import gc
import io
import os
import sys
from importlib import import_module

import click

from mbtool import __version__
from mbtool.cli.log import ERROR, INFO, WARNING, log, run_log_format
from mbtool.cli.parsing import QuickHelp, did_you_mean
from mbtool.cli.settings import ERRORS_AS_JSON
from mbtool.cli.sinks.json import error_json
from mbtool.errors import (
    KNOWN_ERRORS,
    STOP_SIGNALS,
    ExitCode,
    MbtoolError,
    OutputFailed,
    PartialRead,
    Verdict,
    exit_code_for,
)
from mbtool.link import register_scheme

COMPLETE_VAR = "_MBTOOL_COMPLETE"  # Click's name for it: _{PROG}_COMPLETE

# command name -> the module that defines it (as a function named like the command)
COMMANDS = {
    "read-coils": "read",
    "read-discrete-inputs": "read",
    "read-holding-registers": "read",
    "read-input-registers": "read",
    "read": "read",
    "write-coil": "write",
    "write-register": "write",
    "write-coils": "write",
    "write-registers": "write",
    "write": "write",
    "write-bit": "write",
    "read-exception-status": "functions",
    "diag": "diagnostics",
    "event-counter": "functions",
    "event-log": "functions",
    "report-id": "functions",
    "read-file-record": "functions",
    "write-file-record": "functions",
    "mask-write-register": "functions",
    "read-write-registers": "functions",
    "fifo": "functions",
    "device-id": "functions",
    "scan": "scan",
    "ping": "ping",
    "monitor": "monitor",
    "raw": "offline",
    "decode": "offline",
    "crc": "offline",
    "lrc": "offline",
    "serve": "serve",
    "bridge": "bridge",
    "check": "check",
    "dump": "dump",
    "diff": "snapshot",
    "restore": "snapshot",
    "poll": "poll",
    "exporter": "exporter",
    "inventory": "inventory",
    "sunspec": "sunspec",
    "maps": "library",
    "identify": "library",
}


def register_schemes() -> None:
    """The master side knows no device: sim:// reaches the simulated one through this.
    Done by ``main`` (not on import), so importing the CLI changes nothing."""
    register_scheme("sim", _open_sim)


def _open_sim(framer_name: str):
    from mbtool.device.sim import SimTransport  # noqa: PLC0415 - the device loads only when sim:// is used

    return SimTransport(framer_name)


def _show_version(ctx: click.Context, param: click.Parameter, value: bool) -> None:
    # Not click.version_option: it runs gettext (and imports locale) on every start.
    if value and not ctx.resilient_parsing:
        click.echo(f"mbtool {__version__}")
        ctx.exit()


class LazyGroup(QuickHelp, click.Group):
    def list_commands(self, ctx):
        return list(COMMANDS)

    def parse_args(self, ctx, args):
        # `mbtool -p sim:// read-coils 0`: the group has no connection options; say where they go.
        command = next((arg for arg in args if arg in COMMANDS), None)
        if command is not None:
            before = args[: args.index(command)]
            own = {name for param in self.get_params(ctx) for name in param.opts}  # -h, -V
            if any(arg.startswith("-") and arg not in own for arg in before):
                fixed = " ".join(["mbtool", command, *args[args.index(command) + 1 :], *before])
                raise click.UsageError(f"options follow the command: {fixed}", ctx)
        return super().parse_args(ctx, args)

    def resolve_command(self, ctx, args):
        name = args[0] if args else ""
        if name and not name.startswith("-") and name not in COMMANDS:
            import difflib  # noqa: PLC0415 - 0.8 ms: a mistyped command only

            close = difflib.get_close_matches(name, COMMANDS, n=3, cutoff=0.6)
            raise click.UsageError(f"no such command {name}{did_you_mean(close)}", ctx)
        return super().resolve_command(ctx, args)

    def format_commands(self, ctx, formatter):
        # Each command's summary whole, wrapped in its column: Click cuts it to the width
        # left on one line ("Read by a device manual's reference, or a...").
        rows = [(name, self.get_command(ctx, name).get_short_help_str(limit=1000)) for name in COMMANDS]
        with formatter.section("Commands"):
            formatter.write_dl(rows)

    def get_command(self, ctx, name):
        module = COMMANDS.get(name)
        if module is None:
            return None
        return getattr(import_module(f"mbtool.cli.commands.{module}"), name.replace("-", "_"))


@click.group(
    cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100}
)
@click.option(
    "-V",
    "--version",
    is_flag=True,
    expose_value=False,
    is_eager=True,
    callback=_show_version,
    help="Show the version and exit.",
)
def cli() -> None:
    """A Modbus master for the command line: RTU, ASCII and TCP, every function code,
    and the frames on the wire shown as they are.

    Try it without hardware: mbtool read-holding-registers 0 10 -p sim://

    Exit codes: 0 ok, 1 internal error, 2 bad input (nothing sent), 3 no response,
    4 Modbus exception, 5 invalid response, 6 cannot open or connect, 7 cannot write the
    output (disk full), 8 partial (some of a map's points, a dump cut short), 130 interrupted, 141 the
    reader of stdout went away (or stdout closed). check exits with its plugin state, 0-3.
    """


# --- the one way out ---------------------------------------------------------------------


def _terminate(signum, frame):
    raise KeyboardInterrupt


def main(argv: list[str] | None = None) -> None:
    """Run the CLI; every outcome leaves through one exit code and at most one stderr line."""
    # What start-up built (click, the codec's classes) lives until exit.  Frozen (Python's
    # gc.freeze), the cyclic collector never walks it again, during the run or at exit:
    # a one-shot read ends about 6 ms sooner (bench/oneshot.py).  The script imported all
    # this with the collector off (mbtool.__main__.run): on again for the run.
    gc.freeze()
    gc.enable()
    register_schemes()  # before completion, which offers sim:// too
    if COMPLETE_VAR in os.environ:  # the shell asks for completions (completions/, Click's scripts)
        from click.shell_completion import shell_complete  # noqa: PLC0415 - TAB only, 0.5 ms

        sys.exit(shell_complete(cli, {}, "mbtool", COMPLETE_VAR, os.environ[COMPLETE_VAR]))
    for stop in STOP_SIGNALS:  # SIGINT is Python's KeyboardInterrupt already
        if stop != _signal.SIGINT and _signal.getsignal(stop) != _signal.SIG_IGN:
            _signal.signal(stop, _terminate)
    if sys.stdout is None:
        _closed_stdout_as_a_gone_reader()
    if sys.stderr is None:
        _closed_stderr_as_nowhere()
    elif sys.stderr is sys.__stderr__:  # fd 2 itself, not a test's capture of it
        _stderr_that_cannot_fail()
    error: BaseException | Verdict | None = None
    meta: dict = {}  # the run's click context's: what the options noted as they were parsed
    try:
        # Not cli.main: it turns a closed pipe into exit 1 before any handler here sees it.
        with cli.make_context("mbtool", sys.argv[1:] if argv is None else list(argv)) as ctx:
            meta = ctx.meta
            ended = cli.invoke(ctx)
        if isinstance(ended, Verdict):  # a run's end: its line after what it wrote to stdout
            error, code = _flushed(ended, ended.exit_code)
        else:
            sys.stdout.flush()  # here, where a full disk is still ours to report
            code = ExitCode.OK
    except click.exceptions.Exit as done:  # --help, --version
        error, code = _flushed(None, done.exit_code)
    except click.ClickException as failure:  # usage errors: nothing was sent
        hint = ""
        if isinstance(failure, click.UsageError) and failure.ctx is not None:
            hint = f" (see '{failure.ctx.command_path} --help')"
        error = MbtoolError(f"{failure.format_message()}{hint}")
        code = ExitCode.USAGE
    except (KeyboardInterrupt, click.exceptions.Abort):
        log(WARNING, "interrupted", run_log_format(meta))
        code = ExitCode.INTERRUPTED
    except BrokenPipeError:
        # The reader went away (| head): stop at once and quietly, with the status a shell
        # gives a program that SIGPIPE ended (SIGPIPE itself would also end us on sockets).
        discard_stdout()
        code = ExitCode.READER_GONE
    except OSError as failure:  # what reaches here unconverted is stdout failing (disk full)
        discard_stdout()
        error = OutputFailed("standard output", failure)
        code = error.exit_code
    except KNOWN_ERRORS as failure:
        if isinstance(failure, OutputFailed):
            discard_stdout()
            error, code = failure, failure.exit_code
        else:  # what the command wrote first (dump -, diff's lines) goes before the verdict
            error, code = _flushed(failure, exit_code_for(failure))
    except Exception as failure:  # a bug: say so in one line; MBTOOL_DEBUG=1 shows the traceback
        if os.environ.get("MBTOOL_DEBUG", "0") not in ("", "0"):
            raise
        error = MbtoolError(
            f"internal error: {type(failure).__name__}: {failure} (set MBTOOL_DEBUG=1 for details)"
        )
        code = exit_code_for(failure)
    if error is not None:
        log(_level(code), str(error), run_log_format(meta), exit_code=int(code))
        if code and meta.get(ERRORS_AS_JSON) and not isinstance(error, Verdict | OutputFailed | PartialRead):
            # -o json: a script reading stdout alone gets an object for every outcome
            # (polling writes its own per poll, and a Verdict is no error object; a
            # partial read's object names the points it could not read).
            _write_quietly(error_json(str(error), int(code)) + "\n")
    sys.exit(int(code))


def _level(code: int) -> str:
    """The level of a run's last line: a run that ran fine ends with information, one that
    read some devices and not others (8) or was stopped (130) with a warning, else an error."""
    if code == ExitCode.OK:
        return INFO
    return WARNING if code in (ExitCode.PARTIAL, ExitCode.INTERRUPTED) else ERROR


def _flushed(error: BaseException | Verdict | None, code: int) -> tuple[BaseException | Verdict | None, int]:
    """The outcome once what the command wrote to stdout is out: a reader that went away or a
    full disk then ends the run as they do any write (141 quietly, 7), not at exit with a
    traceback from the interpreter's last flush."""
    try:
        sys.stdout.flush()
    except BrokenPipeError:
        discard_stdout()
        return None, ExitCode.READER_GONE
    except OSError as failure:
        discard_stdout()
        failed = OutputFailed("standard output", failure)
        return failed, failed.exit_code
    return error, code


def _closed_stderr_as_nowhere() -> None:
    """Started with stderr closed (``2>&-``; Python then has no sys.stderr, and print(file=None)
    writes to stdout): /dev/null takes its place, so warnings, events and statistics go
    nowhere, never into stdout's data nor a crash, and fd 2 is taken: no socket or file
    opened later becomes stderr."""
    null = os.open(os.devnull, os.O_WRONLY)
    if null != 2:  # fd 2 is the lowest free one but when stdin or stdout is closed too
        os.dup2(null, 2)
        os.close(null)
    sys.stderr = open(2, "w", encoding="utf-8", closefd=False)


class _StderrOrNowhere(io.RawIOBase):
    """fd 2 until a write to it fails (a full disk, ``2>/dev/full``; a pipe whose reader went
    away): then /dev/null takes fd 2's place, as for a closed stderr.  A line for the human
    that cannot be shown must not end the run, nor be taken for stdout failing (141, 7)."""

    def writable(self) -> bool:
        return True

    def fileno(self) -> int:
        return 2

    def isatty(self) -> bool:
        return os.isatty(2)

    def write(self, data) -> int:
        try:
            return os.write(2, data)
        except OSError:
            _closed_stderr_as_nowhere()
            return len(data)


def _stderr_that_cannot_fail() -> None:
    """sys.stderr, as Python opened it, but over a fd 2 whose failures are nowhere."""
    sys.stderr = io.TextIOWrapper(
        io.BufferedWriter(_StderrOrNowhere()),
        encoding=sys.stderr.encoding,
        errors=sys.stderr.errors,
        line_buffering=True,
        write_through=True,
    )


def _closed_stdout_as_a_gone_reader() -> None:
    """Started with stdout closed (``>&-``; Python then has no sys.stdout): a pipe whose reader
    has gone takes its place, so a write fails as it does after ``| head`` and ends the run the
    same way (141, quietly), and fd 1 is taken: no socket or file opened later becomes stdout."""
    reader, writer = os.pipe()
    os.close(reader)
    if writer != 1:  # fd 1 is the lowest free one, so the pipe normally lands there
        os.dup2(writer, 1)
        os.close(writer)
    sys.stdout = open(1, "w", encoding="utf-8", closefd=False)


def discard_stdout() -> None:
    """Point stdout at /dev/null: what is still buffered must not fail again at exit."""
    try:
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    except (OSError, ValueError):
        pass


def _write_quietly(text: str) -> None:
    try:
        sys.stdout.write(text)
        sys.stdout.flush()
    except OSError:
        discard_stdout()
