"""Records (codec/record.py): the generic __init__, and the hand-written ones of hot records."""

from __future__ import annotations

import pytest

from mbtool.codec.data_access import BitsResponse, ReadHoldingRegisters, RegistersResponse
from mbtool.codec.record import FrozenInstanceError, field, fields, record, replace


def fresh_classes():
    @record
    class Reply:
        unit: int
        values: tuple
        note: str = ""
        checked: list = field(default=None, kw_only=True, compare=False)

        def __post_init__(self) -> None:
            if self.unit < 0:
                raise ValueError("unit below 0")

    @record
    class Odd:  # a default before a field without one
        first: int = 1
        second: int = ...

    return Reply, Odd


def test_fields_defaults_keywords_and_post_init():
    Reply, _ = fresh_classes()
    reply = Reply(1, (2, 3))
    assert (reply.unit, reply.values, reply.note, reply.checked) == (1, (2, 3), "", None)
    assert Reply(1, (2,), "n", checked=[1]).checked == [1]
    assert Reply(unit=4, values=()) == Reply(4, ())
    assert Reply(1, (), checked=[1]) == Reply(1, (), checked=[2])  # compare=False
    assert replace(reply, note="x").note == "x"
    with pytest.raises(ValueError, match="unit below 0"):
        Reply(-1, ())
    with pytest.raises(TypeError, match="missing argument 'values'"):
        Reply(1)
    with pytest.raises(TypeError, match="takes 3 positional arguments"):
        Reply(1, (), "", [])
    with pytest.raises(TypeError, match="unexpected arguments"):
        Reply(1, (), colour="red")
    with pytest.raises(FrozenInstanceError):
        reply.unit = 5
    with pytest.raises(FrozenInstanceError):
        del reply.unit


def test_a_default_before_a_required_field():
    _, Odd = fresh_classes()
    odd = Odd(1, 2)
    assert (odd.first, odd.second) == (1, 2)
    assert Odd(second=3).first == 1


def test_hand_written_init_is_kept_and_inherited_by_subclasses_without_fields():
    @record
    class Base:
        a: int

        def __init__(self, a: int) -> None:
            self.__dict__["a"] = a * 10

    @record
    class Same(Base):
        pass

    @record
    class More(Base):
        b: int = 2

    assert Base(1).a == 10
    assert Same(1).a == 10 and Same(1) == Same(1) and Same(1) != Base(1)
    assert (More(1).a, More(1).b) == (1, 2)  # its own fields: the generic __init__


@pytest.mark.parametrize(
    "make, generic",
    [
        (lambda: RegistersResponse(3, (1, 2)), lambda: RegistersResponse(function_code=3, registers=(1, 2))),
        (
            lambda: BitsResponse(1, (True, False), warnings=("odd",)),
            lambda: BitsResponse(function_code=1, bits=(True, False)),
        ),
    ],
)
def test_hand_written_inits_make_the_same_records(make, generic):
    made = make()
    assert made == generic()
    assert hash(made) == hash(generic())
    assert {spec.name for spec in fields(made)} == set(vars(made))
    assert replace(made) == made
    with pytest.raises(FrozenInstanceError):
        made.unit = 2


def test_requests_still_check_their_fields():
    with pytest.raises(ValueError, match="registers"):
        ReadHoldingRegisters(0, 126)


def test_a_field_set_by_post_init_is_no_argument():
    # field(init=False): a value worked out from the others (registermap's Point.ref), declared
    # so a type checker knows it; the constructor refuses it, replace() works it out anew.
    @record
    class Reg:
        address: int
        ref: str = field(init=False, compare=False)

        def __post_init__(self) -> None:
            object.__setattr__(self, "ref", f"4{self.address + 1:04d}")

    reg = Reg(9)
    assert reg.ref == "40010" and repr(reg) == "Reg(address=9)"
    assert replace(reg, address=10).ref == "40011"
    with pytest.raises(TypeError):
        Reg(9, "40010")
    with pytest.raises(TypeError):
        Reg(9, ref="40010")
