"""Thin transports: bytes in, bytes out, and nothing about Modbus.

* Serial lines through ``serial.serial_for_url``: device paths, ``socket://``
  and ``rfc2217://`` TCP-bridged serial ports, ``loop://`` (pyserial url handlers).
* Modbus TCP (``tcp://host[:port]``, default port 502): a plain socket.
* Modbus/TCP Security (``tls://host[:port]``, port 802): ``mbtool.link.tls``.
* Modbus over UDP (``udp://host[:port]``, ``rtu+udp://host:port``): ``mbtool.link.udp``.
* ``sim://``: the built-in simulated device, answering in-process (registered by
  the CLI: ``mbtool.link.register_scheme``).

Every read waits at most the time it is given (over TCP a wait of 50 ms or more,
timed by the kernel, may end a few milliseconds late); the client owns the clock.
"""

from __future__ import annotations

# The socket options' numbers, from the module socket.py wraps: socket itself costs 12 M
# instructions that no one-shot read need pay (link.base.connect makes its connection on _socket).
import _socket
import contextlib
import errno
import functools
import math
import os
import re
import select
import struct
import sys
import time
from collections.abc import Callable
from urllib.parse import urlsplit

from mbtool.codec.record import record, replace
from mbtool.codec.timing import character_bits
from mbtool.errors import ConnectionFailed, UsageError
from mbtool.link import IN_PROCESS
from mbtool.link.base import (  # noqa: F401  (the transports' shared part, named here as ever)
    FRAME_CHUNK,
    READ_CHUNK,
    WRITE_TIMEOUT,
    ConnectionClosed,
    Transport,
    _errno,
    connect,
    host_text,
    reason,
)
from mbtool.link.settings import TlsSettings, default

MODBUS_TCP_PORT = 502
# The kernel times socket waits in scheduler ticks (4 ms at HZ=250), so a wait shorter than
# this goes by select, which is exact; a longer one may end a tick or two late.
KERNEL_TIMER_MIN = 0.05
# A read's time left differs from the last by the work between reads: within this, the
# socket's timeout is left as it is rather than set again (a system call).
KERNEL_TIMER_SLACK = 0.005
DISCARD_BUDGET = 65536  # stale bytes dropped before a request, at most (a flood never ends)
# Windows leaves a socket whose receive timed out in an undefined state: waits go by select.
KERNEL_TIMED_READS = sys.platform != "win32"


@record
class SerialSettings:
    """What a serial port is opened with: the line's character and speed (SERIAL's rows of
    ``link.settings.SETTINGS``, with their defaults), and RTS's lead and trail when RTS sets
    the direction (``link.connection.rs485_direction``: the rows rs485 and rs485_delays)."""

    baud: int = default("baud")
    parity: str = default("parity")
    bytesize: int = default("bytesize")
    stopbits: int = default("stopbits")
    rs485: tuple[float, float] | None = None  # RTS lead and trail (s) when RTS sets the direction

    def __str__(self) -> str:
        return f"{self.baud} {self.bytesize}{self.parity}{self.stopbits}"

    @property
    def char_bits(self) -> int:
        """Bits one character takes on this line (its t3.5 is 3.5 of them)."""
        return character_bits(self.parity, self.bytesize, self.stopbits)


