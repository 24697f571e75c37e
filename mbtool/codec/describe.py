"""Offline decoding: one frame, field by field, like the tables of seed 002 (spec §2, §3).

``describe(adu)`` finds the envelope (RTU, ASCII ``:``, or MBAP), checks its
CRC or LRC, decides whether the PDU is a request or a reply, and lists every
field with the bytes it came from and what they mean.  A request seen just
before (``previous``) lets a reply be checked against it: byte counts, echoes,
and the padding bits of FC01/02 that only the request's quantity can tell.
"""

from __future__ import annotations

import binascii
import struct

from mbtool.codec.checksum import crc_ok, lrc
from mbtool.codec.errors import ProtocolError, RequestError, exception_name
from mbtool.codec.pdu import ExceptionResponse, Request, function_type
from mbtool.codec.record import record


@record
class Field:
    name: str  # one token
    raw: bytes
    value: object
    text: str | None = None


@record
class Described:
    framing: str  # rtu | ascii | tcp | pdu
    adu: bytes  # the binary frame (ASCII: its bytes, unhexed)
    unit: int | None
    pdu: bytes
    kind: str  # request | response | exception | request or echo | unknown
    function: int | None
    name: str
    fields: list[Field]
    checksum_ok: bool | None  # None: no checksum (TCP)
    checksum: str  # the verdict, e.g. "CRC 0E 84 ok"
    warnings: list[str]
    error: str  # why the PDU does not decode, "" when it does
    request: Request | None = None  # the typed request, for the next frame's context


def parse_hex(text: str) -> bytes:
    """Hex bytes as a user types them: ``01 03 00 6B``, ``01036B``, ``0x01,0x03``."""
    cleaned = text.replace(",", " ").replace(":", " ").replace("-", " ")
    tokens = cleaned.split()
    out = bytearray()
    for token in tokens:
        token = token[2:] if token.lower().startswith("0x") else token
        if len(token) % 2:
            if len(tokens) > 1 and len(token) == 1:
                token = "0" + token
            else:
                raise RequestError(f"{token} is not whole bytes of hex (an odd number of digits)")
        try:
            out += binascii.unhexlify(token)
        except (binascii.Error, ValueError):
            raise RequestError(f"{token} is not hex") from None
    return bytes(out)


# --- envelopes ----------------------------------------------------------------------------


def _looks_tcp(data: bytes) -> bool:
    return len(data) >= 8 and data[2:4] == b"\x00\x00" and int.from_bytes(data[4:6], "big") == len(data) - 6


def split_frame(
    text: str, framing: str | None = None
) -> tuple[str, bytes, int | None, bytes, bool | None, str]:
    """(framing, adu, unit, pdu, checksum ok, verdict) of a frame as typed.

    Auto-detection: a leading ``:`` is ASCII; bytes whose RTU CRC checks are RTU;
    bytes with a consistent MBAP header (protocol 0, length = rest) are TCP;
    anything else is taken as RTU with a bad CRC.
    """
    stripped = text.strip()
    if framing == "ascii" or (framing is None and stripped.startswith(":")):
        body_text = stripped.lstrip(":").replace("\\r", "").replace("\\n", "").strip()
        body = parse_hex(body_text)
        if len(body) < 3:
            raise RequestError(f"ASCII frame too short: {len(body)} bytes (unit, function, LRC at least)")
        expected = lrc(body[:-1])
        ok = body[-1] == expected
        verdict = f"LRC {body[-1]:02X} ok" if ok else f"LRC {body[-1]:02X} BAD, expected {expected:02X}"
        return "ascii", body, body[0], body[1:-1], ok, verdict
    data = parse_hex(stripped)
    if framing is None:
        framing = "rtu" if crc_ok(data) or not _looks_tcp(data) else "tcp"
    if framing == "tcp":
        if len(data) < 8:
            raise RequestError(f"MBAP frame too short: {len(data)} bytes (7-byte header and a function code)")
        tid, pid, length = struct.unpack_from(">HHH", data)
        ok = pid == 0 and length == len(data) - 6
        problems = []
        if pid != 0:
            problems.append(f"protocol id {pid}, expected 0")
        if length != len(data) - 6:
            problems.append(f"length {length}, expected {len(data) - 6}")
        verdict = f"MBAP tid {tid} length {length} " + ("ok" if ok else "BAD: " + "; ".join(problems))
        return "tcp", data, data[6], data[7:], ok, verdict
    if len(data) < 4:
        raise RequestError(
            f"RTU frame too short: {len(data)} bytes (unit, function and 2 CRC bytes at least)"
        )
    from mbtool.codec.framing import crc_verdict

    return "rtu", data, data[0], data[1:-2], crc_ok(data), crc_verdict(data)


