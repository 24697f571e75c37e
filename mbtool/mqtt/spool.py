"""QoS 1 messages kept while the broker is away, sent in order once it is back.

The spool holds at most ``size`` messages: past it the oldest is dropped, and counted.  With
a file (``spool = PATH``) every message is appended to it as it is kept, so a poller stopped
or killed while the broker was away sends them on its next start; the file is rewritten
whole when it holds twice the bound (the dropped ones), and emptied once they are sent.
"""

from __future__ import annotations

import base64
import json
import os
from collections import deque
from pathlib import Path
from typing import NamedTuple


class Message(NamedTuple):
    """A message to publish.  A tuple, not a record: one is made a poll, and a frozen
    record's fields, set one by one, cost several times a tuple's."""

    topic: str
    payload: bytes
    qos: int
    retain: bool


class Spool:
    def __init__(self, size: int, path: str | None = None) -> None:
        self.size = size
        self.path = Path(path) if path else None
        self.messages: deque[Message] = deque()
        self.kept = 0  # messages that came to the spool
        self.sent = 0  # messages taken from it to send
        self.dropped = 0  # the oldest, dropped past the bound
        self.lines = 0  # lines in the file
        if self.path is not None and self.path.exists():
            for line in self.path.read_text(errors="replace").splitlines():
                message = _parsed(line)
                if message is not None:
                    self._keep(message)
            self._rewrite()

    def __len__(self) -> int:
        return len(self.messages)

    def add(self, message: Message) -> None:
        self.kept += 1
        self._keep(message)
        if self.path is not None:
            if self.lines >= 2 * self.size:
                self._rewrite()
            else:
                with self.path.open("a") as file:
                    file.write(_line(message))
                self.lines += 1

    def take(self) -> list[Message]:
        """Every message kept, oldest first; the spool is empty after."""
        messages = list(self.messages)
        self.sent += len(messages)
        self.messages.clear()
        if self.path is not None:
            self._rewrite()
        return messages

    def _keep(self, message: Message) -> None:
        self.messages.append(message)
        if len(self.messages) > self.size:
            self.messages.popleft()
            self.dropped += 1

    def _rewrite(self) -> None:
        path = self.path
        assert path is not None  # a spool kept in a file
        temporary = path.with_name(path.name + ".new")
        temporary.write_text("".join(_line(message) for message in self.messages))
        os.replace(temporary, path)
        self.lines = len(self.messages)


def _line(message: Message) -> str:
    payload = base64.b64encode(message.payload).decode()
    return json.dumps([message.topic, payload, message.qos, message.retain]) + "\n"


def _parsed(line: str) -> Message | None:
    """A line of the file; None for one a crash cut short."""
    try:
        topic, payload, qos, retain = json.loads(line)
        return Message(topic, base64.b64decode(payload), int(qos), bool(retain))
    except (ValueError, TypeError):
        return None
