"""Modicon controller facts from seed 002: diagnostic-register bits and FC17 layouts (spec §4, §6).

Pure tables and functions, no I/O.  Bit numbers count from 0 = least
significant; "bit 15 is the most significant, a bit set to 1 is TRUE" (seed 002,
FC08 sub-function 02).  Where the seed's Chinese text is garbled, the entries
were checked against the seed's other copy of the same table and noted here.
"""

from __future__ import annotations

# --- FC08 sub-function 02: the diagnostic register, per controller family ----------------

DIAGNOSTIC_REGISTER_BITS: dict[str, dict[int, str]] = {
    "184/384": {
        0: "continue on error",
        1: "run light failed",
        2: "T-bus test failed",
        3: "asynchronous bus test failed",
        4: "force listen only mode",
        7: "ROM chip 0 test failed",
        8: "continuous ROM checksum test in execution",
        9: "ROM chip 1 test failed",
        10: "ROM chip 2 test failed",
        11: "ROM chip 3 test failed",
        12: "RAM chip 5000-53FF test failed",
        13: "RAM chip 6000-67FF test failed, even addresses",
        14: "RAM chip 6000-67FF test failed, odd addresses",
        15: "timer chip test failed",
    },
    # Seed 002 prints the 484 table twice; the labelled copy has typos in bits 10-11
    # ("1800-17FF", "0000-1FFF"), the unlabelled copy gives the contiguous ROM ranges.
    # Bits 12-15 are RAM chips (labelled copy; the address range 4000-43FF is RAM).
    "484": {
        0: "continue on error",
        1: "CPU test or run light failed",
        2: "parallel port failed",
        3: "asynchronous bus test failed",
        4: "timer 0 test failed",
        5: "timer 1 test failed",
        6: "timer 2 test failed",
        7: "ROM chip 0000-07FF test failed",
        8: "continuous ROM checksum test in execution",
        9: "ROM chip 0800-0FFF test failed",
        10: "ROM chip 1000-17FF test failed",
        11: "ROM chip 1800-1FFF test failed",
        12: "RAM chip 4000-40FF test failed",
        13: "RAM chip 4100-41FF test failed",
        14: "RAM chip 4200-42FF test failed",
        15: "RAM chip 4300-43FF test failed",
    },
    "584/984": {
        0: "illegal configuration",
        1: "backup checksum error in high-speed RAM",
        2: "logic checksum error",
        3: "invalid node type",
        4: "invalid traffic cop type",
        5: "CPU/solve diagnostic failed",
        6: "real-time clock failed",
        7: "watchdog timer failed: scan time over 250 ms",
        8: "no end-of-logic node, or end-of-segment count differs from the configured segments",
        9: "state RAM test failed",
        10: "start of network did not begin network",
        11: "bad order of solve table",
        12: "illegal peripheral intervention",
        13: "dim awareness flag",
        15: "peripheral port stop executed (not an error)",
    },
    "884": {
        0: "Modbus IOP overrun error flag",
        1: "Modbus option overrun error flag",
        2: "Modbus IOP failed",
        3: "Modbus option failed",
        4: "Ourbus IOP failed",
        5: "remote I/O failed",
        6: "main CPU failed",
        7: "table RAM checksum failed",
        8: "scan task exceeded its time limit (too much user logic)",
    },
}

CONTROLLERS = tuple(DIAGNOSTIC_REGISTER_BITS)


def set_bits(value: int, names: dict[int, str]) -> list[tuple[int, str]]:
    """The set bits of a 16-bit word with their names (unnamed bits say so)."""
    return [(bit, names.get(bit, "unassigned bit")) for bit in range(16) if value >> bit & 1]


def diagnostic_register_bits(value: int, controller: str) -> list[tuple[int, str]]:
    return set_bits(value, DIAGNOSTIC_REGISTER_BITS[controller])


# --- FC17: Report Slave ID layouts ---------------------------------------------------------

SLAVE_IDS = {0: "Micro 84", 1: "484", 2: "184/384", 3: "584", 8: "884", 9: "984"}  # spec §6

# 184/384 status word (bytes 3-4): bit 0 is always 0, bit 1 memory protect, bits 2-3 the model.
STATUS_184_384 = {1: "memory protect on"}