# --- field helpers ----------------------------------------------------------------------------


def _u16(pdu: bytes, at: int, name: str, text: str | None = None) -> Field:
    value = int.from_bytes(pdu[at : at + 2], "big")
    return Field(
        name, bytes(pdu[at : at + 2]), value, text if text is not None else f"{value} (0x{value:04X})"
    )


def _u8(pdu: bytes, at: int, name: str, text: str | None = None) -> Field:
    return Field(name, bytes(pdu[at : at + 1]), pdu[at], text if text is not None else str(pdu[at]))


def _registers(pdu: bytes, start: int, end: int, first: int | None, name: str = "register") -> list[Field]:
    out = []
    for i, at in enumerate(range(start, end - 1, 2)):
        label = f"{name}[{first + i if first is not None else i}]"
        out.append(_u16(pdu, at, label))
    return out


def _bit_bytes(
    pdu: bytes, start: int, end: int, first: int | None, count: int | None, what: str
) -> list[Field]:
    out = []
    for i, at in enumerate(range(start, end)):
        byte = pdu[at]
        low = 8 * i
        n = 8 if count is None else max(0, min(8, count - low))
        states = " ".join("ON" if byte >> b & 1 else "OFF" for b in range(n or 8))
        where = (
            f"{what} {first + low}-{first + low + max(n, 1) - 1}"
            if first is not None
            else f"bits {low}-{low + 7}"
        )
        out.append(Field(f"data[{i}]", bytes([byte]), byte, f"0x{byte:02X} {where}: {states}"))
    return out


def _groups_read_request(pdu: bytes) -> list[Field]:
    out = [_u8(pdu, 1, "byte_count")]
    at, g = 2, 0
    while at + 7 <= len(pdu):
        out += [
            _u8(pdu, at, f"group{g}.reference_type"),
            _u16(pdu, at + 1, f"group{g}.file", str(int.from_bytes(pdu[at + 1 : at + 3], "big"))),
            _u16(pdu, at + 3, f"group{g}.record", str(int.from_bytes(pdu[at + 3 : at + 5], "big"))),
            _u16(pdu, at + 5, f"group{g}.length", str(int.from_bytes(pdu[at + 5 : at + 7], "big"))),
        ]
        at, g = at + 7, g + 1
    return out


def _groups_write(pdu: bytes) -> list[Field]:
    out = [_u8(pdu, 1, "byte_count")]
    at, g = 2, 0
    while at + 7 <= len(pdu):
        length = int.from_bytes(pdu[at + 5 : at + 7], "big")
        out += [
            _u8(pdu, at, f"group{g}.reference_type"),
            _u16(pdu, at + 1, f"group{g}.file", str(int.from_bytes(pdu[at + 1 : at + 3], "big"))),
            _u16(pdu, at + 3, f"group{g}.record", str(int.from_bytes(pdu[at + 3 : at + 5], "big"))),
            _u16(pdu, at + 5, f"group{g}.length", str(length)),
        ]
        out += _registers(pdu, at + 7, min(len(pdu), at + 7 + 2 * length), None, f"group{g}.register")
        at, g = at + 7 + 2 * length, g + 1
    return out


def _groups_read_reply(pdu: bytes) -> list[Field]:
    out = [_u8(pdu, 1, "byte_count")]
    at, g = 2, 0
    while at + 2 <= len(pdu):
        length = pdu[at]
        out += [_u8(pdu, at, f"group{g}.length"), _u8(pdu, at + 1, f"group{g}.reference_type")]
        out += _registers(pdu, at + 2, min(len(pdu), at + 1 + length), None, f"group{g}.register")
        at, g = at + 1 + max(length, 1), g + 1
    return out


# --- requests ------------------------------------------------------------------------------


