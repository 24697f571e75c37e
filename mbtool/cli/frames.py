"""Frames as mbtool shows them: a decoded frame as a Report (what decode, raw, --dry-run and
monitor print for one frame), a frame in one line, and the --hex trace."""

from __future__ import annotations

import sys
from collections.abc import Callable
from typing import TextIO

from mbtool.cli.results import Report, Row
from mbtool.codec.errors import ChecksumError, FrameError, function_code_text
from mbtool.codec.framing import Framer

SUMMARY_FIELDS = 8  # decoded fields shown on one line before "..."


def one_line(described) -> str:
    """A decoded frame in one line, as monitor and bridge show it: its name and the first
    fields after the function code."""
    fields = [f for f in described.fields if f.name != "function"]
    parts = [f"{f.name}={_shown(f)}" for f in fields]
    if len(parts) > SUMMARY_FIELDS:
        parts = parts[:SUMMARY_FIELDS] + [f"... ({len(fields) - SUMMARY_FIELDS} more)"]
    text = described.name + (": " + " ".join(parts) if parts else "")
    if described.error:
        text += f" (invalid: {described.error})"
    return text


def _shown(field) -> str:
    """A field as decode shows it where its words say more than its number (coils as ON/OFF,
    an exception by name); a plain number stays a number."""
    number = str(field.value)
    if isinstance(field.value, int) and (
        field.text in (None, number) or field.text.startswith(f"{number} (0x")
    ):
        return number
    return field.text or number


def frame_report(described, header: bool = True):
    """The rows of a decoded frame: envelope, fields, checksum, warnings; JSON with every field."""
    d = described
    # The exact bytes first, to copy into a manual or a tester: hex for RTU and MBAP, the
    # text line for ASCII (its CR LF left to the line's end).
    frame = ":" + d.adu.hex().upper() + "\r\n" if d.framing == "ascii" else d.adu.hex(" ").upper()
    rows = [Row("raw", frame, frame.rstrip("\r\n")), Row("frame", f"{d.framing} {d.kind}")]
    if d.framing == "tcp":
        adu = d.adu
        rows += [
            Row("transaction_id", int.from_bytes(adu[0:2], "big"), raw=adu[0:2]),
            Row("protocol_id", int.from_bytes(adu[2:4], "big"), raw=adu[2:4]),
            Row("length", int.from_bytes(adu[4:6], "big"), raw=adu[4:6]),
            Row("unit_id", d.unit, raw=adu[6:7]),
        ]
    else:
        rows.append(Row("slave_address", d.unit, raw=d.adu[0:1]))
    rows += [Row(f.name, f.value, f.text, f.raw) for f in d.fields]
    verdict = d.checksum.split(" ", 1)[1]  # "CRC 0E 84 ok" -> the row is named crc already
    if d.framing == "rtu":
        rows.append(Row("crc", d.checksum_ok, verdict, d.adu[-2:]))
    elif d.framing == "ascii":
        rows.append(Row("lrc", d.checksum_ok, verdict, d.adu[-1:]))
    else:
        rows.append(Row("mbap", d.checksum_ok, verdict))
    rows += [Row("warning", text) for text in d.warnings]
    if d.error:
        rows.append(Row("error", d.error))
    data = {
        "framing": d.framing,
        "kind": d.kind,
        "raw": frame,
        "frame": frame,
        "checksum": {"ok": d.checksum_ok, "verdict": d.checksum},
        "fields": [
            {
                "name": r.name,
                "bytes": None if r.raw is None else r.raw.hex(" ").upper(),
                "value": r.value,
                "text": r.shown,
            }
            for r in rows
        ],
        "warnings": d.warnings,
        "error": d.error or None,
    }
    title = f"[bold]{d.framing.upper()} {d.kind}[/]: {d.name}"
    if d.function is not None:
        title += f" · {function_code_text(d.function & 0x7F)}"
    if d.unit is not None:
        title += f" · unit {d.unit}"
    return Report(d.unit, d.function, d.name, rows, data, title=title, header=header)


class HexTrace:
    """``--hex``: every frame sent and received, in hex on stderr, its checksum judged."""

    def __init__(
        self, framer: Framer, out: TextIO | None = None, label: Callable[[], str] | None = None
    ) -> None:
        self.framer = framer
        self.out = out or sys.stderr
        self.label = label  # whose frames these are, asked at each line (poll: `bus1 meter1`)

    def sent(self, adu: bytes) -> None:
        self._line("TX", adu, self.framer.check(adu))

    def received(self, adu: bytes, note: str = "") -> None:
        verdict = self.framer.check(adu)
        self._line("RX", adu, f"{verdict}; {note}" if note else verdict)

    def rejected(self, data: bytes, error: FrameError) -> None:
        # A whole frame with a bad checksum is judged like any frame; other bytes say why not.
        verdict = self.framer.check(data) if isinstance(error, ChecksumError) else f"rejected: {error}"
        self._line("RX", data, verdict)

    def _line(self, direction: str, data: bytes, verdict: str) -> None:
        whose = f"[{self.label()}] " if self.label else ""
        self.out.write(f"{whose}{direction} {shown_frame(data)}  {verdict}\n")
        self.out.flush()


def shown_frame(data: bytes) -> str:
    """A frame as the traces show it: hex pairs, or an ASCII frame's own text."""
    return data.hex(" ").upper() if not data.startswith(b":") else data.decode("ascii", "replace").strip()
