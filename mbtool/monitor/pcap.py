"""Capture files of a monitored bus that Wireshark opens and decodes as Modbus unconfigured,
and read back (``monitor --from-file``) with their time stamps.

Classic libpcap format (the one every version of Wireshark and tcpdump reads),
written with struct: a 24-byte file header, then per packet a 16-byte record header
(seconds, microseconds, captured and original length) and the bytes.

The link type is LINKTYPE_WIRESHARK_UPPER_PDU (252, "exported PDU"): each packet
starts with tags naming the dissector for the bytes that follow.  We name
Wireshark's "mbrtu" (Modbus RTU) dissector, so each RTU frame is stored exactly as
it was on the wire, CRC and all, and Wireshark shows unit, function, fields, the
CRC (checked with the mbrtu.crc_verification preference) and pairs responses with
their requests, with no "Decode As" or port setting.  The alternatives were worse:
Wireshark has no link type for a serial Modbus line; RTU inside fake IPv4/UDP or TCP
on port 502 is dissected as Modbus/TCP or Modbus/UDP (MBAP), not RTU, and the
"Modbus RTU over TCP/UDP" dissector has no default port; converting frames to MBAP
would drop the CRC, the very thing a bus monitor is for.  Checked with tshark 4.0
(Debian 12): ``tshark -r FILE -T fields -e mbrtu.unit_id -e modbus.func_code``.

Garbage is stored under the "data" dissector (shown as raw bytes).  Wireshark has
no Modbus ASCII dissector, so an ASCII frame with a good LRC is stored as the RTU
frame with the same unit and PDU (the CRC computed here); an ASCII frame with a bad
LRC is stored as its text under "data", so nothing shows as valid that was not.
"""

from __future__ import annotations

import contextlib
import struct
from collections.abc import Iterator
from typing import BinaryIO

from mbtool.codec.checksum import crc_bytes
from mbtool.errors import OutputFailed

PCAP_MAGIC = 0xA1B2C3D4  # microsecond timestamps
PCAP_NANO_MAGIC = 0xA1B23C4D  # nanosecond timestamps (read, never written)
PCAPNG_MAGIC = 0x0A0D0D0A  # Wireshark's default format since 1.8 (not read)
PCAP_VERSION = (2, 4)
SNAPLEN = 65535
LINKTYPE_WIRESHARK_UPPER_PDU = 252
# Tags of the exported-PDU header (Wireshark's wsutil/exported_pdu_tlvs.h):
# a 2-byte tag, a 2-byte length, the value padded with NULs to 4 bytes.
TAG_END_OF_OPT = 0
TAG_PROTO_NAME = 12
RTU_DISSECTOR = "mbrtu"
RAW_DISSECTOR = "data"


def exported_pdu(dissector: str, payload: bytes) -> bytes:
    """``payload`` behind the tags that tell Wireshark which dissector reads it."""
    name = dissector.encode("ascii")
    padded = name + b"\0" * (-len(name) % 4)
    return (
        struct.pack(">HH", TAG_PROTO_NAME, len(padded))
        + padded
        + struct.pack(">HH", TAG_END_OF_OPT, 0)
        + payload
    )


class PcapWriter:
    """A classic pcap file that always ends on a record boundary.

    Each record goes out whole, straight to the file (no buffer), so a killed monitor
    leaves a readable file; a write that fails (a full disk, a file size limit) is cut
    back to the last whole record and reported, so what was written stays readable.
    """

    def __init__(self, file: BinaryIO, linktype: int = LINKTYPE_WIRESHARK_UPPER_PDU, name: str = "") -> None:
        self.file = file
        self.name = name or getattr(file, "name", "the capture file")
        self.whole = 0  # bytes of the file up to the end of its last whole record
        self._write(struct.pack("<IHHiIII", PCAP_MAGIC, *PCAP_VERSION, 0, 0, SNAPLEN, linktype))

    def packet(self, when: float, data: bytes) -> None:
        seconds = int(when)
        micros = min(int(round((when - seconds) * 1_000_000)), 999_999)
        self._write(struct.pack("<IIII", seconds, micros, len(data), len(data)) + data)

    def _write(self, record: bytes) -> None:
        view = memoryview(record)
        try:
            while view:
                view = view[self.file.write(view) :]
            self.file.flush()
        except OSError as error:
            with contextlib.suppress(OSError):
                self.file.truncate(self.whole)  # what was written stays readable
            raise OutputFailed(f"capture file {self.name}", error) from None
        self.whole += len(record)

    def close(self) -> None:
        self.file.close()