def request_fields(pdu: bytes) -> list[Field]:
    """The fields after the function code of a request PDU (spec §3 request column)."""
    code = pdu[0]
    if code in (0x01, 0x02, 0x03, 0x04):
        return [
            _u16(pdu, 1, "starting_address"),
            _u16(pdu, 3, "quantity", str(int.from_bytes(pdu[3:5], "big"))),
        ]
    if code == 0x05:
        value = int.from_bytes(pdu[3:5], "big")
        state = {0xFF00: "ON", 0x0000: "OFF"}.get(value, "invalid: neither FF00 nor 0000")
        return [_u16(pdu, 1, "output_address"), _u16(pdu, 3, "output_value", f"0x{value:04X} {state}")]
    if code == 0x06:
        return [_u16(pdu, 1, "register_address"), _u16(pdu, 3, "register_value")]
    if code == 0x08:
        return _diagnostics(pdu)
    if code == 0x0F:
        count = int.from_bytes(pdu[3:5], "big")
        address = int.from_bytes(pdu[1:3], "big")
        return [
            _u16(pdu, 1, "starting_address"),
            _u16(pdu, 3, "quantity", str(count)),
            _u8(pdu, 5, "byte_count"),
        ] + _bit_bytes(pdu, 6, len(pdu), address, count, "coils")
    if code == 0x10:
        address = int.from_bytes(pdu[1:3], "big")
        return [
            _u16(pdu, 1, "starting_address"),
            _u16(pdu, 3, "quantity", str(int.from_bytes(pdu[3:5], "big"))),
            _u8(pdu, 5, "byte_count"),
        ] + _registers(pdu, 6, len(pdu), address)
    if code == 0x14:
        return _groups_read_request(pdu)
    if code == 0x15:
        return _groups_write(pdu)
    if code == 0x16:
        return _mask_write(pdu)
    if code == 0x17:
        write_address = int.from_bytes(pdu[5:7], "big")
        return [
            _u16(pdu, 1, "read_starting_address"),
            _u16(pdu, 3, "quantity_to_read", str(int.from_bytes(pdu[3:5], "big"))),
            _u16(pdu, 5, "write_starting_address"),
            _u16(pdu, 7, "quantity_to_write", str(int.from_bytes(pdu[7:9], "big"))),
            _u8(pdu, 9, "write_byte_count"),
        ] + _registers(pdu, 10, len(pdu), write_address)
    if code == 0x18:
        return [_u16(pdu, 1, "fifo_pointer_address")]
    if code == 0x2B:
        from mbtool.codec.device_id import OBJECT_NAMES

        codes = {1: "basic", 2: "regular", 3: "extended", 4: "one specific object"}
        return [
            _u8(pdu, 1, "mei_type", f"0x{pdu[1]:02X} read device identification"),
            _u8(pdu, 2, "read_device_id_code", f"{pdu[2]} {codes.get(pdu[2], 'invalid')}"),
            _u8(pdu, 3, "object_id", f"0x{pdu[3]:02X} {OBJECT_NAMES.get(pdu[3], '')}".strip()),
        ]
    return []  # FC 07, 11, 12, 17: the function code is the whole request


def _diagnostics(pdu: bytes) -> list[Field]:
    from mbtool.codec.serial_line import SUB_FUNCTION_NAMES, sub_function_number

    sub = int.from_bytes(pdu[1:3], "big")
    fields = [
        _u16(
            pdu,
            1,
            "sub_function",
            f"{sub_function_number(sub)} {SUB_FUNCTION_NAMES.get(sub, 'not in the spec')}",
        )
    ]
    if len(pdu) > 3:
        data = bytes(pdu[3:])
        text = data.hex(" ").upper()
        if len(data) == 2:
            text += f" ({int.from_bytes(data, 'big')})"
        fields.append(Field("data", data, int.from_bytes(data, "big") if len(data) <= 8 else text, text))
    return fields


def _mask_write(pdu: bytes) -> list[Field]:
    and_mask = int.from_bytes(pdu[3:5], "big")
    or_mask = int.from_bytes(pdu[5:7], "big")
    return [
        _u16(pdu, 1, "reference_address"),
        _u16(pdu, 3, "and_mask", f"0x{and_mask:04X}"),
        _u16(pdu, 5, "or_mask", f"0x{or_mask:04X}"),
        Field(
            "result",
            b"",
            mask_formula(and_mask, or_mask),
            mask_formula(and_mask, or_mask),
        ),
    ]