class SerialTransport(Transport):
    def __init__(self, url: str, settings: SerialSettings, listen_only: bool = False) -> None:
        """``listen_only``: a monitor's port, opened with RTS low and never written to."""
        import serial  # noqa: PLC0415 - pyserial: a serial line only

        self.description = url
        if url.lower().startswith("socket://"):
            # socket:// carries serial frames (RTU, ASCII); a Modbus TCP device, on whatever
            # port, ignores them or hangs up, and silence is all the user sees.
            port = "Modbus TCP's port: " if _port_of(url) == MODBUS_TCP_PORT else ""
            self.silence_hint = (
                f" ({port}socket:// sends RTU or ASCII frames; for a Modbus TCP device use tcp://)"
            )
        try:
            self.port = serial.serial_for_url(
                url,
                baudrate=settings.baud,
                parity=settings.parity,
                bytesize=settings.bytesize,
                stopbits=settings.stopbits,
                timeout=0,
                # A stuck UART (flow control) must not hang a write forever; url
                # handlers have no write timeout (rfc2217:// refuses the setting).
                # A local port is locked (flock) so that a second mbtool, or another program
                # that locks, cannot share it and split the replies between them.
                **({} if "://" in url else {"write_timeout": WRITE_TIMEOUT, "exclusive": True}),
                do_not_open=True,
            )
            if listen_only or settings.rs485 is not None:
                # RTS low as the port opens, not just after: where RTS enables the RS-485
                # driver, a raised RTS would hold the bus (pyserial raises it by default).
                self.port.rts = False
            self.port.open()
        # pyserial raises NotImplementedError for a setting a url handler does not support:
        # the port cannot be opened as asked, which is the user's to change (exit 6).
        except (serial.SerialException, OSError, ValueError, NotImplementedError, *_termios_error()) as error:
            if _errno(error) in (errno.EAGAIN, errno.EWOULDBLOCK):  # the lock is another's
                raise ConnectionFailed(
                    f"cannot open {url}: port busy (another program has it open)"
                ) from None
            if _errno(error) == errno.ENOENT and "://" not in url:
                raise ConnectionFailed(f"cannot open {url}: no such device ({_serial_ports()})") from None
            if _errno(error) == errno.EINVAL:
                # e.g. a pseudo-terminal refuses 7 data bits: name the settings it refused
                raise ConnectionFailed(f"cannot open {url}: it refused {settings}: {reason(error)}") from None
            raise ConnectionFailed(f"cannot open {url}: {reason(error)}") from None
        self._serial_error = serial.SerialException
        self._rts_switching: tuple[float, float] | None = None
        if settings.rs485 is not None:
            self._drive_direction(url, settings.rs485)
        # A local serial port has a descriptor to wait on; url handlers (socket://,
        # rfc2217://, loop://) wait inside pyserial with their own timeout.
        self._fd = self.port.fileno() if type(self.port).__module__ == "serial.serialposix" else None
        self._bridge = self.port._socket if _is_socket_url(self.port) else None

    def _drive_direction(self, url: str, delays: tuple[float, float]) -> None:
        """RS-485 direction by RTS: the kernel driver's RS-485 mode switches it in time with
        the UART's last stop bit; where the driver has none, mbtool switches RTS around each
        write, which costs the OS's timing slack (pyserial's serial.rs485 does the same)."""
        import serial.rs485  # noqa: PLC0415 - pyserial: --rs485 only

        before, after = delays
        if type(self.port).__module__ == "serial.serialposix":
            try:
                self.port.rs485_mode = serial.rs485.RS485Settings(
                    rts_level_for_tx=True,
                    rts_level_for_rx=False,
                    delay_before_tx=before,
                    delay_before_rx=after,
                )
                return
            except (ValueError, OSError):
                # No kernel RS-485 on this driver (most USB adapters): forget the setting,
                # or every later reconfiguration of the port would fail on it again.
                self.port.rs485_mode = None
        try:
            self.port.rts = False  # receive until there is something to send
        except (self._serial_error, OSError, ValueError) as error:
            self.port.close()
            raise ConnectionFailed(f"cannot drive RTS of {url} for --rs485: {reason(error)}") from None
        self._rts_switching = delays

    def write(self, data: bytes) -> None:
        written = False
        switching = self._rts_switching
        try:
            if switching:
                self.port.rts = True
                time.sleep(switching[0])
            try:
                self.port.write(data)
                written = True
                self.port.flush()  # a real UART: return when the last stop bit has left
                if switching:
                    time.sleep(switching[1])
            finally:
                if switching:
                    self.port.rts = False  # never leave the line driven: it would silence the bus
        # pyserial's flush lets termios.error through (tcdrain on a port that went away).
        except (self._serial_error, OSError, *_termios_error()) as error:
            if written:
                # The frame was handed over, then the port went away (a pty's other end
                # closed, an adapter unplugged): a hang-up, like one during the reply.
                raise ConnectionClosed(
                    f"{self.description} went away while sending ({reason(error)})"
                ) from None
            raise ConnectionFailed(f"cannot write to {self.description}: {reason(error)}") from None

    def read(self, timeout: float) -> bytes:
        try:
            if self._fd is None:
                self.port.timeout = max(timeout, 0)
                data = self.port.read(1)
                if data and self._bridge is not None:
                    # The rest of what has come, at once: socket://'s in_waiting says 0 or 1,
                    # so a reply behind garbage would otherwise come two bytes a read.
                    return data + self._bridge_bytes(self._bridge)
            else:
                # Wait on the descriptor: setting port.timeout would re-run tcsetattr on
                # every read, which some drivers (and Linux ptys) refuse or glitch on.
                ready, _, _ = select.select([self._fd], [], [], max(timeout, 0))
                data = self.port.read(1) if ready else b""
            if data and self.port.in_waiting:
                data += self.port.read(self.port.in_waiting)
            return data
        except (self._serial_error, OSError) as error:
            raise ConnectionClosed(f"{self.description}: {reason(error)}{self.silence_hint}") from None

    def input_waiting(self) -> bool:
        try:
            if self._fd is not None:
                return bool(select.select([self._fd], [], [], 0)[0])
            return self.port.in_waiting > 0
        except (self._serial_error, OSError):
            return True  # the read that follows says what is wrong

    @staticmethod
    def _bridge_bytes(bridge) -> bytes:
        """What socket:// holds now, in one recv (pyserial's socket.recv, without its loop)."""
        if not select.select([bridge], [], [], 0)[0]:
            return b""
        return bridge.recv(READ_CHUNK)  # b"" at the end: the next read says it closed

    def discard_input(self) -> bytes:
        try:
            if self._bridge is not None:
                return self._bridge_bytes(self._bridge)
            waiting = self.port.in_waiting
            return self.port.read(min(waiting, DISCARD_BUDGET)) if waiting else b""
        except (self._serial_error, OSError):
            return b""

    def close(self) -> None:
        bridge, self._bridge = self._bridge, None
        if bridge is not None:
            # pyserial's socket:// close sleeps 0.3 s "in case of quick reconnects", which
            # every one-shot command would pay on exit; close the bridge's socket at once.
            with contextlib.suppress(OSError):
                bridge.shutdown(_socket.SHUT_RDWR)
            bridge.close()
            self.port._socket = None
            self.port.is_open = False
            return
        self.port.close()


