"""mbtool's lines on stderr (events, warnings, errors) in the format a log collector reads:
``--log-format`` (poll, exporter) or ``MBTOOL_LOG_FORMAT`` (every command).

- ``text``: ``mbtool: MESSAGE``, for people (the default);
- ``telegraf``: the level's prefix Telegraf's ``inputs.execd`` reads (``E! ``, ``W! ``,
  ``I! ``), so it logs a device going offline as a warning and its return as information,
  not every line of its plugin's stderr as an error;
- ``logfmt`` and ``json``: one record a line, ``time``, ``level`` and ``msg`` first, then
  what the line is about (``device``, ``state``, ``reason``...).
"""

from __future__ import annotations

import os
import sys

import click

from mbtool.cli.sinks.json import to_json
from mbtool.cli.stamps import local_time

LOG_FORMATS = ("text", "telegraf", "logfmt", "json")
ENV_VAR = "MBTOOL_LOG_FORMAT"
META_KEY = "mbtool.log_format"  # the run's format, in its click context's meta
ERROR, WARNING, INFO = "error", "warning", "info"
TELEGRAF = {ERROR: "E! ", WARNING: "W! ", INFO: "I! "}


def log_format_option(command):
    """The option poll and the exporter take; noted in the run's context, where ``main`` finds
    it for the run's last line too."""

    def noted(ctx: click.Context, param: click.Parameter, value: str | None) -> None:
        if value is not None:
            ctx.meta[META_KEY] = value

    return click.option(
        "--log-format",
        type=click.Choice(LOG_FORMATS),
        envvar=ENV_VAR,
        expose_value=False,
        is_eager=True,
        callback=noted,
        help="The format of mbtool's lines on stderr: text (default), telegraf (E!/W!/I! level "
        "prefixes, for Telegraf's inputs.execd), logfmt or json (one record a line). "
        f"Environment: {ENV_VAR}.",
    )(command)


def run_log_format(meta: dict | None = None) -> str:
    """The run's format: its option's (``meta``: the click context's, else the current one's),
    else the environment's, else text."""
    if meta is None:
        ctx = click.get_current_context(silent=True)
        meta = ctx.meta if ctx is not None else {}
    fmt = meta.get(META_KEY) or os.environ.get(ENV_VAR, "text")
    return fmt if fmt in LOG_FORMATS else "text"


def log_line(level: str, message: str, log_format: str, **fields) -> str:
    """One line of stderr, without its newline."""
    if log_format == "text":
        return f"mbtool: {message}"
    if log_format == "telegraf":
        return f"{TELEGRAF[level]}mbtool: {message}"
    record = {"time": local_time(), "level": level, "msg": message} | {
        key: value for key, value in fields.items() if value is not None
    }
    return RECORDS[log_format](record)


def _logfmt(record: dict) -> str:
    return " ".join(f"{key}={_logfmt_value(value)}" for key, value in record.items())


RECORDS = {"json": to_json, "logfmt": _logfmt}  # a record a line, in each of the two formats


def log(level: str, message: str, fmt: str | None = None, **fields) -> None:
    """Write one line on stderr (``fmt``: the run's, found in its context when not given)."""
    print(log_line(level, message, fmt or run_log_format(), **fields), file=sys.stderr, flush=True)


def _logfmt_value(value) -> str:
    """A bare word where logfmt allows one, else a quoted string (JSON's escapes)."""
    text = value if isinstance(value, str) else to_json(value)
    if text and not any(c in text for c in ' ="\\') and text.isprintable():
        return text
    return to_json(str(text))
