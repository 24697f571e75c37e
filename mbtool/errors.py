"""Exit codes and the errors that lead to them: the one place that maps one to the other.

Two layers of failure are kept apart (design notes, "Two layers of failure"):
a transport or protocol fault (timeout, checksum, framing, mismatched ids,
cannot open the port) is mbtool's problem with the link, while a Modbus
exception response is a valid answer from the device.
"""

from __future__ import annotations

from enum import IntEnum


class ExitCode(IntEnum):
    OK = 0
    INTERNAL = 1  # a bug in mbtool
    USAGE = 2  # usage or bad input; nothing was sent
    TIMEOUT = 3  # no response within the timeout
    EXCEPTION = 4  # the device answered with a Modbus exception
    INVALID_RESPONSE = 5  # checksum, framing, wrong unit/function/transaction id, byte count
    CONNECTION = 6  # cannot open the port or connect
    OUTPUT = 7  # cannot write the output: disk full, a file too large, an I/O error
    INTERRUPTED = 130  # Ctrl-C / SIGTERM
    READER_GONE = 141  # stdout's reader went away (| head): what a shell reports for SIGPIPE


class MbtoolError(Exception):
    """Base of every error mbtool raises on purpose; str() is the one line the user sees."""

    exit_code = ExitCode.INTERNAL


class RequestError(MbtoolError, ValueError):
    """A request that breaks the spec (quantity, address, value): refused before sending."""

    exit_code = ExitCode.USAGE

    def __init__(self, message: str, exception_code: int = 0x03) -> None:
        super().__init__(message)
        # What a server answers to such a request: 02 for addresses, 03 for values.
        self.exception_code = exception_code


class FrameError(MbtoolError):
    """Bytes that do not make a valid frame or PDU (checksum, framing, length, byte count)."""

    exit_code = ExitCode.INVALID_RESPONSE

    def __init__(self, message: str, data: bytes = b"") -> None:
        super().__init__(message)
        self.data = data  # the offending bytes, for the hex trace


class ChecksumError(FrameError):
    """A frame whose CRC or LRC does not match its contents."""

    def __init__(self, message: str, data: bytes, received: int, expected: int) -> None:
        super().__init__(message, data)
        self.received = received
        self.expected = expected


class DecodeError(FrameError):
    """A PDU that does not decode as its function code says it should."""


class MismatchError(FrameError):
    """A well-formed reply that answers another request (unit, function or transaction id)."""


class Summary(MbtoolError):
    """The end of a run (polling, scan, monitor): the counts on one stderr line, the verdict
    in the exit code, leaving through cli.main like every error."""

    def __init__(self, message: str, exit_code: ExitCode) -> None:
        super().__init__(message)
        self.exit_code = exit_code


class NoResponse(MbtoolError):
    exit_code = ExitCode.TIMEOUT


class ConnectionFailed(MbtoolError):
    exit_code = ExitCode.CONNECTION


class OutputFailed(MbtoolError):
    """The output could not be written (stdout, a capture file): one line naming it and why."""

    exit_code = ExitCode.OUTPUT

    def __init__(self, where: str, error: OSError) -> None:
        super().__init__(f"cannot write to {where}: {error.strerror or error}")


class ModbusException(MbtoolError):
    """The device answered with an exception response (function code | 0x80, code)."""

    exit_code = ExitCode.EXCEPTION

    def __init__(self, function_code: int, exception_code: int) -> None:
        from mbtool.codec.pdu import exception_name

        self.function_code = function_code
        self.exception_code = exception_code
        self.name = exception_name(exception_code)
        super().__init__(f"exception {exception_code:02X} {self.name} (function {function_code:02X})")


def exit_code_for(error: BaseException) -> ExitCode:
    """Map any error to its exit code; anything not raised on purpose is a bug."""
    if isinstance(error, MbtoolError):
        return error.exit_code
    if isinstance(error, KeyboardInterrupt):
        return ExitCode.INTERRUPTED
    return ExitCode.INTERNAL
