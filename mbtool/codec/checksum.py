"""The two serial-line checksums (spec §2).

CRC-16/MODBUS for RTU: init 0xFFFF, reflected polynomial 0xA001, no final xor,
sent low byte first.  LRC for ASCII: the two's complement of the 8-bit sum of
the binary bytes from the unit address through the last data byte (the colon
and CR LF are not summed, whatever seed 002's prose says).
"""

from __future__ import annotations


def _crc_table() -> tuple[int, ...]:
    """The byte-at-a-time table, built on first use (Modbus TCP never needs it)."""
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE: tuple[int, ...] = ()


def crc16(data: bytes) -> int:
    """CRC-16/MODBUS of data; crc16(b"\\x11\\x03\\x00\\x6b\\x00\\x03") == 0x8776."""
    global _CRC_TABLE
    table = _CRC_TABLE or (_CRC_TABLE := _crc_table())
    crc = 0xFFFF
    for byte in data:
        crc = (crc >> 8) ^ table[(crc ^ byte) & 0xFF]
    return crc


def crc_bytes(data: bytes) -> bytes:
    """The CRC as it goes on the wire: low byte first."""
    return crc16(data).to_bytes(2, "little")


def lrc(data: bytes) -> int:
    """LRC of the binary bytes; lrc(bytes.fromhex("0A0104A10001")) == 0x4F."""
    return -sum(data) & 0xFF