def mask_formula(and_mask: int, or_mask: int) -> str:
    """FC22 in words: (current AND and) OR (or AND NOT and), spec §3 (not seed 002's formula)."""
    forced_on = or_mask & ~and_mask & 0xFFFF
    forced_off = ~and_mask & ~or_mask & 0xFFFF
    return (
        f"(current AND 0x{and_mask:04X}) OR (0x{or_mask:04X} AND NOT 0x{and_mask:04X})"
        f" = (current AND 0x{and_mask:04X}) OR 0x{forced_on:04X}: keeps bits 0x{and_mask:04X},"
        f" sets 0x{forced_on:04X}, clears 0x{forced_off:04X}"
    )


# --- replies ------------------------------------------------------------------------------------


def response_fields(pdu: bytes, request: Request | None = None) -> list[Field]:
    """The fields after the function code of a normal reply PDU (spec §3 response column)."""
    code = pdu[0]
    if code in (0x01, 0x02):
        count = getattr(request, "count", None)
        first = getattr(request, "address", None)
        what = "coils" if code == 0x01 else "inputs"
        return [_u8(pdu, 1, "byte_count")] + _bit_bytes(pdu, 2, len(pdu), first, count, what)
    if code in (0x03, 0x04, 0x17):
        first = getattr(request, "address", getattr(request, "read_address", None))
        return [_u8(pdu, 1, "byte_count")] + _registers(pdu, 2, len(pdu), first)
    if code in (0x05, 0x06, 0x08, 0x15, 0x16):
        return request_fields(pdu)  # an echo, or FC08's same layout
    if code == 0x07:
        status = pdu[1]
        states = " ".join(f"{b}:{'ON' if status >> b & 1 else 'OFF'}" for b in range(8))
        return [Field("status", bytes(pdu[1:2]), status, f"0x{status:02X} bits {states}")]
    if code == 0x0B:
        return [_status(pdu, 1), _u16(pdu, 3, "event_count", str(int.from_bytes(pdu[3:5], "big")))]
    if code == 0x0C:
        from mbtool.codec.serial_line import describe_event

        fields = [
            _u8(pdu, 1, "byte_count"),
            _status(pdu, 2),
            _u16(pdu, 4, "event_count", str(int.from_bytes(pdu[4:6], "big"))),
            _u16(pdu, 6, "message_count", str(int.from_bytes(pdu[6:8], "big"))),
        ]
        for i, byte in enumerate(pdu[8:]):
            fields.append(Field(f"event[{i}]", bytes([byte]), byte, f"0x{byte:02X} {describe_event(byte)}"))
        return fields
    if code in (0x0F, 0x10):
        return [
            _u16(pdu, 1, "starting_address"),
            _u16(pdu, 3, "quantity", str(int.from_bytes(pdu[3:5], "big"))),
        ]
    if code == 0x11:
        return _slave_id(pdu)
    if code == 0x14:
        return _groups_read_reply(pdu)
    if code == 0x18:
        return [
            _u16(pdu, 1, "byte_count", str(int.from_bytes(pdu[1:3], "big"))),
            _u16(pdu, 3, "fifo_count", str(int.from_bytes(pdu[3:5], "big"))),
        ] + _registers(pdu, 5, len(pdu), None, "fifo")
    if code == 0x2B:
        return _device_id(pdu)
    return []


def _status(pdu: bytes, at: int) -> Field:
    value = int.from_bytes(pdu[at : at + 2], "big")
    meaning = {0xFFFF: "busy", 0x0000: "idle"}.get(value, "neither busy (FFFF) nor idle (0000)")
    return Field("status", bytes(pdu[at : at + 2]), value, f"0x{value:04X} {meaning}")


def printable(data: bytes) -> str:
    return "".join(chr(b) if 0x20 <= b < 0x7F else "." for b in data)


