"""``mbtool ping``: is a device there, and how fast does it answer -- ping(8) for Modbus (issue 32).

One small request at a time (FC 03 of one register, or FC 08's echo carrying the sequence
number), one line for each reply or failure, and at the end ping(8)'s summary beside every
transaction's outcome as all of mbtool's summaries count them (``link.stats``).  An exception
is the device answering: it is alive.  A gateway's 0A or 0B is the gateway answering for a
device that did not (spec §3): that request is lost.
"""

from __future__ import annotations

import time

import click

from mbtool.cli.options import device_command
from mbtool.cli.param_types import ADDRESS, Choice, Number, PositiveFloat
from mbtool.cli.session import open_client
from mbtool.codec.data_access import ReadHoldingRegisters
from mbtool.codec.errors import ModbusException, RequestError, function_code_text
from mbtool.codec.serial_line import Diagnostics, DiagnosticSubFunction
from mbtool.durations import Durations
from mbtool.errors import KNOWN_ERRORS, ConnectionFailed, ExitCode, UsageError, Verdict
from mbtool.link.managed import Backoff, ManagedLink
from mbtool.link.scan import GATEWAY_EXCEPTIONS
from mbtool.link.stats import Stats, outcome_of, untimed_text

# What each --function asks: a read of one holding register, or the diagnostics echo.
FUNCTIONS = {"03": "read one holding register", "08": "diagnostics, return query data (echo)"}


@device_command(
    "ping", output=False, short_help="Is a device there, and how fast does it answer (like ping)."
)
@click.option(
    "-c", "--count", type=Number(1, 2**31, "count"), help="Stop after COUNT requests (default: until Ctrl-C)."
)
@click.option(
    "-i",
    "--interval",
    type=PositiveFloat(zero_ok=True),
    default=1.0,
    show_default=True,
    help="Seconds from one request to the next (0: back to back).",
)
@click.option(
    "--function",
    type=Choice(list(FUNCTIONS), aliases={"3": "03", "8": "08"}),
    default="03",
    show_default=True,
    help="03: read the holding register at --address; 08: the diagnostics echo (return query "
    "data), which carries the sequence number back.",
)
@click.option("--address", type=ADDRESS, default=0, show_default=True, help="The register FC 03 reads.")
@click.option("-q", "--quiet", is_flag=True, help="No line for each request: only the summary.")
def ping(connection, settings, count, interval, function, address, quiet):
    """Ask a device the same small question again and again, like ping(8): one line for each
    reply ("unit 1: seq=3 time=4.2 ms") or for what went wrong (timeout, corrupt, not ours,
    link lost), then the summary on stderr: sent, answered, lost and rtt min/avg/max/mdev,
    with every transaction's outcome.

    An exception reply counts as answered: the device is there. Exception 0A or 0B from a
    gateway counts as lost: the gateway answered, the device behind it did not. With
    --retries, a reply that took a retry is shown with the retries and counted as recovered.

    Exit 0 when any reply came, 3 when none did, 6 when none did because the link could not be
    opened or reached (130 when interrupted before the first).
    """
    ctx = click.get_current_context()
    if function == "08" and ctx.get_parameter_source("address") is not click.core.ParameterSource.DEFAULT:
        raise UsageError("--address is the register FC 03 reads; --function 08 reads none")
    request_for = _requests(function, address)
    unit = connection.unit
    if settings.dry_run:
        with open_client(connection, settings, "ping", then="then the same again every --interval") as client:
            client.execute(unit, request_for(1))
        return
    return Pinger(connection, settings, request_for, quiet).run(count, interval)


def _requests(function: str, address: int):
    """The request of each sequence number: FC 08's echo carries the number, so a late echo of
    an earlier one is told from its own (it is not ours)."""
    if function == "03":
        request = ReadHoldingRegisters(address, 1)
        return lambda seq: request

    return lambda seq: Diagnostics(DiagnosticSubFunction.RETURN_QUERY_DATA, (seq & 0xFFFF).to_bytes(2, "big"))