class BusCapture(PcapWriter):
    """What the bus monitor saw (sniffer.BusFrame records), one packet per frame or garbage run."""

    @classmethod
    def create(cls, path: str) -> BusCapture:
        # Unbuffered: a record is written whole by one write (or cut back if it cannot be).
        return cls(open(path, "wb", buffering=0), name=path)  # noqa: SIM115 - closed by close()

    def frame(self, frame) -> None:
        if frame.direction == "garbage":
            self.packet(frame.time, exported_pdu(RAW_DISSECTOR, frame.wire))
        elif frame.framing == "rtu":
            self.packet(frame.time, exported_pdu(RTU_DISSECTOR, frame.wire))
        elif frame.checksum_ok and frame.described is not None:
            body = bytes([frame.unit]) + frame.described.pdu
            self.packet(frame.time, exported_pdu(RTU_DISSECTOR, body + crc_bytes(body)))
        else:
            self.packet(frame.time, exported_pdu(RAW_DISSECTOR, frame.wire))


def _magic(data: bytes) -> tuple[str, int] | None:
    """The byte order and magic number a capture file starts with, or None for raw bytes."""
    if len(data) < 4:
        return None
    for order in "<>":
        magic = struct.unpack(order + "I", data[:4])[0]
        if magic in (PCAP_MAGIC, PCAP_NANO_MAGIC, PCAPNG_MAGIC):
            return order, magic
    return None


def is_pcap(data: bytes) -> bool:
    """Whether ``data`` starts like a capture file (classic pcap or pcapng) rather than raw bytes."""
    return _magic(data) is not None


def packets(data: bytes) -> Iterator[tuple[float, bytes]]:
    """(time stamp, bytes) of each packet of a classic pcap file, either byte order.

    Exported-PDU packets (what BusCapture writes) give the bytes behind their tags; packets
    of any other link type are taken whole.  ValueError, after the packets before it, for
    a pcapng file, a truncated header or a truncated packet.
    """
    found = _magic(data)
    if found is None:
        raise ValueError("not a pcap file")
    order, magic = found
    if magic == PCAPNG_MAGIC:
        raise ValueError("a pcapng file: save it as pcap (Wireshark: File > Export, format pcap)")
    if len(data) < 24:
        raise ValueError("not a pcap file: shorter than a pcap header")
    scale = 1e-9 if magic == PCAP_NANO_MAGIC else 1e-6
    linktype = struct.unpack_from(order + "I", data, 20)[0] & 0x0FFFFFFF  # the top bits are flags
    at, count = 24, 0
    while at < len(data):
        if at + 16 > len(data):
            raise ValueError(f"truncated after {count} packets (a capture cut short?)")
        seconds, fraction, size, _ = struct.unpack_from(order + "IIII", data, at)
        body = data[at + 16 : at + 16 + size]
        if len(body) < size:
            raise ValueError(f"truncated after {count} packets (a capture cut short?)")
        at += 16 + size
        count += 1
        yield (
            seconds + fraction * scale,
            _behind_tags(body) if linktype == LINKTYPE_WIRESHARK_UPPER_PDU else body,
        )


def _behind_tags(packet: bytes) -> bytes:
    """The payload of an exported-PDU packet: what follows its end-of-options tag."""
    at = 0
    while at + 4 <= len(packet):
        tag, length = struct.unpack_from(">HH", packet, at)
        at += 4 + length + (-length % 4)
        if tag == TAG_END_OF_OPT:
            return packet[at:]
    return b""  # no end tag: no payload
