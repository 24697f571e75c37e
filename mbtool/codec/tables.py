"""The four tables of the Modbus data model and the Modicon references of device manuals (spec §1).

A device manual rarely gives wire addresses.  It writes references: a table's
digit, then the 1-based number of the item in that table.

* ``0`` coils, ``1`` discrete inputs, ``3`` input registers, ``4`` holding registers
* five digits, the classic form: ``40001``–``49999`` (items 1–9999)
* six digits, for the whole 16-bit range: ``400001``–``465536``
* ``4x0108``: the same as ``40108``, with the table digit spelled out

The wire address is the number minus one: ``40108`` is holding register 107.
"""

from __future__ import annotations

import re

from mbtool.codec.data_access import (
    ReadCoils,
    ReadDiscreteInputs,
    ReadHoldingRegisters,
    ReadInputRegisters,
    WriteMultipleCoils,
    WriteMultipleRegisters,
    WriteSingleCoil,
    WriteSingleRegister,
)
from mbtool.codec.errors import RequestError
from mbtool.codec.record import record


@record
class Table:
    name: str  # the short name maps and JSON use
    digit: str  # the reference prefix
    item: str  # one item, in Modbus words
    bits: bool  # coils and discrete inputs hold bits, the others 16-bit registers
    writable: bool

    @property
    def items(self) -> str:
        return self.item + "s"


COILS = Table("coils", "0", "coil", True, True)
DISCRETE_INPUTS = Table("discrete", "1", "discrete input", True, False)
INPUT_REGISTERS = Table("input", "3", "input register", False, False)
HOLDING_REGISTERS = Table("holding", "4", "holding register", False, True)
TABLES = (COILS, DISCRETE_INPUTS, INPUT_REGISTERS, HOLDING_REGISTERS)

# The request that reads each table (FC 01-04), by the table's name.
READS = {
    COILS.name: ReadCoils,
    DISCRETE_INPUTS.name: ReadDiscreteInputs,
    INPUT_REGISTERS.name: ReadInputRegisters,
    HOLDING_REGISTERS.name: ReadHoldingRegisters,
}


def write_of(table: Table, address: int, values, multiple: bool = False):
    """The request that writes ``values`` (bits or registers) from ``address``: FC 05/06 for
    one, FC 15/16 for more, or for one too when ``multiple`` (some devices accept only
    FC 15/16).  Only coils and holding registers can be written."""
    if table is COILS:
        if len(values) == 1 and not multiple:
            return WriteSingleCoil(address, bool(values[0]))
        return WriteMultipleCoils(address, tuple(bool(v) for v in values))
    if len(values) == 1 and not multiple:
        return WriteSingleRegister(address, values[0])
    return WriteMultipleRegisters(address, tuple(values))


# The table each read function code reads, by its code (a Result names its table by it).
TABLE_OF_READ = {kind.function_code: name for name, kind in READS.items()}

_BY_DIGIT = {table.digit: table for table in TABLES}
_BY_NAME = {table.name: table for table in TABLES}
_HINT = "a reference has 5 or 6 digits: 00001 for coil 1, 40001 for holding register 1"
_PREFIXES = "0 coils, 1 discrete inputs, 3 input registers, 4 holding registers"


def table_named(name: str) -> Table:
    """The table a map or option names: coils, discrete, input or holding."""
    try:
        return _BY_NAME[name.lower()]
    except KeyError:
        raise RequestError(f"unknown table {name}: use one of {', '.join(_BY_NAME)}") from None


def parse_reference(text: str) -> tuple[Table, int]:
    """The table and 0-based wire address of a reference such as 40108, 400108 or 4x0108."""
    text = text.strip()
    match = re.fullmatch(r"([0-9])[xX]([0-9]{1,5})", text)
    if match:
        digit, number, limit = match[1], int(match[2]), 65536
    elif text.isascii() and text.isdigit() and len(text) in (5, 6):
        digit, number = text[0], int(text[1:])
        limit = 9999 if len(text) == 5 else 65536
    else:
        raise RequestError(f"{text or 'an empty text'} is not a reference: {_HINT}")
    table = _BY_DIGIT.get(digit)
    if table is None:
        raise RequestError(f"{text} is not a reference: no table has the prefix {digit} ({_PREFIXES})")
    if not 1 <= number <= limit:
        first = f"{digit}0001" if limit == 9999 else f"{digit}00001"
        raise RequestError(
            f"{text} is not a reference: {table.items} count from 1 ({first} is {table.item} 1, "
            f"wire address 0) up to {limit}"
        )
    return table, number - 1


def reference(table: Table, address: int) -> str:
    """The manual's reference for a wire address: five digits while they suffice, else six."""
    number = address + 1
    return f"{table.digit}{number:04d}" if number <= 9999 else f"{table.digit}{number:05d}"
