"""The framings by name: RTU, ASCII and Modbus TCP (MBAP), the three envelopes around a PDU
(spec §2), for ``--framer`` and a target's default.

Each envelope is a module of its own (``codec/rtu.py``, ``codec/ascii.py``,
``codec/mbap.py``) on the base in ``codec/framer.py`` and the resync search in
``codec/resync.py``.  This module is their face: the base's names, the registry, and the
envelopes' names too, each envelope's module imported when a name of it is first asked for,
so a one-shot read loads only its own envelope.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from importlib import import_module

from mbtool.codec.framer import Event, Frame, Framer, Rejected

__all__ = ["FRAMERS", "Event", "Frame", "Framer", "Rejected", "device_framer", "is_broadcast", "make_framer"]


class _Framers(Mapping):
    """The framer type of each framing's name, imported on the first look-up."""

    def __getitem__(self, name: str) -> type[Framer]:
        if name == "rtu":
            from mbtool.codec.rtu import RtuFramer  # noqa: PLC0415 - an envelope loads when asked for

            return RtuFramer
        if name == "ascii":
            from mbtool.codec.ascii import AsciiFramer  # noqa: PLC0415 - an envelope loads when asked for

            return AsciiFramer
        if name == "tcp":
            from mbtool.codec.mbap import TcpFramer  # noqa: PLC0415 - an envelope loads when asked for

            return TcpFramer
        raise KeyError(name)

    def __iter__(self) -> Iterator[str]:
        return iter(("rtu", "ascii", "tcp"))

    def __len__(self) -> int:
        return 3


FRAMERS: Mapping[str, type[Framer]] = _Framers()


def is_broadcast(unit: int, framer_name: str) -> bool:
    """Unit 0 is a broadcast in RTU and ASCII framing, an address like any other in MBAP."""
    return unit == FRAMERS[framer_name].broadcast_unit


def make_framer(name: str, responses: bool = True) -> Framer:
    return FRAMERS[name](responses)


def device_framer(name: str) -> Framer:
    """The framer a device reads requests with (mbtool serve and sim://)."""
    if name == "rtu":
        from mbtool.codec.rtu import DeviceRtuFramer  # noqa: PLC0415 - an envelope loads when asked for

        return DeviceRtuFramer()
    return make_framer(name, responses=False)


# The envelopes' and the resync's names, for code that takes them from here: the module that
# defines one is imported when it is first asked for (PEP 562), as FRAMERS does.
_DEFINED_IN = {
    "RtuFramer": "rtu",
    "DeviceRtuFramer": "rtu",
    "RTU_MAX_ADU": "rtu",
    "crc_verdict": "rtu",
    "AsciiFramer": "ascii",
    "ASCII_MAX_CHARS": "ascii",
    "TcpFramer": "mbap",
    "MBAP_HEADER": "mbap",
    "FrameSearch": "resync",
    "Verdict": "resync",
    "FRAME": "resync",
    "NO_FRAME": "resync",
}


def __getattr__(name: str):
    module = _DEFINED_IN.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(import_module(f"mbtool.codec.{module}"), name)
