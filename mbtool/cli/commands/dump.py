"""``dump``: what a device holds, written to a file that ``mbtool serve --data`` loads
unchanged, so a dump is also a simulator of the device."""

from __future__ import annotations

import signal
import sys
import time
from functools import partial

import click
import tomli_w

from mbtool.cli.data_files import TABLE_SECTIONS, data_file
from mbtool.cli.options import device_command
from mbtool.cli.param_types import FilePath, Number
from mbtool.cli.session import open_client
from mbtool.cli.sinks.table import ProgressBar
from mbtool.cli.whole_file import WholeFile
from mbtool.codec.device_id import ReadDeviceIdentification
from mbtool.codec.errors import ModbusException, ProtocolError
from mbtool.codec.pdu import ExceptionCode
from mbtool.codec.serial_line import ReportSlaveId
from mbtool.codec.tables import table_named
from mbtool.errors import KNOWN_ERRORS, STOP_SIGNALS, ExitCode, NoResponse, UsageError, Verdict, exit_code_for
from mbtool.link.dump import Dumper, OutOfRequests, Span, TableDump, read_identification
from mbtool.words import counted


def parse_span(text: str):
    """TABLE:FIRST-LAST (holding:0-999), TABLE:ADDRESS, or TABLE alone (0-65535)."""
    name, _, where = text.partition(":")
    table = table_named(name.strip())
    if not where:
        return Span(table)
    first, dash, last = where.partition("-")
    try:
        low = int(first, 0)
        high = int(last, 0) if dash else low
    except ValueError:
        raise UsageError(f"--range {text}: write it as TABLE:FIRST-LAST, such as holding:0-999") from None
    if not 0 <= low <= high <= 0xFFFF:
        raise UsageError(f"--range {text}: addresses run 0..65535, FIRST no more than LAST")
    return Span(table, low, high)


def _text_or_bytes(value: bytes):
    try:
        text = value.decode("utf-8")
    except UnicodeDecodeError:
        return list(value)
    return text if text.isprintable() else list(value)


def _identity(execute) -> dict:
    """FC 17 and FC 43/14, when the device answers them: what serve --data replays, byte
    for byte (a run indicator that is neither 00 nor FF as its byte, no extra bytes as "",
    the conformity level, and exactly the objects the device has); ``refused`` lists those
    of the two it answered exception 01 (no such function), which the copy refuses too."""
    identity: dict = {}
    refused = []
    try:
        reply = execute(ReportSlaveId())
        run = reply.run_indicator if reply.run_indicator_byte is None else reply.run_indicator_byte
        identity |= {"slave_id": reply.slave_id, "run": run, "extra": _text_or_bytes(reply.extra)}
    except ModbusException as error:
        if error.exception_code == ExceptionCode.ILLEGAL_FUNCTION:
            refused.append(ReportSlaveId.function_code)  # Modbus TCP devices often have no FC 17
    except (ProtocolError, NoResponse):
        pass  # silence or a bad reply says nothing of the function: the copy keeps its own
    for read_code in (0x03, 0x02, 0x01):  # extended: every object; a lesser device may refuse it
        try:
            objects, conformity = read_identification(execute, read_code)
        except ModbusException as error:
            if error.exception_code == ExceptionCode.ILLEGAL_FUNCTION:
                refused.append(ReadDeviceIdentification.function_code)  # no FC 43/14 at all
                break
            continue
        except (ProtocolError, NoResponse):
            break
        if objects:
            identity["conformity"] = conformity
            identity["objects"] = {str(key): _text_or_bytes(value) for key, value in objects.items()}
        break
    if refused:
        identity["refused"] = refused
    return identity


