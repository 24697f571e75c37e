"""``sim://``: the simulated device as a link the master opens in-process.

Frames go through the same device framer and handlers as ``serve``'s, with no
socket or line in between: a first command works on a machine with nothing
attached.  The CLI registers it with ``mbtool.link.register_scheme``.
"""

from __future__ import annotations

from mbtool.codec.framing import device_framer
from mbtool.device.device import Device
from mbtool.device.model import demo_model
from mbtool.link.transport import Transport


class SimTransport(Transport):
    """The built-in device, answering in-process through the same framer as a real one."""

    description = "sim://"

    def __init__(self, framer_name: str) -> None:
        self.device = Device(demo_model())
        self.framer = device_framer(framer_name)
        self._pending = bytearray()

    def write(self, data: bytes) -> None:
        self.framer.feed(data)
        while (event := self.framer.next_event()) is not None:
            self._answer(event)
        # One write is one whole frame, and the line falls silent after it: that ends a
        # request whose length the framer cannot tell (an unknown function code, a long
        # return-query-data), as t3.5 would on a real bus.
        while (event := self.framer.silence()) is not None:
            self._answer(event)

    def _answer(self, event) -> None:
        reply = self.device.answer_frame(event, self.framer)
        if reply:
            self._pending += reply

    def read(self, timeout: float) -> bytes:
        if not self._pending:
            return super().read(timeout)  # a device with nothing to say stays silent
        data = bytes(self._pending)
        self._pending.clear()
        return data
