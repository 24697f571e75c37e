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

from mbtool.errors import UsageError
from mbtool.files import beside, read_toml
from mbtool.link.settings import SETTINGS, File, Setting

# A profile's map: not a link setting, but read -m's (and check's, write's...) map, named beside
# the device it is of.
MAP = Setting(
    "map",
    File(),
    None,
    "",
    ("--map",),
    'a register map file, such as "pump.toml" (beside this file unless absolute), or a map\'s name, such as "sdm630"',
)
# A profile's keys: every link setting (each the option's parameter name, and the Connection
# field it sets), and the map.
READERS = {name: setting for name, setting in SETTINGS.items()} | {"map": MAP}
# key -> the TOML types it takes, and how to say so (the man page lists them)
KEYS = {key: (setting.kind.toml, setting.wanted) for key, setting in READERS.items()}
# Keys that name a file: read from the folder of the file that names them (a profile's, an
# inventory's), not from wherever mbtool happens to run.
PATH_KEYS = tuple(key for key, setting in READERS.items() if isinstance(setting.kind, File))


def config_path() -> Path:
    explicit = os.environ.get("MBTOOL_CONFIG")
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "mbtool" / "config.toml"


def names() -> list[str]:
    """The profiles the config file defines, for completion: none if it cannot be read."""
    try:
        profiles = read_toml(config_path(), "profile file").get("profiles", {})
    except UsageError:
        return []
    return sorted(profiles) if isinstance(profiles, dict) else []


def load(name: str, path: Path | None = None) -> dict:
    """The settings of profile ``name``, as the file gives them, each of a type its key takes;
    UsageError (exit 2) naming the file for any problem."""
    path = path or config_path()
    profiles = read_toml(path, "profile file").get("profiles", {})
    if not isinstance(profiles, dict) or not isinstance(profiles.get(name, {}), dict):
        raise UsageError(f"{path}: [profiles.{name}] must be a table")
    if name not in profiles:
        known = ", ".join(sorted(profiles)) or "none"
        raise UsageError(f"{path}: no profile {name} (profiles: {known})")
    settings = profiles[name]
    for key, value in settings.items():
        if key not in READERS:
            raise UsageError(f"{path}: profiles.{name}.{key}: unknown key (known: {', '.join(READERS)})")
        try:
            READERS[key].check_type(value)
        except UsageError as error:
            raise UsageError(f"{path}: profiles.{name}.{key}: {error}") from None
    return settings


def defaults(name: str) -> dict:
    """The profile's values for the current command's options that were left at their default.

    Keys the command has no option for are passed over: monitor takes a device's profile
    for its line settings and has no use for its unit or timeout.
    """
    ctx = click.get_current_context()
    path = config_path()
    settings = load(name, path)
    params = {param.name for param in ctx.command.params}
    changes = {}
    for key, raw in settings.items():
        if key not in params:
            continue
        source = ctx.get_parameter_source(key)
        if source not in (None, click.core.ParameterSource.DEFAULT):
            continue  # given on the command line or in the environment: that wins
        if key == "map":
            from mbtool.library import is_name  # noqa: PLC0415 - a profile's map only

            if is_name(raw, path.parent):  # a map's name (sdm630): -m finds it as it finds any
                changes[key] = raw
                continue
        if key in PATH_KEYS:  # relative: from the config file's folder
            changes[key] = str(beside(path.parent, raw))
            continue
        try:
            changes[key] = READERS[key].read(raw)
        except UsageError as error:
            raise UsageError(f"{path}: profiles.{name}.{key}: {error}") from None
    return changes