# The PIB table a 184/384 with a J347 interface appends (bytes 5-74: 35 words).
PIB_WORDS_184_384 = (
    "PIB start address",
    "controller serial number",
    "executive ID",
    "maximum output coils",
    "output coil enable table",
    "input coil / run table address",
    "number of input coils",
    "input coil enable table",
    "first latch number (multiple of 16)",
    "last latch number (multiple of 16)",
    "input register address",
    "number of input registers",
    "number of output and holding registers",
    "user logic address",
    "output coil RAM table address",
    "function inhibit mask",
    "extended function routing address",
    "data transfer routing",
    "bytes 41-42 (not named in seed 002)",
    "unused",
    "function inhibit mask",
    "A-mode history table address",
    "DX printer request table",
    "number of sequence groups",
    "sequence image table",
    "sequence RAM address",
    "number of 50XX registers",
    "50XX table address",
    "output coil RAM image address",
    "input RAM image address",
    "delayed output start group",
    "delayed output end group",
    "watchdog line",
    "latch RAM address",
    "number of delayed output groups",
)

# Machine state word (configuration word 101).  Bits 4-6 are active low (0 = ON / OK).
MACHINE_STATE_584 = {
    15: "port 1 set up",
    14: "port 2 set up",
    13: "port 1 address set",
    12: "port 2 address set",
    10: "constant sweep on",
    9: "single sweep on",
    8: "16-bit nodes (else 24-bit)",
    7: "power on",
    6: "RUN light off",
    5: "memory protect off",
    4: "battery not OK",
}
# Bits 4-6 are spelled out as the state they give (RUN light, memory protect, battery), each
# on or off: listed again by their set-bit names they read as the opposite of the line before.
STATE_SPELLED = (4, 5, 6)
# The 984 keeps the 584's bits 4-10 and adds bit 0; it has no port set-up bits.
MACHINE_STATE_984 = {
    **{bit: name for bit, name in MACHINE_STATE_584.items() if bit <= 10},
    0: "memory downsized (see configuration words 99, 100, 175)",
}

# Machine stop code (configuration word 105).  The 584's copy in seed 002 is cut short at
# bits 8 and 4; it matches the 584/984 diagnostic register bit for bit, which completes it.
STOP_CODE_584 = {
    15: "peripheral port stop (controlled stop)",
    12: "illegal peripheral intervention",
    9: "state RAM test failed",
    8: "no end of logic detected, or bad number of segments",
    7: "watchdog timer expired",
    6: "real-time clock error",
    5: "CPU diagnostic failed",
    4: "invalid traffic cop type",
    3: "invalid node type",
    2: "logic checksum error",
    1: "backup checksum error",
    0: "illegal configuration",
}
STOP_CODE_984 = {
    15: "peripheral port stop (controlled stop)",
    14: "extended memory partially failed (984A, B, X)",
    12: "illegal peripheral intervention",
    10: "start node did not start segment",
    9: "state RAM test failed",
    8: "logic check loop, or bad number of segments",
    7: "watchdog timer expired",
    6: "real-time clock error",
    5: "CPU diagnostic failed (984A, B, X); bad coil used table (other 984)",
    4: "S908 remote I/O head failure",
    3: "invalid node type",
    2: "logic checksum error",
    1: "coil disabled while in RUN mode",
    0: "illegal configuration",
}


def modicon_layout(slave_id: int, extra: bytes) -> str | None:
    """Which seed 002 layout fits this FC17 reply: "184/384", "584", "984" or None.

    The slave id alone is not enough (any device may answer 2, 3 or 9); the byte
    count must match too: 4 or 74 for the 184/384, 9 for the 584 and 984.
    """
    if slave_id == 2 and len(extra) in (2, 72):
        return "184/384"
    if slave_id in (3, 9) and len(extra) == 7:
        return "584" if slave_id == 3 else "984"
    return None


def _bit_list(value: int, names: dict[int, str]) -> str:
    found = [text for bit, text in set_bits(value, names) if bit in names]
    return ", ".join(found) if found else "none"


def modicon_fields(layout: str, extra: bytes) -> list[tuple[str, int, str]]:
    """The device-specific bytes of a Modicon FC17 reply as (name, value, meaning)."""
    if layout == "184/384":
        status = int.from_bytes(extra[0:2], "big")
        model = "384" if status >> 2 & 1 else "184"
        if status >> 3 & 1:
            model = "unknown (bit 3 set)"
        fields = [
            (
                "status_word",
                status,
                f"0x{status:04X}: model {model}, memory protect {'on' if status & 2 else 'off'}",
            ),
        ]
        for index, name in enumerate(PIB_WORDS_184_384):
            at = 2 + 2 * index
            if at + 2 > len(extra):
                break
            word = int.from_bytes(extra[at : at + 2], "big")
            fields.append((f"pib_{index:02d}", word, f"{name}: 0x{word:04X}"))
        return fields
    state = int.from_bytes(extra[3:5], "big")
    stop = int.from_bytes(extra[5:7], "big")
    state_names = MACHINE_STATE_584 if layout == "584" else MACHINE_STATE_984
    stop_names = STOP_CODE_584 if layout == "584" else STOP_CODE_984
    run_light = "off" if state >> 6 & 1 else "on"
    memory_protect = "off" if state >> 5 & 1 else "on"
    battery = "not OK" if state >> 4 & 1 else "OK"
    return [
        ("page0_memory_4k", extra[0], f"{extra[0]} x 4K words of page-0 memory"),
        ("state_ram_1k", extra[1], f"{extra[1]} x 1K words of state RAM"),
        ("segments", extra[2], f"{extra[2]} user logic segments"),
        (
            "machine_state",
            state,
            f"0x{state:04X}: RUN light {run_light}, memory protect {memory_protect}, battery {battery};"
            f" also set: {_bit_list(state, {b: n for b, n in state_names.items() if b not in STATE_SPELLED})}",
        ),
        ("stop_code", stop, f"0x{stop:04X}: {_bit_list(stop, stop_names) if stop else 'running (no stop)'}"),
    ]


