"""Records behave the same before and after their __init__ is compiled (codec/record.py)."""

from __future__ import annotations

import pytest

from mbtool.codec.record import COMPILE_AFTER, FrozenInstanceError, field, record, replace


def made_often(cls, *args, **kwargs):
    """Make ``cls`` enough times that its __init__ is compiled, then once more."""
    for _ in range(COMPILE_AFTER):
        cls(*args, **kwargs)
    return cls(*args, **kwargs)


def fresh_classes():
    @record
    class Reply:
        unit: int
        values: tuple  # named like nothing special, but once clashed with the compiled code's local
        note: str = ""
        checked: list = field(default=None, kw_only=True, compare=False)

        def __post_init__(self) -> None:
            if self.unit < 0:
                raise ValueError("unit below 0")

    @record
    class Odd:  # a default before a field without one: no signature can say that
        first: int = 1
        second: int = ...

    return Reply, Odd


@pytest.mark.parametrize("compiled", [False, True], ids=["generic", "compiled"])
def test_fields_defaults_keywords_and_post_init(compiled):
    Reply, _ = fresh_classes()
    make = made_often if compiled else (lambda cls, *a, **k: cls(*a, **k))
    reply = make(Reply, 1, (2, 3))
    assert (reply.unit, reply.values, reply.note, reply.checked) == (1, (2, 3), "", None)
    assert make(Reply, 1, (2,), "n", checked=[1]).checked == [1]
    assert make(Reply, unit=4, values=()) == Reply(4, ())
    assert replace(reply, note="x").note == "x"
    with pytest.raises(ValueError, match="unit below 0"):
        Reply(-1, ())
    with pytest.raises(TypeError):
        Reply(1)
    with pytest.raises(FrozenInstanceError):
        reply.unit = 5
    assert (Reply.__init__.__name__ == "__init__") is compiled


def test_a_record_no_signature_can_describe_keeps_the_generic_init():
    _, Odd = fresh_classes()
    odd = made_often(Odd, 1, 2)
    assert (odd.first, odd.second) == (1, 2)
    assert Odd.__init__.__name__ == "_init"
