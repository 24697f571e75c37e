"""The files a user names for mbtool to read whole: register maps, poll's inventories, serve's
--data files, profiles.  One rule for all of them: a regular file, at most MAX_FILE_BYTES;
a TOML one (the config file, an inventory) is parsed here too, and a path it names is read
from its folder.

A character device (/dev/zero) read whole grows memory until the kernel kills the process, and
a FIFO that nobody writes waits for ever, on its opening and on its reading; neither is a
file to load.  The check is on the opened file (fstat), not on the name, so nothing can be
swapped in between; the FIFO is opened without blocking, so its opening returns at once.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from mbtool.errors import UsageError

# Far above any real map, inventory or profile, and above a data file of every address of all
# four tables (about 2 MB as dump writes it); parsing a file of this size takes seconds.
MAX_FILE_BYTES = 16 << 20

_KINDS = {
    stat.S_ISCHR: "a character device",
    stat.S_ISBLK: "a block device",
    stat.S_ISFIFO: "a FIFO",
    stat.S_ISSOCK: "a socket",
    stat.S_ISDIR: "a directory",
}


def read_whole(path: str | os.PathLike, what: str) -> bytes:
    """The bytes of the file at ``path``; UsageError (exit 2) naming ``what`` it is meant to
    be and the path when it cannot be read, is not a regular file or is too large."""
    try:
        descriptor = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    except OSError as error:
        raise UsageError(f"cannot read {what} {path}: {error.strerror or error}") from None
    try:
        mode = os.fstat(descriptor).st_mode
        if not stat.S_ISREG(mode):  # before a file object is made of it: a directory's refuses
            kind = next((name for test, name in _KINDS.items() if test(mode)), "not a file")
            raise UsageError(f"cannot read {what} {path}: not a regular file ({kind})")
        with open(descriptor, "rb", closefd=False) as file:
            data = file.read(MAX_FILE_BYTES + 1)  # a file that grows meanwhile is read no further
    except OSError as error:
        raise UsageError(f"cannot read {what} {path}: {error.strerror or error}") from None
    finally:
        os.close(descriptor)
    if len(data) > MAX_FILE_BYTES:
        raise UsageError(
            f"cannot read {what} {path}: larger than {MAX_FILE_BYTES >> 20} MiB, too large to be one"
        )
    return data


def read_toml(path: Path, what: str) -> dict:
    """A TOML file (the config file, poll's inventory); UsageError (exit 2) naming the file for
    any problem."""
    import tomllib  # noqa: PLC0415 - 2 ms: -P and inventories only

    try:
        return tomllib.loads(read_whole(path, what).decode("utf-8"))
    except UnicodeDecodeError as error:
        raise UsageError(f"{path}: not UTF-8 text (byte {error.start}), as TOML must be") from None
    except tomllib.TOMLDecodeError as error:
        raise UsageError(f"{path}: not valid TOML: {error}") from None
    except RecursionError:  # tomllib parses arrays and tables inside one another recursively
        raise UsageError(f"{path}: nested too deeply (arrays or tables inside one another)") from None


def beside(folder: Path, raw: str) -> Path:
    """A path a file names (a profile's, an inventory's): relative to that file's folder
    unless absolute, ~ expanded."""
    return folder / Path(raw).expanduser()
