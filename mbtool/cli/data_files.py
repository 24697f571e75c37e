"""The data file a dump writes and ``mbtool serve --data`` loads unchanged: its tables'
sections, writing one (``dump``), and reading one back (``diff``, ``restore``)."""

from __future__ import annotations

from mbtool.device.datafile import load_data
from mbtool.errors import UsageError

TABLE_SECTIONS = {  # a table's name in mbtool's messages -> its section in a data file
    "coils": "coils",
    "discrete": "discrete_inputs",
    "input": "input_registers",
    "holding": "holding_registers",
}
RUN = 16  # equal values in a row written as one { value, count }: long runs stay compact


def data_file(dumps, identity: dict, complete: bool) -> dict:
    """The dump as ``serve --data`` reads it: sparse, so an address it lacks is exception 02."""
    document: dict = {"sparse": True}
    if not complete:
        document["complete"] = False
    for dump in dumps:
        section: dict = {}
        for first, values in dump.runs:
            for start, chunk in _chunks(first, [int(v) for v in values]):
                section[str(start)] = chunk
        if section:
            document[TABLE_SECTIONS[dump.table.name]] = section
    if identity:
        document["identity"] = identity
    return document


def _chunks(first: int, values: list[int]):
    """(address, values or a run) pieces of one readable run."""
    plain: list[int] = []
    start = i = 0
    while i < len(values):
        same = i
        while same < len(values) and values[same] == values[i]:
            same += 1
        if same - i >= RUN:
            if plain:
                yield first + start, plain
            yield first + i, {"value": values[i], "count": same - i}
            plain, start = [], same
        else:
            if not plain:
                start = i
            plain.extend(values[i:same])
        i = same
    if plain:
        yield first + start, plain


def snapshot(path: str) -> tuple[dict[str, dict[int, int]], bool]:
    """A data file's listed addresses and their values, by table (coils, discrete, input,
    holding), and whether the file is complete (a dump cut short says complete = false).

    One device's tables: a file with [units.N] sections (serve's, one set a unit) is
    refused rather than read as something it is not."""
    model, units = load_data(path, frozenset(range(1, 256)), listed_only=True)
    if units:
        raise UsageError(
            f"{path} has [units.{min(units)}]: diff and restore take one device's tables, "
            "as mbtool dump writes them, not serve's sections a unit"
        )
    out: dict[str, dict[int, int]] = {}
    defined = model.defined or {}
    for name, section in TABLE_SECTIONS.items():
        mask = defined.get(section)
        if mask:
            values = getattr(model, section)
            out[name] = {address: int(values[address]) for address, there in enumerate(mask) if there}
    return out, model.complete
