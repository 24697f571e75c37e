"""Every function code of the spec is registered and defines its whole codec (no ABC checks it)."""

from __future__ import annotations

from mbtool.codec.pdu import FUNCTION_MODULES, FUNCTIONS, Request, function_type

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
    function_type(0x01)  # loads every module
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
