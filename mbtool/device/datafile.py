"""The data files of ``serve --data`` (README, "Simulating a device"): JSON or TOML into a model.

A file sets the tables, files, exception status, diagnostic register and identity of the
device (the template every unit starts from) and of single units (``[units.N]``); a sparse
one (``sparse = true``) makes only the addresses it lists exist.  ``mbtool dump`` writes
such files, ``mbtool diff`` and ``restore`` read them through here too.  Every value is
checked against the bounds of ``mbtool.device.model``: a file that breaks one is refused
with one line that says where (UsageError, exit 2).
"""

from __future__ import annotations

from mbtool.codec.errors import RequestError
from mbtool.codec.serial_line import RUN_OFF, RUN_ON
from mbtool.device.model import FILE_SIZE, IDENTITY_FUNCTIONS, MAX_PDU, TABLE_SIZE, TABLES, DataModel
from mbtool.errors import UsageError
from mbtool.files import read_whole

OBJECT_KEYS = {
    "vendor_name": 0x00,
    "product_code": 0x01,
    "revision": 0x02,
    "vendor_url": 0x03,
    "product_name": 0x04,
    "model_name": 0x05,
    "user_application_name": 0x06,
}


def load_data(
    path: str, units: frozenset[int], listed_only: bool = False
) -> tuple[DataModel, dict[int, DataModel]]:
    """A template model and per-unit models from a JSON or TOML file (README, "Simulating a device").

    ``listed_only``: mark the addresses the file lists, as a sparse file does, whatever
    it says (diff compares those and no others)."""
    data = _read(path)
    template = DataModel()
    sparse = data.get("sparse", False)
    if not isinstance(sparse, bool):
        raise UsageError(f"data file {path}: sparse must be true or false")
    if sparse or listed_only:
        template.defined = {}  # only what the file lists exists; units.N add their own
    per_unit_sections = data.get("units", {})
    if not isinstance(per_unit_sections, dict):
        raise UsageError(f"data file {path}: 'units' must map unit ids to sections")
    complete = data.get("complete", True)  # mbtool dump marks a dump it did not finish
    if not isinstance(complete, bool):
        raise UsageError(f"data file {path}: complete must be true or false")
    template.complete = complete
    # write_roles is the server's rule, not the device's data (load_write_roles).
    top = {k: v for k, v in data.items() if k not in ("units", "sparse", "complete", "write_roles")}
    apply_data(template, top, path)
    unit_models = {}
    for key, section in per_unit_sections.items():
        unit = _int(key, f"{path}: units", 1, 255)
        if unit not in units:
            raise UsageError(f"data file {path}: unit {unit} is not among the units served")
        if not isinstance(section, dict):
            raise UsageError(f"data file {path}: units.{key} must be a table")
        model = template.copy()
        apply_data(model, section, f"{path}: units.{key}")
        unit_models[unit] = model
    return template, unit_models


def _read(path: str) -> dict:
    """The data file as a table, JSON or TOML by its name; UsageError naming it if it is neither."""
    raw = read_whole(path, "data file")
    try:
        if path.lower().endswith(".toml"):
            import tomllib  # noqa: PLC0415 - 2 ms: a .toml data file only

            data = tomllib.loads(raw.decode("utf-8"))
        else:
            import json  # noqa: PLC0415 - 1 ms: a .json data file only

            data = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as error:
        raise UsageError(f"data file {path} is not valid {_kind(path)}: {error}") from None
    except RecursionError:  # json and tomllib parse arrays inside one another recursively
        raise UsageError(
            f"data file {path}: nested too deeply (arrays or tables inside one another)"
        ) from None
    if not isinstance(data, dict):
        raise UsageError(f"data file {path}: the top level must be a table of sections")
    return data


def load_write_roles(path: str) -> frozenset[str] | None:
    """The roles a data file lets write on a tls:// server (``write_roles = ["operator"]``;
    Modbus/TCP Security's authorization), None where it says nothing: every role may."""
    roles = _read(path).get("write_roles")
    if roles is None:
        return None
    if not isinstance(roles, list) or not all(isinstance(role, str) and role for role in roles):
        raise UsageError(f'data file {path}: write_roles must be a list of roles, such as ["operator"]')
    return frozenset(roles)


def _kind(path: str) -> str:
    return "TOML" if path.lower().endswith(".toml") else "JSON"


def _int(value, where: str, low: int, high: int) -> int:
    if isinstance(value, bool):
        value = int(value)
    if isinstance(value, str):
        try:
            value = int(value.strip(), 0) if not value.strip().isdigit() else int(value.strip())
        except ValueError:
            raise UsageError(f"data file {where}: {value} is not a number") from None
    if not isinstance(value, int):
        raise UsageError(f"data file {where}: {value} is not a number")
    if not low <= value <= high:
        raise UsageError(f"data file {where}: {value} is out of range {low}..{high}")
    return value


