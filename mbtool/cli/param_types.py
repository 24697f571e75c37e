"""The command line's parameter types: numbers in decimal or hex within their range, unit
lists, seconds, RS-485 delays, and one case rule for every choice.  The rules of those a link
setting takes are the kinds of ``link.settings``, which convert a profile's and an inventory's
values too: each type here hands its text to its kind and says the kind's refusal as click's."""

from __future__ import annotations

import click

from mbtool.errors import UsageError
from mbtool.link import settings as link_settings

parse_int = link_settings.parse_whole  # decimal or 0x hex: every number the command line takes


def parse_units(text: str, broadcast: bool = False) -> frozenset[int]:
    """'1', '1,17', '1-10', '1-3,17': unit ids 1..255 (0 is broadcast, which every unit hears;
    ``broadcast``: 0 may be listed, for a gateway that forwards broadcasts)."""
    units: set[int] = set()
    for part in text.split(","):
        part = part.strip()
        if not part:
            raise UsageError(f"empty unit id in {text}")
        low_text, dash, high_text = part.partition("-")
        low = parse_int(low_text, "unit")
        high = parse_int(high_text, "unit") if dash else low
        if low > high:
            raise UsageError(f"unit range {part} runs backwards")
        lowest = 0 if broadcast else 1
        for unit in (low, high):
            if not lowest <= unit <= 255:
                why = "" if broadcast else " (unit 0 is broadcast: every unit hears it)"
                raise UsageError(f"unit {unit} is out of range {lowest}..255{why}")
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
        self.kind = link_settings.Whole(low, high, what)
        self.low, self.high, self.what = low, high, what  # the man page names the range

    def convert(self, value, param, ctx):
        return _converted(self.kind, value, self, param, ctx)


def _converted(kind: link_settings.Kind, value, param_type: click.ParamType, param, ctx):
    """``value`` by ``kind``'s rule, its refusal click's usage error (exit 2, naming the option)."""
    try:
        return kind.convert(value)
    except UsageError as error:
        param_type.fail(str(error), param, ctx)


ADDRESS = Number(0, 0xFFFF, "address")
COUNT = Number(0, 0xFFFF, "count")  # the spec limit is the codec's to check, per function code


class PositiveFloat(click.ParamType):
    """Seconds, more than 0; with ``zero_ok`` also 0 (poll back to back)."""

    name = "seconds"

    def __init__(self, zero_ok: bool = False) -> None:
        self.kind = link_settings.Seconds(zero_ok)

    def convert(self, value, param, ctx):
        return _converted(self.kind, value, self, param, ctx)


class Shard(click.ParamType):
    """K/N: the shard K (0 to N-1) of N pollers that split one inventory (poll, exporter)."""

    name = "K/N"

    def convert(self, value, param, ctx):
        if isinstance(value, tuple):
            return value
        number, slash, count = str(value).partition("/")
        if slash and number.isdigit() and count.isdigit() and int(number) < int(count):
            return int(number), int(count)
        self.fail(f"{value!r}: expected K/N, a shard K from 0 to N-1 of N, such as 0/2", param, ctx)


class Rs485Delays(click.ParamType):
    """BEFORE[,AFTER] in milliseconds, as modpoll's -4 takes them; kept in seconds."""

    name = "ms[,ms]"
    kind = link_settings.Delays()

    def convert(self, value, param, ctx):
        return _converted(self.kind, value, self, param, ctx)


class Choice(click.Choice):
    """One case rule for every choice: any case is accepted (--type FLOAT32, --order cdab,
    --framer RTU) and the listed spelling is what the command gets, what --help shows and what
    completion offers.  ``aliases`` are other words for a choice, as a field engineer says
    them (parity none, even, odd).

    The case folding is done here rather than by Click's ``case_sensitive=False``, whose
    help and completion show the choices in lower case from Click 8.2 on ([n|e|o] for a
    parity the docs write N, E, O)."""

    def __init__(self, choices, aliases: dict[str, str] | None = None, whole: bool = False) -> None:
        super().__init__(choices, case_sensitive=True)
        self.spelling = {choice.lower(): choice for choice in self.choices}
        self.spelling.update((word.lower(), choice) for word, choice in (aliases or {}).items())
        self.whole = whole  # the choices are numbers (data bits): the command gets the number

    def convert(self, value, param, ctx):
        if isinstance(value, int) and self.whole:
            value = str(value)
        if isinstance(value, str):
            value = self.spelling.get(value.lower(), value)
        choice = super().convert(value, param, ctx)
        return int(choice) if self.whole else choice

    def shell_complete(self, ctx, param, incomplete):
        from click.shell_completion import CompletionItem  # noqa: PLC0415 - TAB only, 0.5 ms

        return [CompletionItem(c) for c in self.choices if c.lower().startswith(incomplete.lower())]


def setting_type(kind: link_settings.Kind) -> click.ParamType | None:
    """The click type of a link setting's kind (None: text as given)."""
    if isinstance(kind, link_settings.Whole):
        return Number(kind.low, kind.high, kind.what)
    if isinstance(kind, link_settings.Seconds):
        return PositiveFloat(kind.zero_ok)
    if isinstance(kind, link_settings.OneOf):
        return Choice(list(kind.choices), kind.aliases, kind.whole)
    if isinstance(kind, link_settings.Delays):
        return Rs485Delays()
    if isinstance(kind, link_settings.File):
        return FilePath(dir_okay=False)
    return None


PARITY = setting_type(link_settings.SETTINGS["parity"].kind)


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


# poll's and the exporter's: the part of the inventory this process polls.
shard_option = click.option(
    "--shard",
    "shard_part",
    type=Shard(),
    help="Poll only the links whose names hash to K of N (MD5 modulo N, as Prometheus' hashmod "
    "relabelling computes it), with their devices: N pollers, 0/N to N-1/N, split one inventory "
    "without overlap.",
)