class TcpTransport(Transport):
    serial_line = False

    def __init__(self, host: str, port: int, timeout: float) -> None:
        self.description = f"tcp://{host}:{port}"
        self.sock = connect(host, port, timeout)
        # Blocking, with the kernel keeping time (SO_RCVTIMEO, SO_SNDTIMEO): a reply's wait is
        # then one recv system call, where select and recv, or Python's socket timeout (poll
        # and recv), make two a read -- a polling loop's largest cost after the device itself.
        self.sock.settimeout(None)
        # A struct timeval's fields are as wide as the kernel says: two longs, or two 64-bit
        # counts on a 32-bit system built with a 64-bit time_t.
        wide = len(self.sock.getsockopt(_socket.SOL_SOCKET, _socket.SO_RCVTIMEO, 16)) == 16
        self._timeval = "@qq" if wide else "@ll"
        self._set_timeout(_socket.SO_SNDTIMEO, WRITE_TIMEOUT)
        self._read_timeout = -1.0  # what SO_RCVTIMEO is set to
        self._chunk = FRAME_CHUNK  # what the next read takes at most
        # Whether bytes came while mbtool was busy (a poll's output written while its reply was
        # on its way): a poll object made once, where select builds descriptor sets from lists
        # and back on every call, twice the instructions (none on Windows: select there).
        self._waiting = select.poll() if hasattr(select, "poll") else None
        if self._waiting is not None:
            self._waiting.register(self.sock, select.POLLIN)
        # The request written and the reply read as a file's, on the socket's descriptor: os.write
        # and os.read take their arguments the fast way, where the socket's send and recv parse
        # them by format string, some 300 instructions a call and two calls a poll.  (Windows'
        # sockets are no files: their own methods there.)
        self._send: Callable[[bytes], int]
        self._recv: Callable[[int], bytes]
        if os.name == "posix":
            self._send = functools.partial(os.write, self.sock.fileno())
            self._recv = functools.partial(os.read, self.sock.fileno())
        else:
            self._send, self._recv = self.sock.send, self.sock.recv

    def write(self, data: bytes) -> None:
        send = self._send  # (called from a local: an instance's callable is no method to look up)
        try:
            sent = send(data)  # a Modbus frame fits an idle socket's buffer at once
            while sent < len(data):  # a peer slow to read: the rest as its buffer empties
                data = data[sent:]
                sent = send(data)
        except BlockingIOError:  # SO_SNDTIMEO passed: a peer that stopped reading
            raise ConnectionFailed(
                f"cannot send to {self.description}: the peer has not read for {WRITE_TIMEOUT:g} s"
            ) from None
        except OSError as error:
            raise ConnectionFailed(f"cannot send to {self.description}: {reason(error)}") from None

    def read(self, timeout: float) -> bytes:
        try:
            if timeout >= KERNEL_TIMER_MIN and KERNEL_TIMED_READS:
                if abs(timeout - self._read_timeout) > KERNEL_TIMER_SLACK:
                    self._set_timeout(_socket.SO_RCVTIMEO, timeout)
                    self._read_timeout = timeout
            elif not select.select([self.sock], [], [], max(timeout, 0))[0]:
                return b""  # else readable: data or the end, so the recv does not wait
            chunk, receive = self._chunk, self._recv  # (the callable from a local, as send's)
            data = receive(chunk)
        except BlockingIOError:  # SO_RCVTIMEO passed
            return b""
        except OSError as error:
            raise ConnectionClosed(f"{self.description}: {reason(error)}") from None
        if not data:
            raise ConnectionClosed(f"{self.description} closed the connection")
        # A read that filled its chunk left more behind, faster than replies come (a flood of
        # garbage): the next takes READ_CHUNK at once.  Else a frame's worth, which the
        # allocator has at hand, where a buffer of READ_CHUNK is made and cut down to the
        # reply every read (some 600 instructions).
        self._chunk = READ_CHUNK if len(data) == chunk else FRAME_CHUNK
        return data

    def input_waiting(self) -> bool:
        try:
            if self._waiting is not None:
                return bool(self._waiting.poll(0))  # readable, or the link hung up or broke
            return bool(select.select([self.sock], [], [], 0)[0])
        except (OSError, ValueError):
            return True  # the read that follows says what is wrong

    def discard_input(self) -> bytes:
        stale = bytearray()
        try:
            # What is already here, up to a budget: a peer that floods would never let a
            # drain that waits for quiet end (the client's deadline bounds what follows).
            while len(stale) < DISCARD_BUDGET and select.select([self.sock], [], [], 0)[0]:
                chunk = self._recv(READ_CHUNK)
                if not chunk:
                    break
                stale += chunk
        except OSError:  # the next read reports it
            pass
        return bytes(stale)

    def _set_timeout(self, option: int, seconds: float) -> None:
        """SO_RCVTIMEO or SO_SNDTIMEO: milliseconds on Windows, else a struct timeval."""
        if sys.platform == "win32":
            value = struct.pack("@L", max(1, round(seconds * 1000)))
        else:
            whole = int(seconds)
            value = struct.pack(self._timeval, whole, int((seconds - whole) * 1e6))
        self.sock.setsockopt(_socket.SOL_SOCKET, option, value)

    def close(self) -> None:
        self.sock.close()
        # The descriptor's number may be another file's from now on: the closed socket's own
        # methods, which fail as a closed socket does.
        self._send, self._recv = self.sock.send, self.sock.recv