def _bytes(value, where: str) -> bytes:
    if isinstance(value, str):
        return value.encode("utf-8")
    if isinstance(value, list):
        return bytes(_int(v, where, 0, 255) for v in value)
    raise UsageError(f"data file {where}: expected a string or a list of bytes")


def _fill(table, section, where: str, high: int, size: int, defined: bytearray | None) -> None:
    """ADDRESS = value, [values] or a run { value = V, count = N } into ``table``;
    ``defined`` (sparse) marks each address set."""
    if not isinstance(section, dict):
        raise UsageError(f"data file {where}: expected a table of ADDRESS = value(s)")
    for key, values in section.items():
        start = _int(key, f"{where}", 0, size - 1)
        if isinstance(values, dict):  # a run of one value, as mbtool dump writes long ones
            if set(values) != {"value", "count"}:
                raise UsageError(f"data file {where}.{key}: a run is {{ value = V, count = N }}")
            values = [values["value"]] * _int(values["count"], f"{where}.{key}.count", 1, size)
        values = values if isinstance(values, list) else [values]
        if start + len(values) > size:
            raise UsageError(f"data file {where}.{key}: {len(values)} values run past {size - 1}")
        for offset, value in enumerate(values):
            table[start + offset] = _int(value, f"{where}.{key}", 0, high)
        if defined is not None:
            defined[start : start + len(values)] = b"\x01" * len(values)


def apply_data(model: DataModel, data: dict, where: str) -> None:
    known = {*TABLES, "files", "exception_status", "diagnostic_register", "identity"}
    unknown = sorted(set(data) - known)
    if unknown:
        raise UsageError(f"data file {where}: unknown section {unknown[0]} (expected one of {sorted(known)})")
    for name in TABLES:
        if name in data:
            bits = name in ("coils", "discrete_inputs")
            _fill(
                model.writable(name),
                data[name],
                f"{where}: {name}",
                1 if bits else 0xFFFF,
                TABLE_SIZE,
                model.defines(name, TABLE_SIZE),
            )
    files = data.get("files", {})
    if not isinstance(files, dict):
        raise UsageError(f"data file {where}: files must map file numbers to records")
    numbers = {key: _int(key, f"{where}: files", 1, 0xFFFF) for key in files}
    try:
        model.make_files(numbers.values())
    except RequestError as error:
        raise UsageError(f"data file {where}: files: {error}") from None
    for key, section in files.items():
        number = numbers[key]
        _fill(
            model.writable_file(number),
            section,
            f"{where}: files.{key}",
            0xFFFF,
            FILE_SIZE,
            model.defines(number, FILE_SIZE),
        )
    if "exception_status" in data:
        model.exception_status = _int(data["exception_status"], f"{where}: exception_status", 0, 0xFF)
    if "diagnostic_register" in data:
        model.diagnostic_register = _int(
            data["diagnostic_register"], f"{where}: diagnostic_register", 0, 0xFFFF
        )
    identity = data.get("identity", {})
    if not isinstance(identity, dict):
        raise UsageError(f"data file {where}: identity must be a table")
    # The FC43/14 objects are exactly those the identity names, as a dump of a device lists
    # them; one that names none keeps the simulator's own.
    objects: dict[int, bytes] = {}
    for key, value in identity.items():
        here = f"{where}: identity.{key}"
        if key == "slave_id":
            model.slave_id = _int(value, here, 0, 0xFF)
        elif key == "run":
            # true or false (FF, 00), or the byte itself: a dump keeps one that is neither.
            if isinstance(value, bool):
                model.run_indicator = RUN_ON if value else RUN_OFF
            elif isinstance(value, int):
                model.run_indicator = _int(value, here, 0, 0xFF)
            else:
                raise UsageError(f"data file {here}: expected true, false or a byte 0..255")
        elif key == "extra":
            model.slave_id_extra = _bytes(value, here)[: MAX_PDU - 4]
        elif key == "conformity":
            model.conformity = _int(value, here, 0, 0xFF)
        elif key == "refused":
            if not isinstance(value, list) or not set(value) <= IDENTITY_FUNCTIONS:
                raise UsageError(f"data file {here}: expected a list of 17 and 43, the functions refused")
            model.refused = frozenset(value)
        elif key in OBJECT_KEYS:
            objects[OBJECT_KEYS[key]] = _object(value, here)
        elif key == "objects":
            if not isinstance(value, dict):
                raise UsageError(f"data file {here}: expected a table of OBJECT_ID = value")
            for object_key, object_value in value.items():
                object_id = _int(object_key, here, 0, 0xFF)
                objects[object_id] = _object(object_value, f"{here}.{object_key}")
        else:
            raise UsageError(f"data file {here}: unknown key")
    if objects:
        model.objects = objects


def _object(value, where: str) -> bytes:
    data = _bytes(value, where)
    if len(data) > MAX_PDU - 9:
        raise UsageError(f"data file {where}: {len(data)} bytes do not fit one reply (at most {MAX_PDU - 9})")
    return data
