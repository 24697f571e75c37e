"""Counts in words, for the lines people read: ``1 request``, ``2 requests``, ``1 entry``.

The one place for the rule (issue 39 item 21), so that no summary says ``1 requests`` or
``in 1 holding registers``.  The standard library only: every package's lines use it.
"""

from __future__ import annotations


def counted(count: int, noun: str, plural: str = "") -> str:
    """``count`` and its noun, singular for exactly one: ``counted(1, "reply", "replies")`` is
    ``1 reply``; ``plural`` defaults to the noun and an s."""
    return f"{count} {noun if count == 1 else plural or noun + 's'}"