@record
class Target:
    """What a ``--port`` names, checked before anything is opened."""

    # "tcp", "tls", "udp", "rtu+udp" (NETWORK_SCHEMES), "serial" (a device path or a pyserial
    # URL), or an in-process scheme ("sim")
    scheme: str
    host: str = ""  # a network link's, or a serial bridge's (socket://, rfc2217://)
    port: int = 0
    path: str = ""  # the device path or URL handed to pyserial
    handler: str = ""  # a pyserial URL's scheme (socket, loop...); "" for a device path

    def __str__(self) -> str:
        if self.scheme in NETWORK_SCHEMES:
            return f"{self.scheme}://{host_text(self.host)}:{self.port}"
        return self.path or f"{self.scheme}://"

    def normalised(self) -> Target:
        """One spelling of the link: the host as the resolver reads it (an IP address in its
        usual form, 127.0.0.01 and 127.1 being 127.0.0.1; a name in lower case) and a serial
        bridge without its options, so that two spellings of one link are one string."""
        if self.scheme in NETWORK_SCHEMES:
            return replace(self, host=canonical_host(self.host))
        if self.handler in BRIDGE_SCHEMES:
            host = canonical_host(self.host)
            return replace(self, host=host, path=f"{self.handler}://{host_text(host)}:{self.port}")
        return self

    def endpoint(self) -> tuple:
        """What the target opens, however it is spelled, so that two spellings of one link are
        told from two links: a host and port by the transport's protocol (tcp:// and tls:// to
        one port are one TCP endpoint, and so are socket:// and rfc2217://; no name is looked
        up, the loopback's being known: endpoint_host), a serial device by the path its symbolic links resolve to (/dev/serial/by-id/...
        is /dev/ttyUSB0), an in-process device by its text."""
        if self.scheme in NETWORK_SCHEMES:
            return (NETWORK_SCHEMES[self.scheme][1], endpoint_host(self.host), self.port)
        if self.handler in BRIDGE_SCHEMES:
            return ("TCP", endpoint_host(self.host), self.port)
        if self.scheme == "serial":
            return ("serial", self.path.lower() if self.handler else os.path.realpath(self.path))
        return (self.scheme, str(self))


