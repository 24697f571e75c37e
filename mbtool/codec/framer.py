"""What every envelope around a PDU shares (spec §2): the framer's buffer and event loop.

Sans-IO, after h11: ``feed(data)`` whatever arrived, then call
``next_event()`` until it returns None (more bytes needed).  An event is a
``Frame`` or a ``Rejected`` run of bytes with the reason it is not a frame, so
the caller can trace garbage and explain a failure instead of only timing out.
A framer reads either replies (a master) or requests (a device): the implicit
length of a PDU depends on which.

The framers differ only in their envelope (tokio-modbus ``frame/{rtu,tcp}.rs``):
``codec/rtu.py``, ``codec/ascii.py`` and ``codec/mbap.py``; ``codec/framing.py`` finds
them by name.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import TYPE_CHECKING, NamedTuple

from mbtool.codec.errors import ChecksumError, FrameError
from mbtool.codec.pdu import Request, pdu_length
from mbtool.codec.record import record


class Frame(NamedTuple):
    """A frame as it came, its envelope taken off.  A named tuple, not a record: a polling
    loop makes one a transaction, and a tuple is made and read in C."""

    unit: int
    pdu: bytes
    adu: bytes  # the exact bytes on the wire
    transaction_id: int | None = None


class Prediction:
    """The reply to a request if it answers as asked, as far as it is known before it comes
    (``Framer.predict``): the same for every attempt of the request, never changed.  Slots, as
    exchange.Prepared's: a named tuple's fields are read the generic way, and a poll reads two."""

    __slots__ = ("repeated", "head", "size", "pdu_at")

    def __init__(self, repeated: int, head: bytes, size: int, pdu_at: int) -> None:
        self.repeated = repeated  # its first bytes are the request's own: MBAP's transaction id (2)
        self.head = head  # then these: the rest of its envelope and its PDU's first bytes
        self.size = size  # the whole reply's
        self.pdu_at = pdu_at  # where its PDU starts


@record
class Rejected:
    data: bytes
    error: FrameError


Event = Frame | Rejected


class Framer(ABC):
    """What every framer shares: the buffer, the garbage run and the event loop."""

    name = ""
    checksum_name = ""
    # The unit id every device on a serial line hears and none answers (spec §2).
    broadcast_unit: int | None = 0

    def __init__(self, responses: bool = True) -> None:
        self.responses = responses  # reading replies (a master) or requests (a device)
        self.expect: Request | None = None  # the request being answered, for lengths that depend on it
        self.expect_unit: int | None = None  # and the unit it went to
        self._buffer = bytearray()
        self._garbage = bytearray()
        self._garbage_error: FrameError | None = None

    # -- input -------------------------------------------------------------------

    def feed(self, data: bytes) -> None:
        self._buffer += data

    def reset(self) -> None:
        self._buffer.clear()
        self._garbage.clear()
        self._garbage_error = None

    @property
    def buffered(self) -> int:
        return len(self._buffer) + len(self._garbage)

    # True when only a pause on the line can end the frame in the buffer: RTU's property,
    # for a PDU of unknown length; a frame with a start and an end (ASCII, MBAP) never waits,
    # and ``pauses_end_frames`` says so once (the client asks the property only where it may be
    # True: a class attribute read on an instance is read the generic way, every pass).
    pauses_end_frames = False
    if TYPE_CHECKING:  # RTU's is a property: to the checker, every framer's is

        @property
        def waiting_for_silence(self) -> bool: ...

    else:
        waiting_for_silence = False

    def next_event(self) -> Event | None:
        while True:
            result = self._parse()
            if result is None:
                # Out of bytes: hand over the garbage so far, so the caller sees it now.
                return self._flush_garbage()
            if isinstance(result, Frame):
                if self._garbage:  # the garbage before the frame first; it is found again next call
                    return self._flush_garbage()
                del self._buffer[: len(result.adu)]
                return result
            # An int: this many bytes at the front are no frame; fold them into the garbage run.
            skip, error = result
            if not self._garbage:
                self._garbage_error = error
            self._garbage += self._buffer[:skip]
            del self._buffer[:skip]

    def silence(self) -> Event | None:
        """The line has gone quiet (or the deadline passed): end whatever is buffered."""
        event = self.next_event()
        if event is not None:
            return event
        while self._buffer:
            frame = self._whole(bytes(self._buffer))
            if isinstance(frame, Frame):
                self._buffer.clear()
                return self._flush_garbage() or frame
            # The front byte starts no frame that ends here: drop it and look again,
            # since a whole frame may still sit behind it.
            if not self._garbage:
                self._garbage_error = frame
            self._garbage.append(self._buffer.pop(0))
            event = self.next_event()
            if event is not None:
                return event
        return self._flush_garbage()

    # -- for subclasses --------------------------------------------------------------

    @abstractmethod
    def _parse(self) -> Frame | tuple[int, FrameError] | None:
        """Look at the front of the buffer: a Frame, (bytes to skip, why), or None for more."""

    def _whole(self, data: bytes) -> Frame | FrameError:
        """After silence: the buffered bytes taken as one frame, or why they are not one."""
        return FrameError(f"truncated frame ({len(data)} bytes)", data)

    @abstractmethod
    def build(self, unit: int, pdu: bytes, transaction_id: int = 0) -> bytes: ...

    @abstractmethod
    def check(self, adu: bytes) -> str:
        """A short verdict on the frame's checksum, for the hex trace."""

    # -- what is the same for every attempt of a request -------------------------------

    def frames(self, unit: int, pdu: bytes) -> Callable[[int], bytes]:
        """The request's frame for each attempt's transaction id, built once a request: a
        polling loop sends the same one again and again.  Here the frame carries no transaction
        id (RTU, ASCII), so every attempt's is the same bytes."""
        adu = self.build(unit, pdu)
        return lambda transaction_id: adu

    def predict(self, unit: int, prefix: tuple[bytes, int] | None) -> Prediction | None:
        """The reply to a request to ``unit`` if it answers as asked, as far as it is known
        before it comes; None when nothing is.  ``prefix`` is the request's reply_prefix (the
        first bytes of its PDU and its length; None: unknown).  A read that is exactly such a
        reply needs no parse (MBAP: one a poll); RTU and ASCII predict nothing, as their
        checksum is to be checked."""
        return None

    # -- helpers ---------------------------------------------------------------------

    def _flush_garbage(self) -> Rejected | None:
        if not self._garbage:
            return None
        data = bytes(self._garbage)
        error = self._garbage_error or FrameError(f"{len(data)} bytes of garbage", data)
        if len(data) > len(error.data) and not isinstance(error, ChecksumError):
            error = FrameError(f"{len(data)} bytes of garbage, starting with: {error}", data)
        self._garbage.clear()
        self._garbage_error = None
        return Rejected(data, error)

    def _pdu_length(self, pdu: bytes) -> int | None:
        return pdu_length(pdu, self.responses, self.expect)
