"""Profiles: named connection settings in a TOML file, chosen with -P/--profile NAME.

Imported only when a profile is named, so a one-shot read without one pays
nothing for it (tomllib included).  Precedence: an option on the command line
> its environment variable (MBTOOL_PORT, MBTOOL_UNIT) > the profile > the
default; click's ParameterSource says which options were left at their default.

The file is ``$MBTOOL_CONFIG``, else ``$XDG_CONFIG_HOME/mbtool/config.toml``
(``~/.config/mbtool/config.toml``)::

    [profiles.boiler]
    port = "/dev/ttyUSB0"
    unit = 17
    baud = 9600
    parity = "N"
"""

from __future__ import annotations

import os
from pathlib import Path

import click

from mbtool.codec.errors import RequestError
from mbtool.files import read_whole

# profile key (the option's parameter name, and the Connection field it sets) -> the TOML
# types it takes, and how to say so
KEYS = {
    "port": ((str,), 'text, such as "/dev/ttyUSB0" or "tcp://10.0.0.5"'),
    "unit": ((int,), "a whole number, 0..255"),
    "framer": ((str,), 'text: "rtu", "ascii" or "tcp"'),
    "baud": ((int,), "a whole number, such as 9600"),
    "parity": ((str,), 'text: "N", "E" or "O" (or none, even, odd)'),
    "bytesize": ((int, str), "7 or 8"),
    "stopbits": ((int, str), "1 or 2"),
    "timeout": ((int, float), "seconds, such as 0.5"),
    "retries": ((int,), "a whole number"),
    "echo": ((bool,), "true or false"),
    "rs485": ((bool,), "true or false"),
    "rs485_delays": ((str, int, float), 'milliseconds, such as 2 or "1,2"'),
    "pause": ((int, float), "seconds, such as 0.05"),
    "connect_delay": ((int, float), "seconds, such as 0.5"),
    "reconnect_each": ((bool,), "true or false"),
    "lenient": ((bool,), "true or false"),
    # tls:// (Modbus/TCP Security): files beside this file unless absolute, as a map is
    "cert": ((str,), 'a certificate file (PEM), such as "client.pem" (beside this file unless absolute)'),
    "key": ((str,), 'its private key (PEM), such as "client.key" (beside this file unless absolute)'),
    "ca": ((str,), 'the CAs to trust (PEM), such as "plant-ca.pem" (beside this file unless absolute)'),
    "insecure": ((bool,), "true or false"),
    "server_name": ((str,), 'the name the server\'s certificate has, such as "plc7.plant.example"'),
    "map": (
        (str,),
        'a register map file, such as "pump.toml" (beside this file unless absolute), or a map\'s name, such as "sdm630"',
    ),
}
# Keys that name a file: read from the folder of the file that names them (a profile's, an
# inventory's), not from wherever mbtool happens to run.
PATH_KEYS = ("cert", "key", "ca", "map")


def beside(folder: Path, raw: str) -> Path:
    """A path a file names (a profile's, an inventory's): relative to that file's folder
    unless absolute, ~ expanded."""
    return folder / Path(raw).expanduser()


def _kind(value: object) -> str:
    return {bool: "true/false", int: "a number", float: "a number", str: "text"}.get(
        type(value), "a table or list"
    )


def config_path() -> Path:
    explicit = os.environ.get("MBTOOL_CONFIG")
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "mbtool" / "config.toml"


def read_toml(path: Path, what: str = "profile file") -> dict:
    """A TOML file (the config file, poll's inventory); RequestError (exit 2) naming the
    file for any problem."""
    import tomllib  # noqa: PLC0415 - 2 ms: -P and inventories only

    try:
        return tomllib.loads(read_whole(path, what).decode("utf-8"))
    except UnicodeDecodeError as error:
        raise RequestError(f"{path}: not UTF-8 text (byte {error.start}), as TOML must be") from None
    except tomllib.TOMLDecodeError as error:
        raise RequestError(f"{path}: not valid TOML: {error}") from None
    except RecursionError:  # tomllib parses arrays and tables inside one another recursively
        raise RequestError(f"{path}: nested too deeply (arrays or tables inside one another)") from None


def names() -> list[str]:
    """The profiles the config file defines, for completion: none if it cannot be read."""
    try:
        profiles = read_toml(config_path()).get("profiles", {})
    except RequestError:
        return []
    return sorted(profiles) if isinstance(profiles, dict) else []


def load(name: str, path: Path | None = None) -> dict:
    """The settings of profile ``name``; RequestError (exit 2) naming the file for any problem."""
    path = path or config_path()
    profiles = read_toml(path).get("profiles", {})
    if not isinstance(profiles, dict) or not isinstance(profiles.get(name, {}), dict):
        raise RequestError(f"{path}: [profiles.{name}] must be a table")
    if name not in profiles:
        known = ", ".join(sorted(profiles)) or "none"
        raise RequestError(f"{path}: no profile {name} (profiles: {known})")
    settings = profiles[name]
    for key, value in settings.items():
        if key not in KEYS:
            raise RequestError(f"{path}: profiles.{name}.{key}: unknown key (known: {', '.join(KEYS)})")
        types, wanted = KEYS[key]
        # bool is an int to Python, not to TOML: true is no unit number
        if not isinstance(value, types) or (isinstance(value, bool) and bool not in types):
            raise RequestError(f"{path}: profiles.{name}.{key}: {_kind(value)}, where {key} takes {wanted}")
    return settings


def defaults(name: str) -> dict:
    """The profile's values for the current command's options that were left at their default.

    Keys the command has no option for are passed over: monitor takes a device's profile
    for its line settings and has no use for its unit or timeout.
    """
    ctx = click.get_current_context()
    path = config_path()
    settings = load(name, path)
    params = {param.name: param for param in ctx.command.params}
    changes = {}
    for key, raw in settings.items():
        if key not in params:
            continue
        source = ctx.get_parameter_source(key)
        if source not in (None, click.core.ParameterSource.DEFAULT):
            continue  # given on the command line or in the environment: that wins
        if key == "map" and isinstance(raw, str):
            from mbtool.library import is_name  # noqa: PLC0415 - a profile's map only

            if is_name(raw, path.parent):  # a map's name (sdm630): -m finds it as it finds any
                changes[key] = raw
                continue
        if key in PATH_KEYS and isinstance(raw, str):  # relative: from the config file's folder
            changes[key] = str(beside(path.parent, raw))
            continue
        changes[key] = _convert(params[key], key, raw, ctx, f"{path}: profiles.{name}.{key}")
    return changes


def _convert(param: click.Parameter, key: str, raw, ctx: click.Context, where: str):
    if key in ("echo", "rs485", "reconnect_each", "lenient", "insecure"):
        if not isinstance(raw, bool):
            raise RequestError(f"{where}: {raw} is not true or false")
        return raw
    if isinstance(raw, bool) or not isinstance(raw, str | int | float):
        raise RequestError(f"{where}: {raw} is not a string or number")
    if key in ("bytesize", "stopbits", "parity", "framer", "port", "rs485_delays", "server_name"):
        raw = str(raw)
    elif key in ("unit", "baud", "retries") and isinstance(raw, float):
        raise RequestError(f"{where}: {raw} is not a whole number")
    try:
        value = param.type.convert(raw, None, ctx)
    except click.BadParameter as error:
        raise RequestError(f"{where}: {error.message}") from None
    # The same conversions device_command makes from the option values.
    if key in ("bytesize", "stopbits"):
        return int(value)
    return value
