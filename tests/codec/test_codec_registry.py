"""Every function code of the spec is registered and defines its whole codec (no ABC checks it)."""

from __future__ import annotations

import subprocess
import sys

from mbtool.codec.pdu import FUNCTION_MODULES, FUNCTIONS, Request, function_type, load_all_functions

SPEC_FUNCTION_CODES = {
    0x01,
    0x02,
    0x03,
    0x04,
    0x05,
    0x06,
    0x07,
    0x08,
    0x0B,
    0x0C,
    0x0F,
    0x10,
    0x11,
    0x14,
    0x15,
    0x16,
    0x17,
    0x18,
    0x2B,
}


def test_every_spec_function_code_is_known():
    assert FUNCTION_MODULES
    assert {code for code in SPEC_FUNCTION_CODES if function_type(code) is not None} == SPEC_FUNCTION_CODES
    assert function_type(0x41) is None


def test_each_type_defines_its_codec():
    load_all_functions()
    for code, kind in FUNCTIONS.items():
        assert issubclass(kind, Request)
        assert kind.function_code == code
        for method in ("encode_data", "decode"):
            assert method in vars(kind) or any(method in vars(base) for base in kind.__mro__[1:-2]), (
                kind,
                method,
            )
        for method in ("encode", "decode"):
            assert callable(getattr(kind.response_type, method, None)), (kind.response_type, method)
        assert kind.name and kind.request_size and kind.response_size


def _modules_loaded_by(code: str) -> set[str]:
    """The function modules a fresh interpreter has loaded after running ``code``."""
    script = f"import sys\n{code}\nprint(' '.join(sorted(sys.modules)))"
    out = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=True
    )
    return {name.rsplit(".", 1)[1] for name in out.stdout.split() if name.rsplit(".", 1)[-1] in ALL_MODULES}


ALL_MODULES = {"data_access", "serial_line", "file_record", "device_id"}


def test_each_module_registers_the_codes_the_registry_lists_for_it():
    load_all_functions()
    listed = {code: module for module, codes in FUNCTION_MODULES.items() for code in codes}
    assert set(listed) == set(FUNCTIONS) == SPEC_FUNCTION_CODES
    for code, kind in FUNCTIONS.items():
        assert kind.__module__ == f"mbtool.codec.{listed[code]}", hex(code)


def test_a_look_up_loads_the_module_of_its_code_alone():
    """Issue 30: a one-shot read pays for the function codes it uses, not for the codec."""
    assert _modules_loaded_by("from mbtool.codec.pdu import function_type; function_type(0x41)") == set()
    assert _modules_loaded_by("from mbtool.codec.pdu import function_type; function_type(0x03)") == {
        "data_access"
    }
    assert _modules_loaded_by("from mbtool.codec.pdu import function_type; function_type(0x2B)") == {
        "device_id"
    }
    assert (
        _modules_loaded_by("from mbtool.codec.pdu import load_all_functions; load_all_functions()")
        == ALL_MODULES
    )


def test_an_rtu_master_loads_only_the_function_modules_of_what_it_reads():
    """Issue 30: the RTU framer used to load every function module when made (it asks about
    all 256 codes), which was most of the RTU one-shot's start-up."""
    read = """
from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.codec.framer import Frame
from mbtool.codec.rtu import RtuFramer
framer = RtuFramer()
framer.expect, framer.expect_unit = ReadHoldingRegisters(0, 2), 0x11
# Garbage before the reply, with function codes nobody knows and the unit's byte in it.
framer.feed(bytes.fromhex("41 42 11 66 7F 11 99") + framer.build(0x11, bytes.fromhex("03 04 00 01 00 02")))
events = [framer.next_event(), framer.next_event()]
assert isinstance(events[1], Frame) and events[1].pdu == bytes.fromhex("03 04 00 01 00 02"), events
"""
    assert _modules_loaded_by(read) == {"data_access"}
    assert _modules_loaded_by("from mbtool.codec.rtu import RtuFramer; RtuFramer()") == set()