IPV4_MAPPED = bytes(10) + b"\xff\xff"  # RFC 4291 2.5.5.2


def canonical_host(host: str) -> str:
    """A host as the resolver reads it: an IPv4 address as inet_aton reads it (getaddrinfo
    does the same for a numeric host: 127.1, 0x7f.0.0.1, 127.0.0.01 are 127.0.0.1), an IPv6
    address compressed in lower case (an IPv4-mapped one as its IPv4 address), any other name in lower case without a final dot."""
    if host and all(c in "0123456789abcdefxABCDEFX." for c in host):
        with contextlib.suppress(OSError):
            return _socket.inet_ntoa(_socket.inet_aton(host))
    if ":" in host:
        address, percent, zone = host.partition("%")
        with contextlib.suppress(OSError, ValueError):
            packed = _socket.inet_pton(_socket.AF_INET6, address)
            if packed[:12] == IPV4_MAPPED:  # ::ffff:a.b.c.d is the IPv4 host a.b.c.d
                return _socket.inet_ntoa(packed[12:])
            return _socket.inet_ntop(_socket.AF_INET6, packed) + percent + zone
    return host.lower().rstrip(".")


# The loopback as a name and as the addresses it stands for (RFC 6761 6.3: localhost, and
# any name under it, is the loopback; ::1 or 127.0.0.1, whichever the device listens on).
LOOPBACK = "localhost"
LOOPBACK_ADDRESSES = frozenset({"127.0.0.1", "::1"})


def endpoint_host(host: str) -> str:
    """A host as an endpoint's: canonical_host, the loopback's names and addresses one, so
    that tcp://localhost and tcp://127.0.0.1 are one device's link, known without a lookup.
    Two devices on ::1 and 127.0.0.1 taken for one only take turns; one device taken for two
    would have two masters at once."""
    host = canonical_host(host)
    if host in LOOPBACK_ADDRESSES or host == LOOPBACK or host.endswith("." + LOOPBACK):
        return LOOPBACK
    return host


MODBUS_TLS_PORT = 802  # Modbus/TCP Security's registered port (MB-TCP-Security-v21)
# The schemes of links mbtool opens itself, with a host and a port: the port each defaults
# to (None: the port must be given) and the transport's protocol, for messages.
NETWORK_SCHEMES = {
    "tcp": (MODBUS_TCP_PORT, "TCP"),
    "tls": (MODBUS_TLS_PORT, "TCP"),  # Modbus/TCP Security: MBAP inside TLS
    "udp": (MODBUS_TCP_PORT, "UDP"),  # MBAP, one ADU a datagram
    "rtu+udp": (None, "UDP"),  # RTU frames in datagrams: serial device servers in UDP mode
}
# The network schemes whose frames are MBAP unless --framer says otherwise.
MBAP_SCHEMES = ("tcp", "tls", "udp")


# pyserial's URL handlers (serial.serial_for_url) that take a host and port, and those
# that take something else; any other scheme is a typo.
BRIDGE_SCHEMES = ("socket", "rfc2217")
OTHER_SERIAL_SCHEMES = ("loop", "spy", "alt", "hwgrep", "cp2110")


def schemes() -> list[str]:
    """Every scheme a --port may start with, for completion and messages."""
    return [*NETWORK_SCHEMES, *BRIDGE_SCHEMES, *IN_PROCESS, *OTHER_SERIAL_SCHEMES]


def target_forms() -> str:
    """What a ``--port`` may be, for messages."""
    in_process = "".join(f"{scheme}://, " for scheme in IN_PROCESS)
    return (
        "tcp://HOST[:PORT], tls://HOST[:PORT], udp://HOST[:PORT], rtu+udp://HOST:PORT, "
        f"socket://HOST:PORT, rfc2217://HOST:PORT, {in_process}or a serial device"
    )