# Where each Modicon field sits in the device-specific bytes (seed 002, FC17 byte tables).
_MODICON_BYTES = {
    "status_word": (0, 2),
    "page0_memory_4k": (0, 1),
    "state_ram_1k": (1, 1),
    "segments": (2, 1),
    "machine_state": (3, 2),
    "stop_code": (5, 2),
}


def _slave_id(pdu: bytes) -> list[Field]:
    from mbtool.codec.modicon import SLAVE_IDS, modicon_fields, modicon_layout

    slave_id, run = pdu[2], pdu[3]
    extra = bytes(pdu[4:])
    layout = modicon_layout(slave_id, extra)
    id_text = str(slave_id) + (f" (Modicon {SLAVE_IDS[slave_id]})" if layout else "")
    run_text = {0xFF: "ON", 0x00: "OFF"}.get(run, f"0x{run:02X}: neither 00 (OFF) nor FF (ON)")
    fields = [
        _u8(pdu, 1, "byte_count"),
        _u8(pdu, 2, "slave_id", id_text),
        _u8(pdu, 3, "run_indicator", run_text),
    ]
    if layout:
        for name, value, text in modicon_fields(layout, extra):
            at, size = _MODICON_BYTES.get(name) or (2 + 2 * int(name.removeprefix("pib_")), 2)
            fields.append(Field(name, extra[at : at + size], value, text))
    elif extra:
        fields.append(
            Field("extra", extra, extra.hex(" ").upper(), f'{extra.hex(" ").upper()} "{printable(extra)}"')
        )
    return fields


def _device_id(pdu: bytes) -> list[Field]:
    from mbtool.codec.device_id import CONFORMITY_LEVELS, object_name

    fields = [
        _u8(pdu, 1, "mei_type", f"0x{pdu[1]:02X}"),
        _u8(pdu, 2, "read_device_id_code"),
        _u8(pdu, 3, "conformity_level", f"0x{pdu[3]:02X} {CONFORMITY_LEVELS.get(pdu[3], 'unknown')}"),
        _u8(pdu, 4, "more_follows", "yes" if pdu[4] else "no"),
        _u8(pdu, 5, "next_object_id", f"0x{pdu[5]:02X}"),
        _u8(pdu, 6, "number_of_objects"),
    ]
    at = 7
    for _ in range(pdu[6]):
        object_id, length = pdu[at], pdu[at + 1]
        value = bytes(pdu[at + 2 : at + 2 + length])
        fields.append(Field(object_name(object_id), bytes(pdu[at : at + 2 + length]), text_of(value)))
        at += 2 + length
    return fields


def text_of(value: bytes) -> str:
    """An identification object as text; bytes that are not printable text as hex."""
    try:
        text = value.decode("utf-8")
    except UnicodeDecodeError:
        return value.hex(" ").upper()
    return text if text.isprintable() else value.hex(" ").upper()


def _padding_set(data: bytes, count: int) -> bool:
    """Bits past ``count`` in the last byte must be zero (spec §1)."""
    used = count % 8
    return bool(used) and len(data) == (count + 7) // 8 and data[-1] >> used != 0


# --- the whole frame ------------------------------------------------------------------------


def _try_request(pdu: bytes) -> tuple[Request | None, str]:
    from mbtool.codec.pdu import decode_request

    try:
        return decode_request(pdu), ""
    except ProtocolError as error:
        return None, str(error)


def _try_response(pdu: bytes, request: Request | None) -> tuple[object | None, str, list[str]]:
    from mbtool.codec.pdu import decode_response

    try:
        if request is not None and request.function_code == pdu[0]:
            reply = request.decode_response(pdu)
        else:
            reply = decode_response(pdu)
    except ProtocolError as error:
        return None, str(error), []
    return reply, "", list(getattr(reply, "warnings", ()))


ECHOES = frozenset({0x05, 0x06, 0x08, 0x15, 0x16})  # the reply repeats the request's layout


def describe(
    text: str,
    framing: str | None = None,
    direction: str | None = None,
    previous: Described | None = None,
) -> Described:
    """Decode one frame as typed.  ``direction``: "request", "response" or None to detect.

    Raises RequestError only for input that is not a frame at all (not hex, too short).
    """
    framing, adu, unit, pdu, ok, verdict = split_frame(text, framing)
    return describe_pdu(framing, adu, unit, pdu, ok, verdict, direction, previous)


