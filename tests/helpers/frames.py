"""Frames written independently of mbtool's codec (the checksums by the spec's arithmetic, an
MBAP header packed by hand), and a framer's events drained for the codec's tests.
"""

from __future__ import annotations

import socket
import struct


def crc16(data: bytes) -> bytes:
    """Modbus RTU CRC-16 (poly 0xA001, init 0xFFFF), low byte first. Independent of mbtool."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return bytes([crc & 0xFF, crc >> 8])


def lrc(data: bytes) -> int:
    return (-sum(data)) & 0xFF


def rtu(frame_wo_crc: bytes) -> bytes:
    return frame_wo_crc + crc16(frame_wo_crc)


def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    """An MBAP ADU: transaction id, protocol 0, length, unit, PDU (spec: Modbus/TCP, MBAP header)."""
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


def read_mbap(sock: socket.socket) -> tuple[int, int, bytes]:
    """(transaction id, unit, PDU) of one MBAP ADU read from ``sock``."""
    header = _read_exactly(sock, 7)
    tid, _, length, unit = struct.unpack(">HHHB", header)
    return tid, unit, _read_exactly(sock, length - 1)


def _read_exactly(sock: socket.socket, size: int) -> bytes:
    data = b""
    while len(data) < size:
        chunk = sock.recv(size - len(data))
        assert chunk, "the peer closed the connection"
        data += chunk
    return data


def ascii_frame(unit: int, pdu: bytes) -> bytes:
    """A Modbus ASCII frame: ':', the unit, PDU and LRC in hex, CR LF."""
    body = bytes([unit]) + pdu
    return b":" + (body + bytes([lrc(body)])).hex().upper().encode() + b"\r\n"


def bad_crc(frame: bytes) -> bytes:
    """An RTU frame with its CRC's last byte spoilt."""
    return frame[:-1] + bytes([frame[-1] ^ 0xFF])


def drain_events(framer) -> list:
    """Every event the framer has now."""
    events = []
    while (event := framer.next_event()) is not None:
        events.append(event)
    return events


def settle_events(framer) -> list:
    """next_event until it has nothing, then silence until it has nothing; nothing may stay buffered."""
    events = drain_events(framer)
    for _ in range(2000):
        event = framer.silence()
        if event is None:
            break
        events.append(event)
    assert framer.buffered == 0
    return events
