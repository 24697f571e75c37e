"""Fakes for the unit tests: a clock that moves only when slept on, a link that answers from a
script, and a map read's ``execute`` answered by a simulated device in-process.
"""

from __future__ import annotations

from mbtool.codec.errors import ModbusException
from mbtool.codec.pdu import ExceptionResponse
from mbtool.link.transport import Transport


class FakeClock:
    """A monotonic clock that moves only when slept on (or when a fake link waits)."""

    def __init__(self) -> None:
        self.now = 100.0
        self.sleeps: list[float] = []

    def __call__(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps.append(seconds)
        self.now += seconds


class ScriptedLink(Transport):
    """Answers each request with the next scripted list of chunks; time passes on silence."""

    def __init__(self, clock: FakeClock, replies: list[list[bytes]], serial_line: bool = True) -> None:
        self.clock = clock
        self.replies = replies
        self.serial_line = serial_line
        self.written: list[bytes] = []
        self.pending: list[bytes] = []

    def write(self, data: bytes) -> None:
        self.written.append(data)
        self.pending = list(self.replies.pop(0)) if self.replies else []

    def read(self, timeout: float) -> bytes:
        if self.pending:
            return self.pending.pop(0)
        self.clock.now += timeout
        return b""


def device_executor(device, requests: list):
    """An ``execute`` (as a map read takes) answered by a simulated device's unit 1 in-process,
    every request recorded in ``requests``; an exception reply raises as the client's does."""

    def execute(request):
        requests.append(request)
        reply = request.decode_response(device.handle(1, request.encode()))
        if isinstance(reply, ExceptionResponse):
            raise ModbusException(reply.function_code, reply.exception_code)
        return reply

    return execute