# A host (and port) given where a serial device goes.  Compiled (1.6 M instructions) only for a
# device that is not there: re's cache keeps it from then on.
_HOST_LIKE = r"(\[[0-9A-Fa-f:.]+\]|localhost|[A-Za-z0-9-]+(\.[A-Za-z0-9-]+)+)(:[0-9]+)?|[A-Za-z0-9.-]+:[0-9]+"


def parse_target(text: str, listening: bool = False) -> Target:
    """The target a ``--port`` names; UsageError (exit 2, nothing opened) if it names none.

    ``listening``: a server's own address, where tcp:// port 0 means any free port."""
    scheme, sep, rest = text.partition("://")
    scheme = scheme.lower()
    if not sep:
        if not text:
            raise UsageError(f"an empty target: use {target_forms()}")
        if not os.path.exists(text) and re.fullmatch(_HOST_LIKE, text):
            raise UsageError(f"{text} is not a serial device; did you mean tcp://{text}?")
        return Target("serial", path=text)
    if scheme in NETWORK_SCHEMES:
        host, port = _host_and_port(text, rest, NETWORK_SCHEMES[scheme][0], 0 if listening else 1)
        return Target(scheme, host, port)
    if scheme in IN_PROCESS:
        return Target(scheme, path=f"{scheme}://")
    if scheme in BRIDGE_SCHEMES:
        # pyserial takes options after "?" (socket://host:port?logging=debug): keep them.
        address, _, options = rest.partition("?")
        host, port = _host_and_port(text, address, None, 1)
        _check_serial_options(text, scheme, options)
        return Target("serial", host, port, path=text, handler=scheme)
    if scheme in OTHER_SERIAL_SCHEMES:
        if scheme == "hwgrep":  # hwgrep://REGEXP&option...: the regular expression first
            pattern, _, options = rest.partition("&")
            try:
                re.compile(pattern)
            except re.error as error:
                raise UsageError(f"{text}: {pattern!r} is no regular expression ({error})") from None
        else:
            options = urlsplit(text).query
        _check_serial_options(text, scheme, options)
        return Target("serial", path=text, handler=scheme)
    raise UsageError(f"unknown scheme {scheme}:// in {text}: use {target_forms()}")


LOG_LEVELS = ("debug", "info", "warning", "error")
# The options each of pyserial's URL handlers takes (its from_url), and what a value must be:
# one of a tuple, a number (float, or int for hwgrep's n, the Nth port found from 2 on), any
# text (str), or None for a flag.  pyserial meets some typos with KeyError or re.error, an
# internal error to mbtool: checked here, a typo is bad input (exit 2), with nothing opened.
SERIAL_URL_OPTIONS: dict[str, dict[str, tuple[str, ...] | type | None]] = {
    "socket": {"logging": LOG_LEVELS},
    "rfc2217": {"logging": LOG_LEVELS, "ign_set_control": None, "poll_modem": None, "timeout": float},
    "loop": {"logging": LOG_LEVELS},
    "spy": {"file": str, "color": None, "raw": None, "all": None},
    "alt": {"class": str},
    "hwgrep": {"n": int, "skip_busy": None},
    "cp2110": {},
}


def _check_serial_options(text: str, scheme: str, options: str) -> None:
    """UsageError unless ``options`` (a=1&b) are options pyserial's ``scheme``:// takes."""
    takes = SERIAL_URL_OPTIONS[scheme]
    known = ", ".join(takes) or "none"
    for option in filter(None, options.split("&")):
        name, equals, value = option.partition("=")
        if name not in takes:
            raise UsageError(f"{text}: {scheme}:// takes no option {name!r} (its options: {known})")
        kind = takes[name]
        if isinstance(kind, tuple) and value not in kind:
            raise UsageError(f"{text}: {name} is one of {', '.join(kind)}")
        if kind is str and not value:
            raise UsageError(f"{text}: {name} needs a value ({name}=...)")
        if kind is int or kind is float:
            try:
                number = kind(value)
            except ValueError:
                number = math.nan
            if not (math.isfinite(number) and number >= (2 if kind is int else 0)):
                lowest = "a whole number, 2 or more" if kind is int else "a number of seconds"
                raise UsageError(f"{text}: {name}={value}: expected {lowest}")


