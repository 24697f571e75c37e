"""Plans of several writes, sent in turn -- ``write -m``'s points, ``restore``'s runs -- and
what the user learns of them: each item written (confirmed, where it was read back), the
one that failed, and those not sent, on stdout as lines, a table, JSON or CSV (issue 28
§2, issue 29 item 15).  The one place for that rule, for both commands.

The first write that fails stops the plan: nothing is sent after it.  The writes were
planned together, against the device as it was (restore reads it first); a device that
refuses one, or stops answering, gives no reason to think the next would land as planned,
and a plant is better left in a state the report names than in whatever mixture pressing
on would make.  What was stopped can be finished by running the command again (restore
writes only what still differs).

The exit code is the failure's own (errors.exit_code_for): 4 an exception reply, 3 no
response or the connection closed, 5 an invalid reply, 6 a link that cannot send, 130
Ctrl-C.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from mbtool.cli.results import Listing, change_parts, value_text
from mbtool.cli.sinks import default_format, render
from mbtool.cli.sinks.table import write_items
from mbtool.codec.errors import ModbusException
from mbtool.codec.record import record
from mbtool.errors import KNOWN_ERRORS, Verdict, exit_code_for

# An item's fate.  One word each, so a script can split a plain line at its first space.
CONFIRMED = "confirmed"  # written, and read back as written
DIFFERS = "differs"  # written, and read back as something else
WRITTEN = "written"  # the device acknowledged it (not read back)
SENT = "sent"  # broadcast: sent, and no device confirms
REFUSED = "refused"  # the device answered with an exception: it did not write it
FAILED = "failed"  # no valid reply: it may or may not have been written
NOT_SENT = "not-sent"  # after the failure: never sent
DONE = (CONFIRMED, DIFFERS, WRITTEN, SENT)


@record
class Step:
    """One request of a plan (with --rmw, a read and a write) and what it writes.

    ``items`` name what is written as diff names it: a dict with table, address and ref,
    and a map's point's name and unit; ``new`` its value, ``old`` what the device held
    (when it was read; None where it had nothing).  Their ``status`` is set as the plan runs.
    """

    label: str  # what the failure line names: "b (40502)", "holding 10-19"
    items: tuple[dict, ...]
    work: Any = None  # what the command's send needs of it: a request, or more (its own shape)


@record
class Outcome:
    steps: tuple[Step, ...]
    done: int  # the steps acknowledged (sent, when broadcast) before the failure
    error: BaseException | None = None

    @property
    def failed(self) -> Step | None:
        return self.steps[self.done] if self.error is not None else None


def send_all(steps: Sequence[Step], send: Callable[[Step], object], broadcast: bool = False) -> Outcome:
    """Send each step in turn; the first that fails (or Ctrl-C) stops the plan.  Each item's
    status says how far it got."""
    done, error = len(steps), None
    for index, step in enumerate(steps):
        try:
            send(step)
        except (*KNOWN_ERRORS, KeyboardInterrupt) as caught:
            done, error = index, caught
            break
    for index, step in enumerate(steps):
        if index < done:
            status = SENT if broadcast else WRITTEN
        elif index == done:
            status = REFUSED if isinstance(error, ModbusException) else FAILED
        else:
            status = NOT_SENT
        for item in step.items:
            item["status"] = status
    return Outcome(tuple(steps), done, error)


def failure(command: str, outcome: Outcome, read_back: bool | None = None) -> Verdict:
    """The stderr line of a plan that failed, with the failure's own exit code: where it
    stopped, why, and how many items were written, refused or failed, and not sent.
    ``read_back``: None for a command that never reads back (write -m), else whether it did."""
    step, error = outcome.failed, outcome.error
    assert step is not None and error is not None
    why = "interrupted" if isinstance(error, KeyboardInterrupt) else str(error)
    return Verdict(
        f"{command} stopped at {step.label}: {why}; {_counts(outcome, read_back)}", exit_code_for(error)
    )


def _counts(outcome: Outcome, read_back: bool | None = None) -> str:
    """``3 written (read back and confirmed), 1 refused, 1 not sent``."""
    items = [item for step in outcome.steps for item in step.items]
    status = [item["status"] for item in items]
    parts = []
    done = sum(s in DONE for s in status)
    if status.count(SENT):
        parts.append(f"{done} sent (broadcast: no device confirms)")
    elif not done:
        parts.append("nothing written")
    else:
        note = ""
        if read_back is False:
            note = " (not read back)"
        elif read_back:
            differ = status.count(DIFFERS)
            note = f" ({differ} read back differently)" if differ else " (read back and confirmed)"
        parts.append(f"{done} written{note}")
    if status.count(REFUSED):
        parts.append(f"{status.count(REFUSED)} refused")
    failed = status.count(FAILED)
    if failed:
        them = "it" if failed == 1 else "they"
        parts.append(f"{failed} failed (no valid reply: {them} may or may not have been written)")
    if status.count(NOT_SENT):
        parts.append(f"{status.count(NOT_SENT)} not sent")
    return ", ".join(parts)


# --- the report: one line, row or object an item ---------------------------------------------


def item_line(item: dict) -> str:
    """``confirmed holding 744: 0 -> 11``, ``written setpoint (40501): 22.5 m3/h``; without a
    status (a dry run) exactly as diff prints a difference."""
    where, old, new = change_parts(item, item.get("old"), item["new"], item.get("unit", ""))
    line = f"{where}: {old} -> {new}" if "old" in item else f"{where}: {new}"
    if "reads" in item:
        line += f" (reads {change_parts(item, item['reads'], None, item.get('unit', ''))[1]})"
    return f"{item['status']} {line}" if "status" in item else line


def report(settings, items: Sequence[dict], head: dict, end: dict | None = None) -> None:
    """Print the items in the run's format (its Settings): ``head`` (unit, map, file) and
    ``end`` (error, exit_code) frame them in JSON."""
    listing = Listing(
        data=lambda: {**head, "writes": list(items), **(end or {})},
        table=lambda: (CSV_HEADER, [_cells(item) for item in items]),
        lines=lambda: [item_line(item) for item in items],
        draw=lambda: write_items(items, head),
    )
    render(listing, settings.output_format or default_format(), csv_header=settings.csv_header)


CSV_HEADER = ["status", "table", "address", "ref", "name", "old", "new", "unit"]


def _cells(item: dict) -> list:
    return [
        "" if item.get(key) is None else value_text(item[key]) if key in ("old", "new") else item[key]
        for key in CSV_HEADER
    ]
