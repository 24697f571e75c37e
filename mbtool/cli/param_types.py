"""The command line's parameter types: numbers in decimal or hex within their range, unit
lists, seconds, RS-485 delays, and one case rule for every choice."""

from __future__ import annotations

import click

from mbtool.codec.errors import RequestError


def parse_int(text: str, what: str = "number") -> int:
    """Decimal or 0x hex (also 0o / 0b); leading zeros are decimal, as a user means them."""
    text = text.strip()
    try:
        if text.lstrip("+-").isdigit():
            return int(text, 10)
        return int(text, 0)
    except ValueError:
        shown = text or "(empty)"
        raise RequestError(f"{what} {shown} is not a number (decimal or 0x hex)") from None


def parse_units(text: str, broadcast: bool = False) -> frozenset[int]:
    """'1', '1,17', '1-10', '1-3,17': unit ids 1..255 (0 is broadcast, which every unit hears;
    ``broadcast``: 0 may be listed, for a gateway that forwards broadcasts)."""
    units: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        if not part:
            raise RequestError(f"empty unit id in {text}")
        low_text, dash, high_text = part.partition("-")
        low = parse_int(low_text, "unit")
        high = parse_int(high_text, "unit") if dash else low
        if low > high:
            raise RequestError(f"unit range {part} runs backwards")
        lowest = 0 if broadcast else 1
        for unit in (low, high):
            if not lowest <= unit <= 255:
                why = "" if broadcast else " (unit 0 is broadcast: every unit hears it)"
                raise RequestError(f"unit {unit} is out of range {lowest}..255{why}")
        units.update(range(low, high + 1))
    return frozenset(units)


def units_text(units: frozenset[int]) -> str:
    """1,2,3,17 -> 1-3,17."""
    runs: list[list[int]] = []
    for unit in sorted(units):
        if runs and unit == runs[-1][1] + 1:
            runs[-1][1] = unit
        else:
            runs.append([unit, unit])
    return ",".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


class Number(click.ParamType):
    """An integer in decimal or hex within [low, high]."""

    name = "number"

    def __init__(self, low: int, high: int, what: str) -> None:
        self.low, self.high, self.what = low, high, what

    def convert(self, value, param, ctx):
        if isinstance(value, int):
            number = value
        else:
            try:
                number = parse_int(value, self.what)
            except RequestError as error:
                self.fail(str(error), param, ctx)
        if not self.low <= number <= self.high:
            self.fail(f"{self.what} {number} is out of range {self.low}..{self.high}", param, ctx)
        return number


ADDRESS = Number(0, 0xFFFF, "address")
COUNT = Number(0, 0xFFFF, "count")  # the spec limit is the codec's to check, per function code


class PositiveFloat(click.ParamType):
    """Seconds, more than 0; with ``zero_ok`` also 0 (poll back to back)."""

    name = "seconds"

    def __init__(self, zero_ok: bool = False) -> None:
        self.zero_ok = zero_ok

    def convert(self, value, param, ctx):
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value} is not a number of seconds", param, ctx)
        if number != number or number == float("inf") or number < 0 or (number == 0 and not self.zero_ok):
            least = "0 or more" if self.zero_ok else "more than 0"
            self.fail(f"must be {least} seconds, not {value}", param, ctx)
        return number


class Rs485Delays(click.ParamType):
    """BEFORE[,AFTER] in milliseconds, as modpoll's -4 takes them; kept in seconds."""

    name = "ms[,ms]"
    LIMIT_MS = 1000  # the kernel keeps these in milliseconds; a second is already absurd

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        parts = str(value).split(",")
        try:
            delays = [float(part) for part in parts]
        except ValueError:
            self.fail(f"{value} is not BEFORE[,AFTER] in milliseconds", param, ctx)
        if len(delays) > 2 or not all(0 <= d <= self.LIMIT_MS for d in delays):
            self.fail(f"{value}: give BEFORE[,AFTER], each 0..{self.LIMIT_MS} ms", param, ctx)
        before, after = (delays + [0.0])[:2]
        return (before / 1000, after / 1000)


class Choice(click.Choice):
    """One case rule for every choice: any case is accepted (--type FLOAT32, --order cdab,
    --framer RTU) and the listed spelling is what the command gets, what --help shows and what
    completion offers.  ``aliases`` are other words for a choice, as a field engineer says
    them (parity none, even, odd).

    The case folding is done here rather than by Click's ``case_sensitive=False``, whose
    help and completion show the choices in lower case from Click 8.2 on ([n|e|o] for a
    parity the docs write N, E, O)."""

    def __init__(self, choices, aliases: dict[str, str] | None = None) -> None:
        super().__init__(choices, case_sensitive=True)
        self.spelling = {choice.lower(): choice for choice in self.choices}
        self.spelling.update((word.lower(), choice) for word, choice in (aliases or {}).items())

    def convert(self, value, param, ctx):
        if isinstance(value, str):
            value = self.spelling.get(value.lower(), value)
        return super().convert(value, param, ctx)

    def shell_complete(self, ctx, param, incomplete):
        from click.shell_completion import CompletionItem  # noqa: PLC0415 - TAB only, 0.5 ms

        return [CompletionItem(c) for c in self.choices if c.lower().startswith(incomplete.lower())]


PARITY = Choice(["N", "E", "O"], aliases={"none": "N", "even": "E", "odd": "O"})


class Seconds(click.ParamType):
    """Seconds, 0 for never."""

    name = "seconds"

    def convert(self, value, param, ctx):
        try:
            number = float(value)
        except (TypeError, ValueError):
            self.fail(f"{value} is not a number of seconds", param, ctx)
        if not 0 <= number < float("inf"):  # also refuses nan
            self.fail(f"{value} is not a number of seconds (0 for never)", param, ctx)
        return number


class FilePath(click.Path):
    """click.Path, named without gettext.

    click.Path names its type through gettext when an option is declared, and gettext's first
    call looks for translation catalogues: about 6.5 M instructions that every command paid,
    3% of a one-shot read (bench/oneshot.py --instructions).  The name is set here instead;
    the checks are click.Path's own."""

    def __init__(self, *, exists: bool = False, file_okay: bool = True, dir_okay: bool = True,
                 allow_dash: bool = False) -> None:  # fmt: skip
        self.exists, self.file_okay, self.dir_okay, self.allow_dash = exists, file_okay, dir_okay, allow_dash
        self.readable, self.writable, self.executable, self.resolve_path, self.type = (
            True,
            False,
            False,
            False,
            None,
        )
        self.name = "file" if not dir_okay else "directory" if not file_okay else "path"
