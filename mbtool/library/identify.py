"""Which device is this: the library's maps judged against what a device answers (issue 43).

``mbtool identify`` asks the device what it says of itself (FC 43/14, FC 17, the SunSpec
marker; cli/commands/library.py) and then reads each map's signature (registermap/header.py)
with ``probe``: reads only, each register read once however many maps ask for it, and none
once the time budget is spent.  ``rank`` puts the maps in order with their evidence: a map
whose vendor and model the device names in FC 43/14 first (the device says what it is),
then those whose every probe fits, by how much their probes say (a model code more than a
value in a range, that more than a register that merely answers); maps that fit in part
after them, said to be partial.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from mbtool.codec.data_access import ReadCoils, ReadDiscreteInputs, ReadHoldingRegisters, ReadInputRegisters
from mbtool.codec.errors import FrameError, ModbusException, exception_name
from mbtool.codec.record import record
from mbtool.codec.values import decode_values
from mbtool.errors import NoResponse
from mbtool.registermap.header import DeviceHeader, Probe

READS = {
    "coils": ReadCoils,
    "discrete": ReadDiscreteInputs,
    "input": ReadInputRegisters,
    "holding": ReadHoldingRegisters,
}
IDENTITY_WEIGHT = 10  # the device naming its vendor and model outweighs any signature


class BudgetSpent(Exception):
    """The time budget ran out before this read."""


@record
class Answer:
    """What a read of some registers (or a bit) gave: what they hold, an exception reply, or
    nothing (no reply, or not read: the budget was spent).  Two maps may read the same
    registers as different types: each probe decodes them its own way."""

    held: tuple = ()
    refused: str = ""  # "exception 02 Illegal Data Address"
    missing: str = ""  # "no response", "not read: time budget spent"

    def value_for(self, point):
        if point.table.bits:
            return bool(self.held[0])
        value = decode_values(list(self.held), point.type, point.order)[0]
        return value.rstrip("\x00 ") if isinstance(value, str) else value


@record
class Candidate:
    name: str
    header: DeviceHeader
    score: int
    complete: bool  # every probe of the signature fits
    named: bool  # FC 43/14 names its vendor and model
    evidence: tuple  # lines of text
    fits: int  # probes that fit
    probes: int


def probe(
    execute: Callable, headers: dict[str, DeviceHeader], deadline: float, clock=time.monotonic
) -> dict[tuple, Answer]:
    """Every signature's reads, each (table, address, size) once, before ``deadline``.
    ``execute(request)`` returns the reply, raises ModbusException for an exception reply,
    NoResponse when there is none and FrameError for a bad one (each an answer of its own);
    a link that fails raises out."""
    answers: dict[tuple, Answer] = {}
    for header in headers.values():
        for check in header.signature:
            point = check.point
            key = (point.table.name, point.address, point.size)
            if key in answers:
                continue
            if clock() >= deadline:
                answers[key] = Answer(missing="not read: time budget spent")
                continue
            answers[key] = _read(execute, point)
    return answers


def _read(execute: Callable, point) -> Answer:
    request = READS[point.table.name](point.address, point.size)
    try:
        reply = execute(request)
    except ModbusException as error:
        code = error.exception_code
        return Answer(refused=f"exception {code:02d} {exception_name(code)}")
    except NoResponse:
        return Answer(missing="no response")
    except FrameError as error:  # a garbled reply says nothing of the register: the next read may
        return Answer(missing=f"a bad reply: {error}")
    return Answer(held=tuple(reply.bits[:1] if point.table.bits else reply.registers))


def judge(check: Probe, answers: dict[tuple, Answer]) -> tuple[bool, str]:
    """Whether a probe fits what its read gave, and the evidence in words."""
    point = check.point
    answer = answers[(point.table.name, point.address, point.size)]
    if answer.missing or answer.refused:
        fits = check.judge(None, bool(answer.refused))
        return fits, f"{check.describe()}: {answer.missing or answer.refused}"
    value = answer.value_for(point)
    shown = repr(value) if isinstance(value, str) else str(value)
    return check.judge(value, False), f"{check.describe()}: {shown}"


def identity_fits(header: DeviceHeader, objects: dict[str, str]) -> bool:
    """Whether FC 43/14's objects name the map's vendor and model: VendorName holds the
    manufacturer, and ProductCode, ProductName or ModelName the model's first word."""
    vendor = objects.get("VendorName", "").lower()
    named = " ".join(objects.get(key, "") for key in ("ProductCode", "ProductName", "ModelName")).lower()
    model = header.model.split()[0].lower() if header.model else ""
    return bool(vendor and model) and header.manufacturer.lower() in vendor and model in named


def rank(
    headers: dict[str, DeviceHeader], answers: dict[tuple, Answer], objects: dict[str, str]
) -> list[Candidate]:
    """The maps that fit, best first: the one FC 43/14 names, then those whose every probe
    fits before those that fit in part, then by score."""
    out = []
    for name, header in headers.items():
        results = [judge(check, answers) for check in header.signature]
        fits = sum(1 for ok, _ in results if ok)
        score = sum(check.weight for check, (ok, _) in zip(header.signature, results, strict=True) if ok)
        evidence = [f"signature: {text}" for ok, text in results if ok]
        named = identity_fits(header, objects)
        if named:
            score += IDENTITY_WEIGHT
            shown = ", ".join(f'{key} "{objects[key]}"' for key in objects if key != "MajorMinorRevision")
            evidence.insert(0, f"FC 43/14 {shown}")
        complete = fits == len(results)
        # A partial fit is worth naming when it is most of the signature and says something
        # beyond registers that merely answer.
        if named or complete or (2 * fits > len(results) and score > fits):
            misses = [f"not: {text}" for ok, text in results if not ok]
            evidence += misses
            out.append(Candidate(name, header, score, complete, named, tuple(evidence), fits, len(results)))
    out.sort(key=lambda c: (not c.named, not c.complete, -c.score, c.name))
    return out
