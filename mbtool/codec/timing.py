"""The serial line's timing rules (spec §2), as arithmetic: no clocks, no I/O.

The client waits t3.5 between frames, the simulated device waits it before a
reply, and the bus monitor ends a frame at it; all three take it from here.
t1.5 (the longest gap inside a frame) is not checked: USB adapters and ptys
deliver bytes in bursts of milliseconds, so a master cannot see it.
"""

from __future__ import annotations

CHAR_BITS = 11  # spec §2: an RTU character is 11 bits on the line (start, 8 data, parity or 2nd stop, stop)
FAST_T35 = 0.00175  # spec §2: a fixed 1.75 ms above 19200 baud


def character_bits(parity: str, bytesize: int, stopbits: int) -> int:
    """Bits one character takes on a line of this format: 11 as the spec has it, 10 for the
    8N1 that many devices ship (spec §2 lets the user choose)."""
    return 1 + bytesize + (parity != "N") + stopbits


def char_time(baud: int, bits: int = CHAR_BITS) -> float:
    """Seconds one character of ``bits`` takes on the line."""
    return bits / baud


def silent_interval(baud: int, bits: int = CHAR_BITS) -> float:
    """t3.5, the silence that ends an RTU frame: 3.5 characters; 1.75 ms above 19200 baud."""
    return FAST_T35 if baud > 19200 else 3.5 * char_time(baud, bits)
