"""--rs485: RTS drives the direction of a two-wire line.

No RS-485 hardware is attached here, so the port is a fake that records what is done
to it (unit tests), and the end-to-end tests prove the option's contract on a real
pseudo-terminal, which has no RTS line at all: one clear error, nothing sent.
"""

from __future__ import annotations

import pytest
import serial
from helpers.checks import assert_one_error_line, expect_ok
from helpers.ptys import PTY_SERIAL_OPTS
from helpers.run import run_cli

from mbtool.errors import ConnectionFailed
from mbtool.link.transport import SerialSettings, SerialTransport


class FakePort:
    """Records writes, flushes, RTS changes and the RS-485 mode set on it, in order."""

    kernel_refuses = False  # the driver has no kernel RS-485 mode (most USB adapters)
    rts_refused = False  # the port has no RTS line (a pseudo-terminal)

    def __init__(self, log: list) -> None:
        self.log = log
        self._mode = None
        self.opened = False

    @property
    def rs485_mode(self):
        return self._mode

    @rs485_mode.setter
    def rs485_mode(self, settings) -> None:
        if settings is not None and self.kernel_refuses:
            raise ValueError("Failed to set RS485 mode: [Errno 25] Inappropriate ioctl for device")
        self._mode = settings
        self.log.append(("mode", settings))

    @property
    def rts(self):
        return None

    @rts.setter
    def rts(self, level: bool) -> None:
        if self.rts_refused and self.opened:  # pyserial only keeps the level until the port opens
            raise OSError(25, "Inappropriate ioctl for device")
        self.log.append(("rts", level))

    def write(self, data: bytes) -> int:
        self.log.append(("write", data))
        return len(data)

    def flush(self) -> None:
        self.log.append(("flush",))

    def open(self) -> None:
        self.opened = True
        self.log.append(("open",))

    def fileno(self) -> int:
        return -1

    def close(self) -> None:
        self.log.append(("close",))


class LocalPort(FakePort):
    """Looks like a local port to the transport: only those can have the kernel's RS-485 mode."""


LocalPort.__module__ = "serial.serialposix"


@pytest.fixture
def opened(monkeypatch):
    """opened(port_class, delays) -> (transport, log, sleeps) with serial_for_url faked."""

    def make(port_class, delays=(0.0, 0.0), **flags):
        log: list = []
        sleeps: list = []
        port = port_class(log)
        for name, value in flags.items():
            setattr(port, name, value)
        monkeypatch.setattr(serial, "serial_for_url", lambda url, **settings: port)
        monkeypatch.setattr(
            "mbtool.link.transport.time.sleep", lambda s: (sleeps.append(s), log.append(("sleep", s)))
        )
        transport = SerialTransport("/dev/ttyFAKE", SerialSettings(rs485=delays))
        return transport, log, sleeps

    return make


def test_without_kernel_mode_mbtool_raises_rts_around_each_frame(opened):
    transport, log, _ = opened(FakePort, (0.002, 0.003))
    transport.write(b"\x01\x03")
    assert log == [
        ("rts", False),  # low as the port opens: a raised RTS would hold the bus
        ("open",),
        ("rts", False),  # receiving until there is something to send
        ("rts", True),
        ("sleep", 0.002),
        ("write", b"\x01\x03"),
        ("flush",),  # the last stop bit is out before RTS drops
        ("sleep", 0.003),
        ("rts", False),
    ]


def test_rts_drops_even_when_the_write_fails(opened):
    transport, log, _ = opened(FakePort)

    def broken(data):
        raise serial.SerialException("device disconnected")

    transport.port.write = broken
    with pytest.raises(ConnectionFailed, match="cannot write"):
        transport.write(b"\x01")
    assert log[-1] == ("rts", False)


def test_kernel_mode_takes_the_delays_and_mbtool_leaves_rts_alone(opened):
    transport, log, sleeps = opened(LocalPort, (0.001, 0.004))
    transport.write(b"\x01\x03")
    (mode,) = [entry[1] for entry in log if entry[0] == "mode"]
    assert (mode.rts_level_for_tx, mode.rts_level_for_rx) == (True, False)
    assert (mode.delay_before_tx, mode.delay_before_rx) == (0.001, 0.004)
    assert [entry for entry in log if entry[0] == "rts"] == [("rts", False)]  # only as it opened
    assert sleeps == []


def test_a_driver_without_kernel_mode_falls_back_to_switching_rts(opened):
    transport, log, _ = opened(LocalPort, (0.0, 0.0), kernel_refuses=True)
    assert transport.port.rs485_mode is None  # forgotten, so later reconfigurations do not fail on it
    transport.write(b"\x01")
    assert [e for e in log if e[0] in ("rts", "write")] == [
        ("rts", False),
        ("rts", False),
        ("rts", True),
        ("write", b"\x01"),
        ("rts", False),
    ]


def test_a_port_without_rts_is_a_connection_error(opened):
    with pytest.raises(ConnectionFailed, match="cannot drive RTS of /dev/ttyFAKE for --rs485"):
        opened(FakePort, rts_refused=True)


def test_without_rs485_rts_is_never_touched(monkeypatch):
    log: list = []
    monkeypatch.setattr(serial, "serial_for_url", lambda url, **settings: FakePort(log))
    SerialTransport("/dev/ttyFAKE", SerialSettings()).write(b"\x01")
    assert log == [("open",), ("write", b"\x01"), ("flush",)]


# --- the command line ----------------------------------------------------------------


def test_on_a_pty_rs485_is_one_clear_error_and_nothing_is_sent(pty_pair):
    res = run_cli("read-holding-registers", "0", "2", "-p", pty_pair.mbtool_path, *PTY_SERIAL_OPTS, "--rs485")
    line = assert_one_error_line(res, 6)
    assert "cannot drive RTS" in line and "--rs485" in line
    assert pty_pair.sent_by_mbtool() == b""


def test_rs485_on_tcp_is_refused_before_connecting(silent_server):
    res = run_cli("read-holding-registers", "0", "2", "-p", silent_server.tcp_target, "--rs485")
    assert "tcp:// target has none" in assert_one_error_line(res, 2)
    assert silent_server.connections == 0


@pytest.mark.parametrize("delays", ["x", "1,2,3", "-1", "5000", "1,"])
def test_bad_delays_are_refused(delays):
    res = run_cli("read-holding-registers", "0", "2", "-p", "sim://", "--rs485-delays", delays)
    assert "--rs485-delays" in assert_one_error_line(res, 2)


def test_sim_accepts_rs485_so_a_cron_line_can_be_tried_first():
    res = expect_ok(
        run_cli("read-holding-registers", "0", "2", "-p", "sim://", "--rs485-delays", "1,2", "-o", "json")
    )
    assert '"values"' in res.stdout


def test_a_profile_can_turn_rs485_on(pty_pair, tmp_path):
    config = tmp_path / "config.toml"
    config.write_text(f'[profiles.bus]\nport = "{pty_pair.mbtool_path}"\nparity = "N"\nrs485 = true\n')
    res = run_cli("read-holding-registers", "0", "2", "-P", "bus", env={"MBTOOL_CONFIG": str(config)})
    assert "cannot drive RTS" in assert_one_error_line(res, 6)


def test_a_monitor_port_opens_with_rts_low(monkeypatch):
    log: list = []
    monkeypatch.setattr(serial, "serial_for_url", lambda url, **settings: FakePort(log))
    SerialTransport("/dev/ttyFAKE", SerialSettings(), listen_only=True)
    assert log == [("rts", False), ("open",)]  # never driving the bus, not even as it opens
