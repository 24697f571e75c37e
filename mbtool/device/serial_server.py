"""The server behind ``serve`` and ``bridge`` on a serial line (``mbtool.device.server`` picks it).

pyserial (a device path or a URL), frames ended by implicit length or by t3.5 of silence
(spec §2), replies sent no sooner than t3.5 after the request.  One master, so one request
at a time: each is answered before the line is read again.  Requests cannot be left unread
on a line, so a request that finds ``OUT_LIMIT`` bytes of replies held back by --delay is
dropped.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from functools import partial

from mbtool.codec.framing import Frame, Rejected, device_framer
from mbtool.codec.timing import silent_interval
from mbtool.device.serving import OUT_LIMIT, TICK, ServerParts, Serving
from mbtool.errors import ConnectionFailed, NoResponse
from mbtool.link.transport import SerialSettings, SerialTransport

# On a serial line t3.5 ends a frame (spec §2), but ptys and USB adapters deliver bytes in
# bursts with pauses of several ms inside one frame; a frame whose length is known never
# waits for it, so only an unknown function code or a broken frame pays this.
MIN_SERIAL_GAP = 0.01


class SerialServer(Serving):
    """Serves as a slave on the serial line ``target.path``, opened with ``settings``."""

    def __init__(
        self,
        parts: ServerParts,
        settings: SerialSettings,
    ) -> None:
        super().__init__(parts)
        self.settings = settings
        self.transport: SerialTransport | None = None  # once open
        self.framer = device_framer(parts.framer_name)
        self._held = 0  # bytes of replies waiting in _pending (--delay)

    def open(self) -> None:
        """Open the serial line; ConnectionFailed (exit 6) if it cannot be."""
        settings = self.settings
        self.transport = SerialTransport(self.target.path, settings)
        self.stats.listening = f"{self.target.path} {settings}"
        self.stats.clients = 1

    def _serve(self) -> None:
        t35 = silent_interval(self.settings.baud, self.settings.char_bits)
        gap = max(t35, MIN_SERIAL_GAP) if self.framer_name == "rtu" else 1.0  # ASCII: 1 s between chars (§2)
        last_rx = 0.0
        peer = self.target.path
        transport = self.transport
        assert transport is not None  # open() opened it
        while not self._stop:
            waiting = self.framer.buffered > 0
            try:
                data = transport.read(self._wait(min(gap, TICK) if waiting else TICK))
            except NoResponse as lost:  # the port went away (USB adapter unplugged)
                raise ConnectionFailed(f"lost the serial line: {lost}") from None
            now = time.monotonic()
            if data:
                last_rx = now
                self.framer.feed(data)
                events = self._drain(self.framer.next_event)
            elif waiting and now - last_rx >= gap:
                events = self._drain(self.framer.silence)
            else:
                events = []
            for event in events:
                if self._held >= OUT_LIMIT and isinstance(event, Frame):
                    why = "request dropped: replies held back by --delay fill the output limit"
                    self.stats.dropped += 1
                    self.stats.frame("--", peer, event.adu, why)
                    self._log("drop", peer, event.adu, why)
                    continue
                reply = self.responder.answer(event, self.framer, peer)
                if reply:
                    # Keep the line quiet for t3.5 after the request before answering (spec §2).
                    due = max(now, last_rx + t35) + self.faults.delay
                    self._held += len(reply)
                    self._later(due, partial(self._write, reply))
            self._send_due()
            self._tick()

    def _drain(self, first: Callable[[], Frame | Rejected | None]) -> list[Frame | Rejected]:
        events = []
        event = first()
        while event is not None:
            events.append(event)
            event = self.framer.next_event()
        return events

    def _write(self, data: bytes) -> None:
        self._held -= len(data)
        assert self.transport is not None  # open() opened it
        self.transport.write(data)

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
