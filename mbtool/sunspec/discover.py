"""Walking a device's SunSpec chain with the reads it is given (``execute``: a request in,
the reply out, a Modbus exception raised), as ``registermap.plan.MapReader`` reads a map.

The marker "SunS" is looked for at each base address (40000, 0, 50000: the SunSpec
specification's, in pysunspec2's order); after it each model is its id and its length,
read together, then its registers, up to 125 a read (spec §3).  The chain ends with the
end model, 0xFFFF.  Real devices end it in other ways, each a warning:

* no end model: the register after the last model answers exception 02 (some SMA
  inverters; bikeshedder/sunspec #20);
* an end marker of 0x0000, where a read of the id and length together answers exception
  02 and the id alone reads 0 (a Kostal inverter; sunspec/models #44).

A model whose registers the device refuses is named (its error kept) and the walk goes on
past it: its length is known.

The walk is bounded (MAX_MODELS, MAX_REGISTERS_READ), and one stopped there, or by Ctrl-C,
keeps the models it found: a chain of zero-length models is not walked read by read to
register 65535.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable
from typing import Any

from mbtool.codec.data_access import MAX_READ_REGISTERS, ReadHoldingRegisters
from mbtool.codec.errors import ModbusException, exception_name
from mbtool.codec.record import record
from mbtool.errors import ExitCode, MbtoolError
from mbtool.sunspec.layout import Layout, lay_out
from mbtool.sunspec.models import BASES, END_MODEL, MARKER, definition
from mbtool.words import counted

Execute = Callable[[ReadHoldingRegisters], Any]  # the reply: a RegistersResponse

# The walk's bounds (issue 40 item 13).  Each model moves the walk forward (its id, its
# length, its registers: at least 2 registers), so it ends by register 65535 whatever the
# device says; a device that says zero-length models took 12,768 reads to get there.  No
# device's chain comes near these: the twin's is 8 models and 404 registers, and the largest
# model SunSpec defines is 1,439 registers.
MAX_MODELS = 100
MAX_REGISTERS_READ = 10_000  # the marker, each model's id and length, and the registers read


class NotSunSpec(MbtoolError):
    """No marker at any base: what each answered.  Exit 4 when every base answered with an
    exception (the device refused), else 5 (it answered, and not as SunSpec says)."""

    def __init__(self, answers: dict[int, str], refused: bool) -> None:
        shown = "; ".join(f"{base}: {answer}" for base, answer in answers.items())
        super().__init__(
            f"no SunSpec marker (SunS) at holding register {', '.join(map(str, answers))}: {shown}"
        )
        self.exit_code = ExitCode.EXCEPTION if refused else ExitCode.INVALID_RESPONSE


@record
class Model:
    """A model as read: where it is laid out, its registers after the length, and the
    device's answer where it refused them (then ``registers`` is empty)."""

    layout: Layout
    registers: tuple[int, ...]
    error: ModbusException | None = None


@record
class Chain:
    base: int  # where the marker is (0-based)
    models: tuple[Model, ...]
    warnings: tuple[str, ...]  # the chain's own quirks; each model's are in its layout
    stopped: str = ""  # why the walk ended before the chain did: "" when it walked to its end
    interrupted: bool = False  # Ctrl-C or SIGTERM stopped it


class _Counted:
    """``execute``, with the registers it has read counted: the walk's budget."""

    def __init__(self, execute: Execute) -> None:
        self.execute, self.registers = execute, 0

    def __call__(self, request: ReadHoldingRegisters):
        reply = self.execute(request)
        self.registers += request.count
        return reply


