"""The serial line's timing rules (spec §2), as arithmetic: no clocks, no I/O.

The client waits t3.5 between frames, the simulated device waits it before a
reply, and the bus monitor ends a frame at it; all three take it from here.
t1.5 (the longest gap inside a frame) is not checked: USB adapters and ptys
deliver bytes in bursts of milliseconds, so a master cannot see it.
"""

from __future__ import annotations

CHAR_BITS = (
    11  # spec §2: every RTU character is 11 bits on the line (start, 8 data, parity or 2nd stop, stop)
)
FAST_T35 = 0.00175  # spec §2: a fixed 1.75 ms above 19200 baud


def char_time(baud: int) -> float:
    """Seconds one character takes on the line."""
    return CHAR_BITS / baud


def silent_interval(baud: int) -> float:
    """t3.5, the silence that ends an RTU frame: 3.5 characters; 1.75 ms above 19200 baud."""
    return FAST_T35 if baud > 19200 else 3.5 * char_time(baud)
