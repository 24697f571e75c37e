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


# Each framing's name and the framer type that reads it (defined where _DEFINED_IN says).
_FRAMER_TYPES = {"rtu": "RtuFramer", "ascii": "AsciiFramer", "tcp": "TcpFramer"}


class _Framers(Mapping):
    """The framer type of each framing's name, its module imported on the first look-up."""

    def __getitem__(self, name: str) -> type[Framer]:
        return _defined(_FRAMER_TYPES[name])

    def __iter__(self) -> Iterator[str]:
        return iter(_FRAMER_TYPES)

    def __len__(self) -> int:
        return len(_FRAMER_TYPES)


FRAMERS: Mapping[str, type[Framer]] = _Framers()


def is_broadcast(unit: int, framer_name: str) -> bool:
    """Unit 0 is a broadcast in RTU and ASCII framing, an address like any other in MBAP."""
    return unit == FRAMERS[framer_name].broadcast_unit


def make_framer(name: str, responses: bool = True) -> Framer:
    return FRAMERS[name](responses)


def device_framer(name: str) -> Framer:
    """The framer a device reads requests with (mbtool serve and sim://)."""
    if name == "rtu":  # a device answers a function it does not know (DeviceRtuFramer)
        return _defined("DeviceRtuFramer")()
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


def _defined(name: str):
    """One of the names above, from the module that defines it (imported now if not yet)."""
    return getattr(import_module(f"mbtool.codec.{_DEFINED_IN[name]}"), name)


def __getattr__(name: str):
    if name not in _DEFINED_IN:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return _defined(name)
