"""The two serial-line checksums (spec §2).

CRC-16/MODBUS for RTU: init 0xFFFF, reflected polynomial 0xA001, no final xor,
sent low byte first.  LRC for ASCII: the two's complement of the 8-bit sum of
the binary bytes from the unit address through the last data byte (the colon
and CR LF are not summed, whatever seed 002's prose says).
"""

from __future__ import annotations

import struct


def _crc_tables() -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]:
    """The byte-at-a-time table, and two for a 16-bit word at a time, built on first use
    (Modbus TCP never needs them)."""
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)

    def two_bytes(crc: int) -> int:
        for _ in range(2):
            crc = (crc >> 8) ^ table[crc & 0xFF]
        return crc

    # Two steps are linear in the 16-bit register: its low and high byte can be looked up apart.
    low = tuple(two_bytes(byte) for byte in range(256))
    high = tuple(two_bytes(byte << 8) for byte in range(256))
    return tuple(table), low, high


_CRC_TABLES: tuple[tuple[int, ...], ...] = ()


def crc16(data: bytes) -> int:
    """CRC-16/MODBUS of data; crc16(b"\\x11\\x03\\x00\\x6b\\x00\\x03") == 0x8776."""
    global _CRC_TABLES
    table, low, high = _CRC_TABLES or (_CRC_TABLES := _crc_tables())
    crc = 0xFFFF
    if len(data) < 16:
        for byte in data:
            crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
        return crc
    # Two bytes per step halves the Python loop: RTU resync checks many long would-be frames.
    even = len(data) & ~1
    for word in struct.unpack_from(f"<{even // 2}H", data):
        crc ^= word
        crc = low[crc & 0xFF] ^ high[crc >> 8]
    if even < len(data):
        crc = (crc >> 8) ^ table[(crc ^ data[-1]) & 0xFF]
    return crc


def crc_ok(buffer, start: int = 0, size: int | None = None) -> bool:
    """Do the ``size`` bytes at ``start`` (all of them by default) end with their CRC, low byte
    first?  The one CRC check of every RTU reader: framers, resync, monitor, decode.
    A frame has at least 4 bytes: unit, function code, CRC (spec §2)."""
    if size is None:
        size = len(buffer) - start
    end = start + size - 2
    return (
        size >= 4
        and start + size <= len(buffer)
        and crc16(buffer[start:end]) == buffer[end] | buffer[end + 1] << 8
    )


def crc_bytes(data: bytes) -> bytes:
    """The CRC as it goes on the wire: low byte first."""
    return crc16(data).to_bytes(2, "little")


def lrc(data: bytes) -> int:
    """LRC of the binary bytes; lrc(bytes.fromhex("0A0104A10001")) == 0x4F."""
    return -sum(data) & 0xFF