def discover(execute: Execute, bases: tuple[int, ...] = BASES, wanted: set[int] | None = None) -> Chain:
    """The chain after the marker; ``wanted``: the model ids whose registers are read (the
    others are walked past: their id and length only).

    The walk stops at MAX_MODELS models, or before a model whose registers would take it past
    MAX_REGISTERS_READ; Ctrl-C or SIGTERM (KeyboardInterrupt) stops it too, once the marker is
    found.  Then ``stopped`` says why, and the models found before are kept: a model whose
    reads were cut short is left out."""
    execute = _Counted(execute)
    base = find_marker(execute, bases)
    found: list[tuple[int, int, tuple[int, ...], ModbusException | None]] = []
    warnings: list[str] = []
    stopped, interrupted = "", False
    address = base + 2
    try:
        while True:
            if len(found) == MAX_MODELS:
                stopped = f"the walk stopped after {MAX_MODELS} models, at register {address}: a chain holds no more"
                break
            header = _header(execute, address, found[-1][0] if found else None, warnings)
            if header is None:
                break
            model_id, length = header
            if address + 2 + length > 65536:
                warnings.append(
                    f"model {model_id} at {address}: its length, {length}, runs past register 65535; "
                    f"{65534 - address} registers read"
                )
                length = 65534 - address
            read = not wanted or model_id in wanted  # else walked past: laid out by its length alone
            if read and execute.registers + length > MAX_REGISTERS_READ:
                stopped = (
                    f"the walk stopped at model {model_id} at {address}: its {length} registers would "
                    f"take it past {MAX_REGISTERS_READ} registers read"
                )
                break
            error = None
            try:
                registers = tuple(read_registers(execute, address + 2, length)) if read else (0,) * length
            except ModbusException as refused:
                registers, error = (0,) * length, refused
            found.append((model_id, address, registers, error))
            address += 2 + length
    except KeyboardInterrupt:
        stopped = f"the walk stopped after {counted(len(found), 'model')}, at register {address}"
        interrupted = True
    keys = _keys([model_id for model_id, *_ in found])
    models = [
        Model(lay_out(model_id, key, address, registers), () if error else registers, error)
        for (model_id, address, registers, error), key in zip(found, keys, strict=True)
    ]
    return Chain(base, tuple(models), tuple(warnings), stopped, interrupted)


def find_marker(execute: Execute, bases: tuple[int, ...] = BASES) -> int:
    """The first base whose two registers hold "SunS".  A unit that does not answer at all
    raises at its first silence: no other base would answer either."""
    answers: dict[int, str] = {}
    refused = True
    for base in bases:
        try:
            registers = tuple(execute(ReadHoldingRegisters(base, 2)).registers)
        except ModbusException as error:
            answers[base] = f"exception {error.exception_code:02d} {exception_name(error.exception_code)}"
            continue
        if registers == MARKER:
            return base
        refused = False
        answers[base] = "holds " + " ".join(f"0x{register:04X}" for register in registers)
    raise NotSunSpec(answers, refused)


def read_registers(execute: Execute, address: int, count: int) -> list[int]:
    """``count`` holding registers from ``address``, in reads of at most 125 (spec §3)."""
    out: list[int] = []
    while len(out) < count:
        size = min(MAX_READ_REGISTERS, count - len(out))
        out += execute(ReadHoldingRegisters(address + len(out), size)).registers
    return out


def _header(execute: Execute, address: int, last: int | None, warnings: list[str]) -> tuple[int, int] | None:
    """The id and length of the model at ``address`` (``last``: the model before it); None
    where the chain ends."""
    after = f"after model {last}" if last is not None else "right after the marker"
    if address > 65534:
        warnings.append(f"the chain reaches register 65535 {after} without its end model")
        return None
    try:
        model_id, length = execute(ReadHoldingRegisters(address, 2)).registers
    except ModbusException as error:
        if error.exception_code != 0x02:
            raise
        # The chain may end in one register (an end marker alone), or with none at all.
        try:
            (model_id,) = execute(ReadHoldingRegisters(address, 1)).registers
        except ModbusException as alone:
            if alone.exception_code != 0x02:
                raise
            warnings.append(
                f"no end model: register {address}, {after}, answers exception 02; the chain ends there"
            )
            return None
        if model_id not in (END_MODEL, 0x0000):
            warnings.append(
                f"model {model_id} at {address}: its length cannot be read (exception 02 at {address + 1}); "
                "the chain ends there"
            )
            return None
        length = None
    if model_id == END_MODEL:
        return None
    if model_id == 0x0000:
        warnings.append(f"the chain ends with 0x0000 at {address}, {after}: the end model is 0xFFFF")
        return None
    return model_id, length


def _keys(model_ids: list[int]) -> list[str]:
    """Each model's name in its points' names: its definition's (model_ID for one SunSpec
    does not define), numbered where it repeats (two meters: ac_meter_abcn_1, ac_meter_abcn_2)."""
    names = []
    for model_id in model_ids:
        group = definition(model_id)
        names.append(group["name"] if group is not None else f"model_{model_id}")
    counts = Counter(names)
    seen: Counter = Counter()
    keys = []
    for name in names:
        seen[name] += 1
        keys.append(f"{name}_{seen[name]}" if counts[name] > 1 else name)
    return keys
