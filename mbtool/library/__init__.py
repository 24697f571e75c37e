"""The device library: register maps of common devices, shipped with mbtool (issue 43).

``maps/NAME.toml`` is a device's register map, its ``[device]`` header saying what the
device is and how ``mbtool identify`` recognises it (registermap/header.py); ``twins/NAME.toml``
is a ``serve --data`` file holding plausible values at that device's registers, and only
those (``sparse``), so a read across a register the device does not have gets exception 02
as from the device.  docs/maps-library.md says how to add one.

A map is named on the command line (``-m sdm630``), in an inventory (``map = "sdm630"``) and
in an exporter's scrape (``module=sdm630``) the same way, by ``resolve_map``: a path is a path,
as it always was; a name is looked up in the user's folders first (those the command gives:
``--maps DIR``, the inventory's folder; then ``$XDG_CONFIG_HOME/mbtool/maps``), so a map of
one's own can shadow the library's, and then here.
"""

from __future__ import annotations

import os
from pathlib import Path

from mbtool.registermap.load import MapError, RegisterMap, load_map

LIBRARY = Path(__file__).parent
MAPS = LIBRARY / "maps"
TWINS = LIBRARY / "twins"
SUFFIXES = (".toml", ".csv")


def user_folder() -> Path:
    """Where a user keeps maps of their own: $XDG_CONFIG_HOME/mbtool/maps."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "mbtool" / "maps"


def is_name(text: str, base: Path = Path()) -> bool:
    """A map's name (sdm630) rather than a file's path (meter.toml, maps/pump): no folder,
    no suffix, and no file of that name in ``base`` (such a file was always read as a map)."""
    return (
        bool(text)
        and "/" not in text
        and os.sep not in text
        and not text.lower().endswith(SUFFIXES)
        and not (base / text).is_file()
    )


def library_names() -> list[str]:
    """The names of the maps mbtool ships, sorted."""
    return sorted(path.stem for path in MAPS.glob("*.toml"))


def twin_path(name: str) -> Path:
    """The ``serve --data`` file of a library map."""
    return TWINS / f"{name}.toml"


def folders(extra: list[Path] | tuple = ()) -> list[Path]:
    """Where a name is looked up, first to last: the command's own folders, the user's, the library."""
    return [*extra, user_folder(), MAPS]


def find_named(name: str, extra: list[Path] | tuple = ()) -> Path | None:
    """The first NAME.toml or NAME.csv in ``folders(extra)``; None if there is none."""
    for folder in folders(extra):
        for suffix in SUFFIXES:
            path = folder / f"{name}{suffix}"
            if path.is_file():
                return path
    return None


def resolve_map(text: str, extra: list[Path] | tuple = (), base: Path = Path()) -> Path:
    """The file a map's path (relative to ``base``, ~ expanded) or name stands for; MapError
    (one line, with the nearest names) for a name found nowhere."""
    if not is_name(text, base):
        return base / Path(text).expanduser()
    path = find_named(text, extra)
    if path is not None:
        return path
    import difflib  # noqa: PLC0415 - 0.8 ms: an unknown name only

    known = {p.stem for folder in folders(extra) if folder.is_dir() for p in folder.iterdir()}
    known = {name for name in known if not name.startswith(".")}
    near = difflib.get_close_matches(text, sorted(known), n=3, cutoff=0.5)
    hint = f"; nearest: {', '.join(near)}" if near else ""
    places = ", ".join(str(folder) for folder in folders(extra)[:-1])
    raise MapError(
        f"no map named {text} (in {places} nor mbtool's library){hint}; mbtool maps list shows the library"
    )


def signatures(extra: list[Path] | tuple = ()) -> dict:
    """name -> DeviceHeader of every map that has a signature, in the user's folders and the
    library (a user's map shadows the library's of its name): what identify judges."""
    out = {}
    for folder in reversed(folders(extra)):  # the first folder's map of a name wins
        for path in sorted(folder.glob("*.toml")) if folder.is_dir() else ():
            header = load_map(path).header
            if header is not None and header.signature:
                out[path.stem] = header
            else:
                out.pop(path.stem, None)
    return dict(sorted(out.items()))


def load_named_map(text: str, extra: list[Path] | tuple = ()) -> RegisterMap:
    """The register map a path or a name stands for (``-m``), loaded and checked."""
    return load_map(resolve_map(text, extra))
