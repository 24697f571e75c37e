"""``@record``: the part of ``@dataclass(frozen=True)`` the codec uses, without its start-up cost.

Why not dataclasses: each frozen dataclass compiles six methods with ``exec``
when its module is imported, about 0.6 ms a class on this project's machines.
The codec has a class per function code and direction, and a one-shot read
from cron pays that on every run; the issue's target (a read costs at most
1.25 x ``python -c "import click"``) cannot be met with them.  These records
share generic methods instead, so defining one costs microseconds.

A record that is made in every transaction of a polling loop (a reply) writes its
``__init__`` by hand, as a plain class would: the generic one below
costs a few microseconds more, which ``bench/polling_cpu.py`` shows.  It sets its fields as
one table of its own (``fields_setter``): Python 3.11 reads an attribute of such a table by
hint, and one of the table an instance's ``__dict__`` makes (split, its keys shared with the
class) the generic way, every time.

Supported: fields from annotations (``ClassVar`` ones skipped), inherited
fields first, defaults, ``field(default=..., kw_only=True, compare=False, init=False)``,
``__post_init__``, equality, hashing, repr, immutability, ``fields()`` and
``replace()``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, dataclass_transform

_R = TypeVar("_R", bound=type)


class FrozenInstanceError(AttributeError):
    pass


class Field:
    __slots__ = ("name", "default", "kw_only", "compare", "init")

    def __init__(
        self, default: Any = ..., kw_only: bool = False, compare: bool = True, init: bool = True
    ) -> None:
        self.name = ""
        self.default = default
        self.kw_only = kw_only
        self.compare = compare
        self.init = init  # False: no argument of the constructor; __post_init__ sets it


def field(default: Any = ..., *, kw_only: bool = False, compare: bool = True, init: bool = True) -> Any:
    return Field(default, kw_only, compare, init)


def _own_fields(cls: type) -> list[Field]:
    out = []
    for name, annotation in cls.__dict__.get("__annotations__", {}).items():
        if "ClassVar" in str(annotation):
            continue
        value = cls.__dict__.get(name, ...)
        spec = value if isinstance(value, Field) else Field(value)
        spec.name = name
        if isinstance(value, Field):
            # Leave no Field object behind as a class attribute.
            if value.default is ...:
                delattr(cls, name)
            else:
                setattr(cls, name, value.default)
        out.append(spec)
    return out


def _init(self, *args: Any, **kwargs: Any) -> None:
    cls = type(self)
    positional = cls.__record_positional__
    if len(args) > len(positional):
        raise TypeError(f"{cls.__name__}() takes {len(positional)} positional arguments, {len(args)} given")
    for spec, value in zip(positional, args, strict=False):
        object.__setattr__(self, spec.name, value)
    for spec in cls.__record_init__:
        if spec.name in kwargs:
            object.__setattr__(self, spec.name, kwargs.pop(spec.name))
        elif spec.name not in self.__dict__:
            if spec.default is ...:
                raise TypeError(f"{cls.__name__}() missing argument {spec.name!r}")
            object.__setattr__(self, spec.name, spec.default)
    if kwargs:
        raise TypeError(f"{cls.__name__}() got unexpected arguments {sorted(kwargs)}")
    self.__post_init__()


def _no_post_init(self) -> None:
    """Every record has a __post_init__, so _init calls it without looking it up."""


def _key(self) -> tuple:
    return tuple(getattr(self, spec.name) for spec in type(self).__record_fields__ if spec.compare)


def _eq(self, other: object) -> bool:
    if other.__class__ is not self.__class__:
        return NotImplemented
    return _key(self) == _key(other)


def _hash(self) -> int:
    return hash((type(self), _key(self)))


def _repr(self) -> str:
    inner = ", ".join(f"{spec.name}={getattr(self, spec.name)!r}" for spec in type(self).__record_init__)
    return f"{type(self).__name__}({inner})"


def _setattr(self, name: str, value: Any) -> None:
    raise FrozenInstanceError(f"cannot assign to field {name!r}")


def _delattr(self, name: str) -> None:
    raise FrozenInstanceError(f"cannot delete field {name!r}")


def fields_setter(cls: type) -> Callable[[object, dict], None]:
    """The setter of a record's fields as one table (a dict of its own), past its frozen
    ``__setattr__``: the ``__dict__`` descriptor's own, bound once (object.__setattr__ looks it
    up every call)."""
    for base in cls.__mro__:
        if "__dict__" in base.__dict__:
            return base.__dict__["__dict__"].__set__
    raise TypeError(f"{cls.__name__} keeps no __dict__")


# A type checker reads a record as the frozen dataclass it behaves as: its constructor's
# arguments (inherited fields first, ``field(kw_only=True)`` after), equality, no assignment.
@dataclass_transform(eq_default=True, frozen_default=True, field_specifiers=(field, Field))
def record(cls: _R) -> _R:
    """Make ``cls`` a frozen record of its annotated fields (see the module docstring)."""
    return _make_record(cls)


def _make_record(cls: Any) -> Any:
    # Any: the attributes set here are the record machinery's, which no checker can see on `type`.
    inherited: list[Field] = []
    for base in reversed(cls.__mro__[1:]):
        for spec in base.__dict__.get("__record_own__", ()):
            inherited = [f for f in inherited if f.name != spec.name] + [spec]
    own = _own_fields(cls)
    names = {spec.name for spec in own}
    all_fields = [f for f in inherited if f.name not in names] + own
    cls.__record_own__ = tuple(own)
    cls.__record_fields__ = tuple(all_fields)
    cls.__record_init__ = tuple(f for f in all_fields if f.init)
    cls.__record_positional__ = tuple(f for f in cls.__record_init__ if not f.kw_only)
    setattr(cls, "__match_args__", tuple(f.name for f in cls.__record_positional__))  # noqa: B010 - mypy refuses the assignment
    if "__init__" in cls.__dict__:
        cls.__record_own_init__ = True
    elif own or not getattr(cls, "__record_own_init__", False):
        cls.__init__ = _init
    # else: no fields of its own, so the __init__ a base wrote by hand still fits
    if not hasattr(cls, "__post_init__"):
        cls.__post_init__ = _no_post_init
    cls.__eq__ = _eq
    cls.__hash__ = _hash
    cls.__repr__ = _repr
    cls.__setattr__ = _setattr
    cls.__delattr__ = _delattr
    return cls


def fields(obj: Any) -> tuple[Field, ...]:
    cls: Any = obj if isinstance(obj, type) else type(obj)
    return cls.__record_fields__


def replace(obj: Any, **changes: Any) -> Any:
    values = {spec.name: getattr(obj, spec.name) for spec in type(obj).__record_init__}
    values.update(changes)
    positional = [values.pop(spec.name) for spec in type(obj).__record_positional__]
    return type(obj)(*positional, **values)