def describe_pdu(
    framing: str,
    adu: bytes,
    unit: int | None,
    pdu: bytes,
    ok: bool | None,
    verdict: str,
    direction: str | None = None,
    previous: Described | None = None,
) -> Described:
    warnings: list[str] = []
    # What the envelope says, the same whatever the PDU turns out to be.
    envelope = {
        "framing": framing,
        "adu": adu,
        "unit": unit,
        "pdu": pdu,
        "checksum_ok": ok,
        "checksum": verdict,
    }
    if not pdu:
        return Described(
            **envelope,
            kind="unknown",
            function=None,
            name="empty PDU",
            fields=[],
            warnings=[],
            error="no function code",
        )
    code = pdu[0]
    asked = previous.request if previous is not None and previous.unit == unit else None
    if code & 0x80 and direction != "request":
        name = exception_name(pdu[1]) if len(pdu) > 1 else "?"
        fields = [
            Field("function", pdu[:1], code, f"0x{code:02X} = 0x{code & 0x7F:02X} | 0x80, an exception")
        ]
        error = ""
        if len(pdu) == 2:
            fields.append(Field("exception_code", pdu[1:2], pdu[1], f"{pdu[1]:02X} {name}"))
            ExceptionResponse.decode(pdu)
        else:
            error = f"exception response: PDU is {len(pdu)} bytes, expected 2"
        kind_type = function_type(code & 0x7F)
        title = f"exception to {kind_type.name}" if kind_type else f"exception to function {code & 0x7F:02X}"
        return Described(
            **envelope,
            kind="exception",
            function=code,
            name=title,
            fields=fields,
            warnings=warnings,
            error=error,
        )
    kind = function_type(code)
    if kind is None:
        fields = [Field("data", bytes(pdu[1:]), bytes(pdu[1:]).hex(" ").upper())] if len(pdu) > 1 else []
        return Described(
            **envelope,
            kind="unknown",
            function=code,
            name=f"function {code:02X}",
            fields=fields,
            warnings=[f"function code {code:02X} is not one the codec knows"],
            error="",
        )
    request, request_error = _try_request(pdu) if direction != "response" else (None, "not tried")
    reply, reply_error, reply_warnings = (None, "not tried", [])
    if direction != "request":
        context = asked if asked is not None and asked.function_code == code else None
        reply, reply_error, reply_warnings = _try_response(pdu, context)
    if request is not None and reply is not None:
        if code in ECHOES:
            chosen = "request or echo"
        elif asked is not None and asked.function_code == code:
            chosen = "response"  # the previous frame asked this unit for this function
        else:
            chosen = "request"
            warnings.append("could also be a response: use --response to read it as one")
    elif request is not None:
        chosen = "request"
    elif reply is not None:
        chosen = "response"
    else:
        chosen = direction or "request"
        if direction is None:
            # Neither reading holds: a reply to the request just seen, else whichever the
            # length fits (a request's length is fixed or counted by the PDU itself).
            if asked is not None and asked.function_code == code:
                chosen = "response"
            else:
                chosen = "request" if kind.request_size.of(pdu) == len(pdu) else "response"
    error = ""
    if chosen == "response":
        warnings += reply_warnings
        error = reply_error if reply is None else ""
        try:
            fields = response_fields(
                pdu, asked if asked is not None and asked.function_code == code else None
            )
        except IndexError:
            fields = []
    else:
        error = request_error if request is None else ""
        try:
            fields = request_fields(pdu)
        except IndexError:
            fields = []
        if code == 0x0F and len(pdu) > 6 and _padding_set(pdu[6:], int.from_bytes(pdu[3:5], "big")):
            warnings.append("unused high bits of the last byte are not zero")
    if error:
        shown = sum(len(f.raw) for f in fields) + 1
        if shown < len(pdu):
            rest = bytes(pdu[shown:])
            fields.append(Field("undecoded", rest, rest.hex(" ").upper()))
    head = [Field("function", pdu[:1], code, f"{code:02X} {kind.name}")]
    return Described(
        **envelope,
        kind=chosen,
        function=code,
        name=kind.name,
        fields=head + fields,
        warnings=warnings,
        error=error,
        request=request if chosen in ("request", "request or echo") else None,
    )
