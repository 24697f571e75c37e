"""Exit codes and the errors that lead to them: the one place that maps one to the other.

The codec's protocol errors (``mbtool.codec.errors``) carry no exit code; the
process-level errors here (no response, cannot connect, cannot write the
output, the end of a run) carry theirs.  ``exit_code_for`` maps both.
"""

from __future__ import annotations

# The signals' numbers from the C module: the signal module makes its IntEnums when imported,
# 4M instructions a one-shot read does not need (bench/oneshot.py --instructions); they equal them.
from _signal import SIGHUP, SIGINT, SIGTERM
from collections.abc import Sequence
from enum import IntEnum
from typing import TypeVar

from mbtool.codec.errors import FrameError, ModbusException, ProtocolError, RequestError
from mbtool.words import counted


class ExitCode(IntEnum):
    OK = 0
    INTERNAL = 1  # a bug in mbtool
    USAGE = 2  # usage or bad input; nothing was sent
    TIMEOUT = 3  # no response within the timeout
    EXCEPTION = 4  # the device answered with a Modbus exception
    INVALID_RESPONSE = 5  # checksum, framing, wrong unit/function/transaction id, byte count
    CONNECTION = 6  # cannot open the port or connect
    OUTPUT = 7  # cannot write the output: disk full, a file too large, an I/O error
    PARTIAL = 8  # part of what was asked was done: some of a map's points, a dump cut short
    INTERRUPTED = 130  # Ctrl-C / SIGTERM
    READER_GONE = 141  # stdout's reader went away (| head): what a shell reports for SIGPIPE


# What interrupts a run: Ctrl-C, a service stopped, a hang-up (the terminal or the ssh
# session gone).  Each is one stop, the same for every command; one the shell left ignored
# (nohup's SIGHUP, a background job's SIGINT) stays ignored.
STOP_SIGNALS = (SIGINT, SIGTERM, SIGHUP)


class MbtoolError(Exception):
    """Base of every error mbtool raises on purpose; str() is the one line the user sees."""

    exit_code = ExitCode.INTERNAL


class UsageError(MbtoolError):
    """A mistake in what the user gave: an option, an argument, a profile, an inventory, a
    setting that does not fit the link.  Exit 2 with nothing sent, one line naming what is wrong.

    Apart from the codec's RequestError, the spec refusing a request (a quantity, an address, a
    value): the codec's handlers catch theirs (a server answers it with an exception reply),
    and must never take a user's mistake for it.  Code that stops on either names both.
    """

    exit_code = ExitCode.USAGE


class Verdict:
    """How a run that ran ended (read --interval, poll, ping, scan, monitor, dump, sunspec, diff,
    restore, a write of several points): the counts on one stderr line and the verdict in the
    exit code.  A command returns it, and cli.program.main writes
    the line after what the command wrote to stdout, and exits with the code."""

    __slots__ = ("exit_code", "message")

    def __init__(self, message: str, exit_code: ExitCode) -> None:
        self.message = message
        self.exit_code = exit_code

    def __str__(self) -> str:
        return self.message


class PartialRead(MbtoolError):
    """A read of several points that got some and not others: ``readings`` has them all, those
    the device refused with their error, for the command to show before it ends with exit 8.
    One line: why each failed, and how many were read."""

    exit_code = ExitCode.PARTIAL

    def __init__(self, readings: list, failures: Sequence[BaseException]) -> None:
        read = len(readings) - len(failures)
        super().__init__(
            "; ".join(map(str, failures)) + f"; {read} of {counted(len(readings), 'point')} read"
        )
        self.readings = readings


class NoResponse(MbtoolError):
    exit_code = ExitCode.TIMEOUT


class ConnectionFailed(MbtoolError):
    exit_code = ExitCode.CONNECTION


_E = TypeVar("_E", bound=BaseException)


def link_failure(error: _E) -> _E | ConnectionFailed:
    """An OSError that opening or using a link raised (a refused connection, a port gone) as
    the ConnectionFailed it means, exit 6, with its text; any other error as it is."""
    return ConnectionFailed(str(error)) if isinstance(error, OSError) else error


class OutputFailed(MbtoolError):
    """The output could not be written (stdout, a capture file): one line naming it and why."""

    exit_code = ExitCode.OUTPUT

    def __init__(self, where: str, error: OSError) -> None:
        super().__init__(f"cannot write to {where}: {error.strerror or error}")


# The codec's errors, by kind.  Two layers of failure (design notes): a frame that is
# wrong is the link's fault (5), an exception response is the device's answer (4).
PROTOCOL_EXIT_CODES = (
    (RequestError, ExitCode.USAGE),  # refused before sending: nothing was sent
    (FrameError, ExitCode.INVALID_RESPONSE),  # checksum, framing, ids, byte count
    (ModbusException, ExitCode.EXCEPTION),
)

# Everything mbtool raises on purpose: its message is the one line the user sees.
KNOWN_ERRORS = (MbtoolError, ProtocolError)


def exit_code_for(error: BaseException) -> ExitCode:
    """Map any error to its exit code; anything not raised on purpose is a bug."""
    if isinstance(error, MbtoolError):
        return error.exit_code
    for kind, code in PROTOCOL_EXIT_CODES:
        if isinstance(error, kind):
            return code
    if isinstance(error, KeyboardInterrupt):
        return ExitCode.INTERRUPTED
    return ExitCode.INTERNAL