# --- FC08 sub-function 21: the 54 words of Modbus Plus statistics (seed 002) -------------------


def _pair(low: str, high: str) -> str:
    return f"LO: {low}; HI: {high}"


def _bitmap_words(what: str) -> tuple[str, ...]:
    return tuple(
        _pair(f"{what}, nodes {n}-{n + 7}", f"{what}, nodes {n + 8}-{n + 15}") for n in range(1, 64, 16)
    )


def _path_words(what: str, first: int, count: int, digits: str = "d") -> tuple[str, ...]:
    def label(n: int) -> str:
        return f"{n:X}" if digits == "X" else str(n)

    return tuple(
        _pair(f"{what} {label(first + 2 * i)}", f"{what} {label(first + 2 * i + 1)}") for i in range(count)
    )


MODBUS_PLUS_WORDS: tuple[str, ...] = (
    (
        "node type ID (0 unknown, 1 PLC, 2 Modbus bridge, 3 host, 4 bridge plus, 5 peer I/O)",
        "software version in bits 0-11 (hex); bit 15 selects the meaning of word 15",
        "network address of this station",
        "MAC state (0 power up, 1 monitor offline, 2 duplicate offline, 3 idle, 4 use token,"
        " 5 work response, 6 pass token, 7 solicit response, 8 check pass, 9 claim token,"
        " 10 claim response)",
        "peer status, LED code (0 monitor link, 32 normal link, 64 never getting token,"
        " 96 sole station, 128 duplicate station)",
        "token pass counter",
        "token rotation time (ms)",
        _pair("data master failed during token ownership", "program master failed during token ownership"),
        _pair("data master token owner bitmap", "program master token owner bitmap"),
        _pair("data slave token owner bitmap", "program slave token owner bitmap"),
        _pair("not named in seed 002", "data slave / get slave command transfer request bitmap"),
        _pair(
            "program master / get master response transfer request bitmap",
            "program slave / get slave command transfer request bitmap",
        ),
        _pair("program master connect status bitmap", "program slave automatic logout request bitmap"),
        _pair("pretransmit deferral error counter", "receive buffer time-out error counter"),
        _pair("repeated command received counter", "frame error counter"),
        _pair(
            "receiver collision-abort error counter (cable A error if word 1 bit 15 is set)",
            "receiver alignment error counter (cable B error if word 1 bit 15 is set)",
        ),
        _pair("receiver CRC error counter", "bad packet-length error counter"),
        _pair("bad link-address error counter", "transmit buffer DMA-underrun error counter"),
        _pair("bad internal packet length error counter", "bad MAC function code error counter"),
        _pair("communication retry counter", "communication failed error counter"),
        _pair("good receive packet counter", "no response received error counter"),
        _pair("exception response received counter", "unexpected path error counter"),
        _pair("unexpected response error counter", "forgotten transaction error counter"),
    )
    + _bitmap_words("active station table")
    + _bitmap_words("token station table")
    + _bitmap_words("global data present table")
    + (
        _pair("receive buffer in use, buffers 1-8", "receive buffer in use, buffers 9-16"),
        _pair("receive buffer in use, buffers 17-24", "receive buffer in use, buffers 25-32"),
        _pair("receive buffer in use, buffers 33-40", "station management command initiated counter"),
    )
    + _path_words("master data output path command initiated counter, path", 1, 4)
    + _path_words("slave data input path command processed counter, path", 0x41, 4, "X")
    + _path_words("master program output path command initiated counter, path", 0x81, 4, "X")
    + _path_words("slave program input path command processed counter, path", 0xC1, 4, "X")
)


# Where each Modicon field sits in the device-specific bytes (seed 002, FC17 byte tables).
MODICON_BYTES = {
    "status_word": (0, 2),
    "page0_memory_4k": (0, 1),
    "state_ram_1k": (1, 1),
    "segments": (2, 1),
    "machine_state": (3, 2),
    "stop_code": (5, 2),
}
