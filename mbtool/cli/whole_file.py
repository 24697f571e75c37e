"""A file replaced whole or not at all: ``dump``'s data file, ``sunspec --map``'s map.

The text goes to a temporary file beside FILE, made when the WholeFile is (a place that
cannot be written fails at once, before a device is read), and is renamed over FILE once
written and synced: FILE is the previous one or the new one, never a part of one (a
SIGKILL, a full disk, a file-size limit).  The new FILE keeps the previous one's
permissions.  (--textfile's writer, cli/sinks/prom.py, also sweeps the temporaries a killed run
left behind, as node_exporter reads that folder.)
"""

from __future__ import annotations

import contextlib
import errno
import os
import tempfile

from mbtool.errors import OutputFailed


class WholeFile:
    def __init__(self, path: str) -> None:
        self.path = path
        self.target = os.path.realpath(path)  # through a symbolic link: the link stays
        folder, name = os.path.split(self.target)
        self.temp: str | None = None  # the file beside it, until it takes FILE's place
        try:
            try:
                mode = os.stat(self.target).st_mode & 0o7777
                if not os.access(self.target, os.W_OK):
                    raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), path)
            except FileNotFoundError:
                umask = os.umask(0)
                os.umask(umask)
                mode = 0o666 & ~umask  # as open() would make it
            fd, self.temp = tempfile.mkstemp(prefix=f".{name}.", suffix=".part", dir=folder)
        except OSError as error:
            raise OutputFailed(path, error) from None
        self.file = os.fdopen(fd, "w", encoding="utf-8")
        os.fchmod(fd, mode)

    def commit(self, text: str) -> None:
        """Write ``text`` and put it in FILE's place; OutputFailed if it cannot be (FILE stays
        as it was)."""
        assert self.temp is not None, "committed twice, or after discard"
        try:
            self.file.write(text)
            self.file.flush()
            os.fsync(self.file.fileno())
            self.file.close()
            os.replace(self.temp, self.target)
        except OSError as error:
            raise OutputFailed(self.path, error) from None
        self.temp = None

    def discard(self) -> None:
        """Remove the temporary file unless it became FILE."""
        with contextlib.suppress(OSError):
            self.file.close()  # a write that failed may fail again here
        if self.temp is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.temp)
            self.temp = None

    def __enter__(self) -> WholeFile:
        return self

    def __exit__(self, *_) -> None:
        self.discard()