class Pinger:
    """The requests one after another, each shown as it ends, and the summary they add up to."""

    def __init__(self, connection, settings, request_for, quiet: bool) -> None:
        self.connection = connection
        self.settings = settings
        self.request_for = request_for
        self.quiet = quiet
        self.stats = Stats()  # every transaction's outcome
        self.alive = 0  # replies from the device itself: answers and its exceptions
        self.alive_rtt = Durations()  # their round trips, ping(8)'s rtt
        self.untimed = 0  # their replies whose round trip is not known (link.client's rtt)
        self.failure = ""  # the outcome of the last request that got no reply (link.stats)

    def run(self, count: int | None, interval: float) -> Verdict:
        connection, unit = self.connection, self.connection.unit
        request = self.request_for(1)
        if not self.quiet:
            what = f"{function_code_text(request.function_code)} {FUNCTIONS[f'{request.function_code:02d}']}"
            if request.function_code == 0x03:
                what += f" at {request.address}"
            click.echo(f"PING {connection.port} unit {unit}: {what}, timeout {connection.timeout:g} s")
        # The link is lost when it closes or breaks, and opened again at most once a timeout
        # (-i 0 against a device that is restarting is not a flood of connections).
        link = ManagedLink(
            lambda: open_client(connection, self.settings, "ping"), Backoff(connection.timeout), self.stats
        )
        # The first link is the command's: one that cannot be opened ends it (exit 6).
        link.open()
        last_sent = time.monotonic()
        interrupted = False
        try:
            while count is None or self.stats.transactions < count:
                seq = self.stats.transactions + 1
                if seq > 1:
                    _sleep_until(last_sent + interval)
                if link.client is None:
                    link.wait()
                    try:
                        link.open()
                    except ConnectionFailed as failure:
                        self._failed(seq, failure, None, 0)
                        self.stats.transaction(failure, 0)
                        last_sent = time.monotonic()
                        continue
                last_sent = time.monotonic()
                try:
                    link.execute(unit, self.request_for(seq))
                except (RequestError, UsageError):
                    raise  # the request itself is wrong: no later one can do better
                except (*KNOWN_ERRORS, OSError) as error:
                    self._failed(seq, error, link.rtt, link.attempts)
                else:
                    self._answered(seq, link.rtt, link.attempts)
        except KeyboardInterrupt:
            interrupted = True
        finally:
            link.close()
        return self._summary(interrupted)

    def _answered(self, seq: int, rtt: float | None, attempts: int, what: str = "") -> None:
        self.alive += 1
        if rtt is not None:
            self.alive_rtt.add(rtt)
        else:
            self.untimed += 1
        retried = f" (after {attempts - 1} {'retry' if attempts == 2 else 'retries'})" if attempts > 1 else ""
        self._line(seq, f"{what}{_time(rtt)}{retried}")

    def _failed(self, seq: int, error: BaseException, rtt: float | None, attempts: int) -> None:
        self.failure = outcome = outcome_of(error)
        if isinstance(error, ModbusException):
            code = f"exception {error.exception_code:02X} {error.name}"
            if error.exception_code in GATEWAY_EXCEPTIONS:
                # The gateway speaks for a device that did not answer (spec §3): lost.
                self._line(
                    seq, f"lost: {code} from the gateway" + (f" {_time(rtt)}" if rtt is not None else "")
                )
            else:
                self._answered(seq, rtt, attempts, code + " ")
            return
        self._line(seq, f"{outcome.replace('_', ' ')}: {error}")

    def _line(self, seq: int, text: str) -> None:
        if not self.quiet:
            click.echo(f"unit {self.connection.unit}: seq={seq} {text}")

    def _summary(self, interrupted: bool) -> Verdict:
        stats = self.stats
        sent = stats.transactions
        lost = 0.0 if not sent else round(100 * (sent - self.alive) / sent, 1)
        text = f"{sent} sent, {self.alive} answered, {lost:g}% lost"
        if self.alive:
            text += f", rtt {self.alive_rtt.text(('min', 'avg', 'max', 'mdev'))}{untimed_text(self.untimed)}"
        text += f"; {stats.outcomes_text()}"
        if interrupted:
            text = "interrupted; " + text
            if not sent:
                return Verdict(text, ExitCode.INTERRUPTED)
        if self.alive:
            return Verdict(text, ExitCode.OK)
        # No reply: 3, as ping(8) says "no reply", unless the link could not be reached at all
        # (the last request's failure), which is 6 here as in every command.
        return Verdict(text, ExitCode.CONNECTION if self.failure == "connection" else ExitCode.TIMEOUT)


def _time(rtt: float | None) -> str:
    """ping(8)'s "time=0.045 ms", "time=4.21 ms", "time=38.5 ms", "time=1203 ms": three figures;
    "untimed" for a reply whose arrival is not known (it came while mbtool was busy)."""
    if rtt is None:
        return "untimed"
    ms = rtt * 1000
    return f"time={ms:.{3 if ms < 1 else 2 if ms < 10 else 1 if ms < 100 else 0}f} ms"


def _sleep_until(when: float) -> None:
    wait = when - time.monotonic()
    if wait > 0:
        time.sleep(wait)
