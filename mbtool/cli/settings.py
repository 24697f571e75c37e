"""How a run shows what it does: one record, made from the options once and passed down.

The sinks (``cli/sinks/``, a module a format) and the poll loop's output take
what they need of it as arguments; no module keeps a setting a run wrote, so a second
command run in the same process (a test, a program embedding the commands) does what its
own options say.  The link's settings are ``link.connection.Connection``'s: this record
holds nothing of the link.
"""

from __future__ import annotations

from mbtool.codec.record import record

# Kept in the run's click context (``ctx.meta``, one a run) by -o's callback as soon as it
# is parsed: -o json was given, so a failure, even one in the options after it, is an
# object on stdout too (``program.main``).
ERRORS_AS_JSON = "mbtool.errors_as_json"


@record
class Settings:
    """What the output options of one run say."""

    output_format: str | None = None  # -o; None: table on a terminal, plain in a pipe
    csv_header: bool = True  # --no-header: CSV without its header row
    hex: bool = False  # --hex: every frame on stderr
    dry_run: bool = False  # --dry-run: show the frames, open nothing, send nothing
    measurement: str = "modbus"  # --measurement: -o influx's measurement, -o prom's prefix
    textfile: str = ""  # --textfile PATH: the Prometheus text goes there, atomically
    device: str = ""  # the profile's name (-P): a tag and a label of the metrics
    changes: bool = False  # --changes: polling prints the values that changed
    stats: str = "line"  # --stats: polling's summary as its line, or also as JSON
    mqtt: str = ""  # --mqtt URL: polling publishes each poll to that broker too
    name: str = ""  # --name: the device's name on the broker
