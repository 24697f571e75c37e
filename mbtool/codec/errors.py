"""The protocol's errors: what the codec raises about a request or a frame.

They know nothing of a process: no exit codes, no stderr.  ``mbtool.errors``
maps each kind to an exit code in one place, the way tokio-modbus keeps its
protocol errors apart from an application's.  Two layers of failure are kept
apart (design notes): a frame that is wrong is a fault of the link, while an
exception response (spec §3) is a valid answer from the device.
"""

from __future__ import annotations

# Exception codes of spec §3, by the names the spec gives them.
EXCEPTION_NAMES = {
    0x01: "Illegal Function",
    0x02: "Illegal Data Address",
    0x03: "Illegal Data Value",
    0x04: "Server Device Failure",
    0x05: "Acknowledge",
    0x06: "Server Device Busy",
    0x07: "Negative Acknowledge",
    0x08: "Memory Parity Error",
    0x0A: "Gateway Path Unavailable",
    0x0B: "Gateway Target Failed to Respond",
}


def exception_name(code: int) -> str:
    return EXCEPTION_NAMES.get(code, "Undefined Exception Code")


def exceptions_by_code(counts) -> dict[str, int]:
    """Exceptions counted by their code, as every statistics output keys them: {"02": 3, "0B": 1}."""
    return {f"{code:02X}": n for code, n in sorted(counts.items())}


def exceptions_text(counts) -> str:
    """Exceptions counted by their code, as every statistics table shows them: "02:3,0B:1", or "0"."""
    return ",".join(f"{code}:{n}" for code, n in exceptions_by_code(counts).items()) or "0"


def function_code_text(code: int) -> str:
    """A function code as every message writes it: decimal, as the spec's tables, the README
    and --help number the functions, with the hex that a frame shows (FC 22 (0x16))."""
    return f"FC {code:02d} (0x{code:02X})"


class ProtocolError(Exception):
    """Base of the codec's errors; str() is the one line the user sees."""


class RequestError(ProtocolError, ValueError):
    """A request that breaks the spec (quantity, address, value): refused before sending."""

    def __init__(self, message: str, exception_code: int = 0x03) -> None:
        super().__init__(message)
        # What a server answers to such a request: 02 for addresses, 03 for values.
        self.exception_code = exception_code


class FrameError(ProtocolError):
    """Bytes that do not make a valid frame or PDU (checksum, framing, length, byte count)."""

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


class ModbusException(ProtocolError):
    """The device answered with an exception response (function code | 0x80, code)."""

    def __init__(self, function_code: int, exception_code: int) -> None:
        self.function_code = function_code
        self.exception_code = exception_code
        self.name = exception_name(exception_code)
        super().__init__(f"exception {exception_code:02X} {self.name} to {function_code_text(function_code)}")