def _host_and_port(text: str, rest: str, default: int | None, lowest: int) -> tuple[str, int]:
    rest = rest.rstrip("/")
    if rest.startswith("["):  # [::1]:502
        host, bracket, port_text = rest[1:].partition("]")
        if not bracket or port_text[:1] not in ("", ":"):
            raise UsageError(f"{text}: an IPv6 address goes in brackets, as in tcp://[::1]:502")
        port_text = port_text[1:]
    else:
        host, _, port_text = rest.rpartition(":") if ":" in rest else (rest, "", "")
        if ":" in host:
            raise UsageError(f"{text}: an IPv6 address goes in brackets, as in tcp://[::1]:502")
    scheme = text.split("://", 1)[0].lower()
    if not host:
        raise UsageError(f"no host in {text} (expected {scheme}://HOST{'[:PORT]' if default else ':PORT'})")
    if not port_text:
        if default is None:
            raise UsageError(f"no port in {text} (expected {scheme}://HOST:PORT)")
        return host, default
    if not port_text.isascii() or not port_text.isdigit() or not lowest <= int(port_text) <= 65535:
        protocol = NETWORK_SCHEMES.get(scheme, (None, "TCP"))[1]
        raise UsageError(f"bad port {port_text} in {text}: a {protocol} port is {lowest}..65535")
    return host, int(port_text)


def open_transport(
    target: str, settings: SerialSettings, timeout: float, framer: str | None, tls: TlsSettings | None = None
) -> Transport:
    """Open the link a ``--port`` target names (checked first: a bad one opens nothing);
    ``tls``: the certificates of a tls:// link (None: the defaults, the system's CAs)."""
    where = parse_target(target)
    if where.scheme == "tls":
        from mbtool.link.tls import TlsTransport  # noqa: PLC0415 - ssl, 6 ms: tls:// only

        return TlsTransport(where.host, where.port, timeout, tls or TlsSettings())
    if where.scheme in ("udp", "rtu+udp"):
        from mbtool.link.udp import UdpTransport  # noqa: PLC0415 - socket, 14 M instructions: udp:// only

        return UdpTransport(where.scheme, where.host, where.port)
    if where.scheme == "tcp":
        link = TcpTransport(where.host, where.port, timeout)
        # Serial frames chosen over tcp:// and only silence back: a Modbus TCP device ignores
        # RTU and ASCII frames.  Silence to MBAP is a plain timeout: an RTU-over-TCP gateway
        # is named only when bytes come back that are an RTU frame (the TCP framer's _not_mbap).
        if framer not in (None, "tcp"):
            link.silence_hint = (
                f" (--framer {framer} sends serial frames; for a Modbus TCP device leave --framer out)"
            )
        return link
    if where.scheme in IN_PROCESS:
        return IN_PROCESS[where.scheme](framer or "rtu")
    return SerialTransport(where.path, settings)


def _port_of(url: str) -> int | None:
    try:
        return urlsplit(url).port
    except ValueError:  # pyserial says what is wrong with the URL
        return None


def default_framer(target: str) -> str:
    """tcp (MBAP) for tcp://, tls:// and udp://; rtu for everything else (serial lines,
    bridges, rtu+udp://, sim://)."""
    return "tcp" if target.lower().startswith(tuple(f"{scheme}://" for scheme in MBAP_SCHEMES)) else "rtu"


def is_network(target: str) -> bool:
    """A tcp://, tls://, udp:// or rtu+udp:// target: no serial line of mbtool's own (no echo,
    no RTS), whatever it carries."""
    return target.lower().partition("://")[0] in NETWORK_SCHEMES and "://" in target


def _is_socket_url(port) -> bool:
    return type(port).__module__ == "serial.urlhandler.protocol_socket"


def _serial_ports() -> str:
    """The serial ports this machine has, for a user who named one it has not."""
    try:
        from serial.tools.list_ports import comports  # noqa: PLC0415 - pyserial: a missing port only

        ports = sorted(port.device for port in comports())
    except (ImportError, OSError):
        ports = []
    if not ports:
        return "no serial ports found here"
    shown = ", ".join(ports[:8]) + (f" and {len(ports) - 8} more" if len(ports) > 8 else "")
    return f"serial ports here: {shown}"


def _termios_error() -> tuple[type[Exception], ...]:
    """termios.error: what pyserial lets through when a port refuses its settings."""
    try:
        import termios  # noqa: PLC0415 - a refused serial setting only; not on Windows
    except ImportError:  # not on Windows
        return ()
    return (termios.error,)