@device_command("dump", output=False)
@click.argument("file", type=FilePath(dir_okay=False, allow_dash=True))
@click.option(
    "--range",
    "ranges",
    multiple=True,
    metavar="TABLE:FIRST-LAST",
    help="Dump only these (repeatable): coils, discrete, input or holding, with an address "
    "range such as holding:0-999. Default: all four tables, 0-65535 each.",
)
@click.option(
    "--max-requests",
    type=Number(1, 10**9, "requests"),
    help="Stop after N requests; the file keeps what was read, marked complete = false, "
    "and the exit status is 8 (partial) unless the dump finished within them.",
)
def dump(connection, settings, file, ranges, max_requests):
    """Dump a device's tables, and its identity, to FILE (- for stdout).

    FILE is TOML that mbtool serve --data loads unchanged: sparse, holding exactly the
    addresses the device has, so the dump serves as a copy of the device. Reads are as
    large as the spec allows; a read refused with exception 02 is narrowed until every
    address is known to be there or not (each missing address costs one request).
    Ctrl-C or SIGTERM keeps what was read so far, in a valid file marked complete =
    false; a second one while it is written is ignored. FILE is replaced only by a whole
    dump (written beside it, then renamed), and a FILE that cannot be written is an
    error before anything is read.
    """
    spans = [parse_span(text) for text in ranges] or [parse_span(name) for name in TABLE_SECTIONS]
    dumps = {span.table.name: TableDump(span.table) for span in spans}
    total = sum(span.size for span in spans)
    # A place that cannot be written fails here, before the device is read.
    output = None if file == "-" or settings.dry_run else WholeFile(file)
    began = time.monotonic()
    stopped, failure, identity, out_of_requests, dumper = "", None, {}, False, None
    try:
        with _Interrupts() as interrupts:
            try:
                with open_client(connection, settings, "Read Holding Registers") as client:
                    execute = partial(client.execute, connection.unit)

                    dumper = Dumper(execute, max_requests)
                    bar = ProgressBar(total, "dump") if sys.stderr.isatty() and not settings.dry_run else None
                    try:
                        for span in spans:
                            done = bar.done if bar else 0
                            progress = partial(bar.past, done) if bar else None
                            dumper.dump(span, dumps[span.table.name], progress)
                            if bar:
                                bar.at(done + span.size)
                        identity = _identity(execute)
                    except OutOfRequests:
                        stopped = f"stopped after {counted(dumper.requests, 'request')} (--max-requests)"
                        out_of_requests = True
                    except KNOWN_ERRORS as error:
                        if settings.dry_run:
                            raise
                        stopped, failure = f"stopped: {error}", error
                    finally:
                        if bar:
                            bar.close()
                    interrupts.hold()
            except KeyboardInterrupt:
                stopped = "interrupted"
            interrupts.hold()  # from here on a signal cannot stop the file being written
            if stopped == "interrupted" and (dumper is None or not dumper.requests):
                raise KeyboardInterrupt  # before anything was read: FILE stays as it was
            text = tomli_w.dumps(data_file(dumps.values(), identity, complete=not stopped))
            if output is None:
                sys.stdout.write(text)
            else:
                output.commit(text)
    finally:
        if output is not None:
            output.discard()
    assert dumper is not None  # made before the first read; a run that read nothing ended above
    found = ", ".join(f"{name} {d.count}" + (" (absent)" if d.absent else "") for name, d in dumps.items())
    refused = f" ({dumper.refused} refused: missing addresses)" if dumper.refused else ""
    summary = (
        f"dump: {found}; {counted(dumper.requests, 'request')}{refused} in {time.monotonic() - began:.1f} s"
    )
    if stopped:
        summary += f"; {stopped}: the file has what was read, marked complete = false"
    code = ExitCode.OK
    if stopped == "interrupted":
        code = ExitCode.INTERRUPTED
    elif out_of_requests:
        code = ExitCode.PARTIAL  # part of what was asked: a finished dump must not look like it
    elif failure is not None:
        code = exit_code_for(failure)
    return Verdict(summary, code)


class _Interrupts:
    """SIGINT, SIGTERM and SIGHUP while a dump runs.  The first stops the reading (KeyboardInterrupt,
    as everywhere in mbtool); a later one, or any once ``hold`` is called, is ignored, as
    the dump ends once the file is written anyway: a second Ctrl-C, or a SIGTERM on top of
    one, must not lose what was read (issue 29).  A signal the shell left ignored (a
    background job's SIGINT) stays ignored."""

    SIGNALS = STOP_SIGNALS

    def __enter__(self) -> _Interrupts:
        self.raised = self.holding = False
        self.previous = {}
        for sig in self.SIGNALS:
            if signal.getsignal(sig) is not signal.SIG_IGN:
                self.previous[sig] = signal.signal(sig, self._arrived)
        return self

    def _arrived(self, signum, frame) -> None:
        if not (self.raised or self.holding):
            self.raised = True
            raise KeyboardInterrupt

    def hold(self) -> None:
        self.holding = True

    def __exit__(self, *exc) -> None:
        for sig, handler in self.previous.items():
            signal.signal(sig, handler)
