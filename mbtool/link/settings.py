"""The link's settings, each once: its name, what it takes, its default, its help, the
transports it is for and where it is refused.

Everything that names a link setting is made from ``SETTINGS``: the command line's options
(``cli/options.py``), a profile's keys (``cli/profiles.py``), an inventory's link keys
(``plant/inventory.py``) and ``Connection``'s defaults (``link/connection.py``).  A value from
any of them is converted here, by its kind, so ``--parity even``, ``parity = "even"`` in a
profile and in an inventory mean one thing and are refused in one sentence.

Click-free: the command line wraps each kind in a click type (``cli/param_types.py``).
"""

from __future__ import annotations

from mbtool.codec.record import record
from mbtool.errors import UsageError

SERIAL = "serial"  # a serial port (or a pyserial URL): baud, parity, RTS
TLS = "tls"  # tls:// (Modbus/TCP Security): certificates


def parse_whole(text: str, what: str = "number") -> int:
    """Decimal or 0x hex (also 0o / 0b); leading zeros are decimal, as a user means them."""
    text = text.strip()
    try:
        if text.lstrip("+-").isdigit():
            return int(text, 10)
        return int(text, 0)
    except ValueError:
        shown = text or "(empty)"
        raise UsageError(f"{what} {shown} is not a number (decimal or 0x hex)") from None


# --- kinds: what a setting takes, from the command line's text or a file's TOML value --------


class Kind:
    """How a setting's value is read: ``convert`` takes the command line's text or a file's
    value and gives the setting's, or raises UsageError saying why not; ``toml``: the TOML
    types a file may give it."""

    toml: tuple[type, ...] = (str,)

    def convert(self, value):
        return value


class Whole(Kind):
    """A whole number in decimal or hex within [low, high]; ``what`` names it in messages."""

    toml = (int,)

    def __init__(self, low: int, high: int, what: str) -> None:
        self.low, self.high, self.what = low, high, what

    def convert(self, value):
        number = value if isinstance(value, int) else parse_whole(value, self.what)
        if not self.low <= number <= self.high:
            raise UsageError(f"{self.what} {number} is out of range {self.low}..{self.high}")
        return number


class Seconds(Kind):
    """Seconds, more than 0; with ``zero_ok`` also 0 (no pause, no delay)."""

    toml = (int, float)

    def __init__(self, zero_ok: bool = False) -> None:
        self.zero_ok = zero_ok

    def convert(self, value):
        try:
            number = float(value)
        except (TypeError, ValueError):
            raise UsageError(f"{value} is not a number of seconds") from None
        if number != number or number == float("inf") or number < 0 or (number == 0 and not self.zero_ok):
            least = "0 or more" if self.zero_ok else "more than 0"
            raise UsageError(f"must be {least} seconds, not {value}")
        return number


class OneOf(Kind):
    """One of ``choices`` in any case (the listed spelling is the value), or one of the
    ``aliases`` a field engineer says (parity none, even, odd); ``whole``: the choices are
    numbers (data bits, stop bits), given as text on the command line and either in a file."""

    def __init__(
        self, choices: tuple[str, ...], aliases: dict[str, str] | None = None, whole: bool = False
    ) -> None:
        self.choices, self.aliases, self.whole = choices, aliases or {}, whole
        self.toml = (int, str) if whole else (str,)
        self.spelling = {choice.lower(): choice for choice in choices}
        self.spelling.update((word.lower(), choice) for word, choice in self.aliases.items())

    def convert(self, value):
        choice = self.spelling.get(str(value).lower())
        if choice is None:
            listed = ", ".join(repr(choice) for choice in self.choices)
            raise UsageError(f"{str(value)!r} is not one of {listed}.")
        return int(choice) if self.whole else choice


class Flag(Kind):
    """On or off: an option without a value; true or false in a file."""

    toml = (bool,)

    def convert(self, value):
        if not isinstance(value, bool):
            raise UsageError(f"{value} is not true or false")
        return value


class Text(Kind):
    """Text as given: a target, a name."""

    def convert(self, value):
        return str(value)


class File(Text):
    """A file's path; a file (profile, inventory) that names one names it from its own folder."""


class Delays(Kind):
    """BEFORE[,AFTER] in milliseconds, as modpoll's -4 takes them; kept in seconds."""

    toml = (str, int, float)
    LIMIT_MS = 1000  # the kernel keeps these in milliseconds; a second is already absurd

    def convert(self, value):
        if isinstance(value, tuple):
            return value
        parts = str(value).split(",")
        try:
            delays = [float(part) for part in parts]
        except ValueError:
            raise UsageError(f"{value} is not BEFORE[,AFTER] in milliseconds") from None
        if len(delays) > 2 or not all(0 <= d <= self.LIMIT_MS for d in delays):
            raise UsageError(f"{value}: give BEFORE[,AFTER], each 0..{self.LIMIT_MS} ms")
        before, after = (delays + [0.0])[:2]
        return (before / 1000, after / 1000)


# --- the table ------------------------------------------------------------------------------


class Setting:
    """One setting of a link.  ``name``: the Connection field, the profile's and the
    inventory's key, the option's parameter; ``flags``: the option's spellings; ``wanted``: what
    a file should give, in words; ``transport``: SERIAL or TLS where it is only for one (""
    for every link); ``misplaced``: the sentence that refuses it on another transport, where
    it is refused ({option}, {scheme} and {port} filled in; "" where it is only unused).

    A plain class, not a record: every command makes the table as it starts, and a record's
    generic ``__init__`` would cost the one-shot read a hundredth of its start-up."""

    __slots__ = (
        "name", "kind", "default", "help", "flags", "wanted", "transport", "misplaced", "metavar",
        "show_default", "envvar",
    )  # fmt: skip

    def __init__(
        self,
        name: str,
        kind: Kind,
        default: object,
        help: str,
        flags: tuple[str, ...],
        wanted: str,
        transport: str = "",
        misplaced: str = "",
        *,
        metavar: str | None = None,
        show_default: bool = False,
        envvar: str | None = None,
    ) -> None:
        self.name, self.kind, self.default, self.help, self.flags = name, kind, default, help, flags
        self.wanted, self.transport, self.misplaced = wanted, transport, misplaced
        self.metavar, self.show_default, self.envvar = metavar, show_default, envvar

    def __repr__(self) -> str:
        return f"Setting({self.name!r})"

    @property
    def option(self) -> str:
        """The option's long spelling, as messages name it: --server-name."""
        return self.flags[-1]

    def read(self, value, key: str = ""):
        """A file's TOML value (a profile's, an inventory's), converted; UsageError saying why
        not, without where (the caller knows the file, the table and the key, ``key`` as the
        file spells it)."""
        self.check_type(value, key)
        return self.kind.convert(value)

    def check_type(self, value, key: str = "") -> None:
        """UsageError when a file's TOML value is not of a type this setting takes."""
        # bool is an int to Python, not to TOML: true is no unit number
        if not isinstance(value, self.kind.toml) or (isinstance(value, bool) and bool not in self.kind.toml):
            raise UsageError(f"{_kind(value)}, where {key or self.name} takes {self.wanted}")


def _kind(value: object) -> str:
    return {bool: "true/false", int: "a number", float: "a number", str: "text"}.get(
        type(value), "a table or list"
    )


SECURITY_WORDS = "(Modbus/TCP Security)"  # what a message says tls:// is
TLS_MISPLACED = "{option} is for tls:// targets " + SECURITY_WORDS + "; {port} is not one"
RS485_DRIVES = "--rs485 drives the RTS line of a serial port"  # what a message says it is for
RS485_MISPLACED = RS485_DRIVES + "; a {scheme}:// target has none"
FILE_BESIDE = " (beside this file unless absolute)"

# In the order a profile's keys are listed (man page); the options' order is their lists' below.
SETTINGS = {
    setting.name: setting
    for setting in (
        Setting(
            "port",
            Text(),
            None,
            "tcp://HOST[:PORT], tls://HOST[:PORT] (Modbus/TCP Security, port 802), udp://HOST[:PORT], "
            "rtu+udp://HOST:PORT, a serial device, socket://HOST:PORT, rfc2217://HOST:PORT, "
            "loop:// or sim:// (the built-in device).",
            ("-p", "--port"),
            'text, such as "/dev/ttyUSB0" or "tcp://10.0.0.5"',
            metavar="TARGET",
            envvar="MBTOOL_PORT",
        ),
        Setting(
            "unit",
            Whole(0, 255, "unit"),
            1,
            "Unit (slave) id; 0 broadcasts a write.",
            ("-u", "--unit"),
            "a whole number, 0..255",
            show_default=True,
            envvar="MBTOOL_UNIT",
        ),
        Setting(
            "framer",
            OneOf(("rtu", "ascii", "tcp")),
            None,  # tcp for tcp://, tls:// and udp://, rtu for everything else
            "Framing: tcp for tcp://, tls:// and udp:// targets, rtu otherwise.",
            ("--framer",),
            'text: "rtu", "ascii" or "tcp"',
        ),
        Setting(
            "baud",
            Whole(1, 4_000_000, "baud rate"),
            19200,
            "Serial baud rate (also sets the t3.5 silence).",
            ("-b", "--baud"),
            "a whole number, such as 9600",
            SERIAL,
            show_default=True,
        ),
        Setting(
            "parity",
            OneOf(("N", "E", "O"), aliases={"none": "N", "even": "E", "odd": "O"}),
            "E",
            "Serial parity: N, E or O (none, even, odd).",
            ("--parity",),
            'text: "N", "E" or "O" (or none, even, odd)',
            SERIAL,
            show_default=True,
        ),
        Setting(
            "bytesize",
            OneOf(("7", "8"), whole=True),
            8,
            "Serial data bits (ASCII mode classically uses 7).",
            ("--bytesize",),
            "7 or 8",
            SERIAL,
            show_default=True,
        ),
        Setting(
            "stopbits",
            OneOf(("1", "2"), whole=True),
            1,
            "Serial stop bits.",
            ("--stopbits",),
            "1 or 2",
            SERIAL,
            show_default=True,
        ),
        Setting(
            "timeout",
            Seconds(),
            1.0,
            "Seconds to wait for each reply.",
            ("-t", "--timeout"),
            "seconds, such as 0.5",
            show_default=True,
        ),
        Setting(
            "retries",
            Whole(0, 100, "retries"),
            0,
            "Times to resend after a timeout or a bad reply.",
            ("--retries",),
            "a whole number",
            show_default=True,
        ),
        Setting(
            "echo",  # a half-duplex adapter echoes every byte sent
            Flag(),
            False,
            "Strip the local echo of a half-duplex adapter.",
            ("--echo",),
            "true or false",
            SERIAL,
            "{option} strips a half-duplex serial adapter's echo; a {scheme}:// link has none",
        ),
        Setting(
            "rs485",  # drive RTS for the direction of a two-wire RS-485 line
            Flag(),
            False,
            "Drive RTS high while sending, for an RS-485 adapter without automatic direction "
            "(the kernel driver's RS-485 mode where it has one, else mbtool switches RTS).",
            ("--rs485",),
            "true or false",
            SERIAL,
            RS485_MISPLACED,
        ),
        Setting(
            "rs485_delays",  # seconds RTS leads and trails a frame
            Delays(),
            None,
            "RTS raised this long before the frame and held this long after it; implies --rs485.",
            ("--rs485-delays",),
            'milliseconds, such as 2 or "1,2"',
            SERIAL,
            RS485_MISPLACED,
            metavar="MS[,MS]",
        ),
        Setting(
            "pause",
            Seconds(zero_ok=True),
            0.0,
            "Seconds at least between a reply and the next request, for devices and gateways "
            "that drop requests sent back to back (polling, scan and multi-request commands).",
            ("--pause",),
            "seconds, such as 0.05",
        ),
        Setting(
            "connect_delay",
            Seconds(zero_ok=True),
            0.0,
            "Seconds to wait after connecting before the first request, for devices that drop "
            "a request sent right after the handshake.",
            ("--connect-delay",),
            "seconds, such as 0.5",
        ),
        Setting(
            "reconnect_each",
            Flag(),
            False,
            "Polling: close and reopen the link for every poll, for devices and gateways that "
            "serve one client or leak connections.",
            ("--reconnect-each",),
            "true or false",
        ),
        Setting(
            "lenient",
            Flag(),
            False,
            "Accept a Modbus TCP reply that breaks the spec harmlessly (bytes after a complete "
            "reply, a byte count that disagrees with whole data, another unit id echoed), with a warning.",
            ("--lenient",),
            "true or false",
        ),
        Setting(
            "cert",
            File(),
            None,
            "tls://: mbtool's client certificate (PEM, its chain after it): Modbus/TCP Security is mutual.",
            ("--cert",),
            'a certificate file (PEM), such as "client.pem"' + FILE_BESIDE,
            TLS,
            TLS_MISPLACED,
            metavar="FILE",
        ),
        Setting(
            "key",
            File(),
            None,
            "tls://: the certificate's private key (PEM) where --cert's file has none; an "
            "encrypted one's password is asked on the terminal or read from MBTOOL_KEY_PASSWORD.",
            ("--key",),
            'its private key (PEM), such as "client.key"' + FILE_BESIDE,
            TLS,
            TLS_MISPLACED,
            metavar="FILE",
        ),
        Setting(
            "ca",
            File(),
            None,
            "tls://: the CA certificates to trust (PEM), or a device's own certificate to trust "
            "that one self-signed device; default: the system's CAs.",
            ("--ca",),
            'the CAs to trust (PEM), such as "plant-ca.pem"' + FILE_BESIDE,
            TLS,
            TLS_MISPLACED,
            metavar="FILE",
        ),
        Setting(
            "insecure",
            Flag(),
            False,
            "tls://: do not check the server's certificate (a warning each run): anyone on the "
            "way can then read and change the traffic.",
            ("--insecure",),
            "true or false",
            TLS,
            TLS_MISPLACED,
        ),
        Setting(
            "server_name",
            Text(),
            None,
            "tls://: the name the server's certificate has, where it is not the host in -p.",
            ("--server-name",),
            'the name the server\'s certificate has, such as "plc7.plant.example"',
            TLS,
            TLS_MISPLACED,
            metavar="NAME",
        ),
    )
}

SERIAL_LINE = ("baud", "parity", "bytesize", "stopbits")  # serve's and monitor's too
USE = ("timeout", "retries", "echo", "pause", "connect_delay", "lenient", "rs485", "rs485_delays")
SECURITY = ("cert", "key", "ca", "insecure", "server_name")


def default(name: str):
    return SETTINGS[name].default


# --- a transport's settings: a record of the rows of the table for it ------------------------
# Written out so that a reader (and a type checker) sees them; tests/link/test_settings.py holds
# their fields to the rows of the table for their transport, and their defaults to the rows'.


@record
class SerialLine:
    """A serial link's settings (SERIAL's rows): the line's character and speed, the adapter's
    echo, and RTS driven for the direction of a two-wire RS-485 line."""

    baud: int = default("baud")
    parity: str = default("parity")
    bytesize: int = default("bytesize")
    stopbits: int = default("stopbits")
    echo: bool = default("echo")  # a half-duplex adapter echoes every byte sent
    rs485: bool = default("rs485")  # drive RTS for the direction of a two-wire RS-485 line
    rs485_delays: tuple[float, float] | None = default("rs485_delays")  # seconds RTS leads and trails a frame


@record
class TlsSettings:
    """A tls:// link's settings (TLS's rows, Modbus/TCP Security): what --cert, --key, --ca,
    --insecure and --server-name say."""

    cert: str | None = default("cert")  # the client's certificate (PEM), its chain after it
    key: str | None = default("key")  # its private key (PEM); None: in the cert file
    ca: str | None = default("ca")  # the CAs (or the device's own certificate) to trust; None: the system's
    insecure: bool = default("insecure")  # no check of the server's certificate
    server_name: str | None = default("server_name")  # the name the certificate must have; None: the host


# The record of each transport's settings, by the transport's name in the table.
RECORDS = {SERIAL: ("serial", SerialLine), TLS: ("tls", TlsSettings)}


# --- the checks that the master, serve and bridge share --------------------------------------


def misplaced(setting: Setting, port: str) -> UsageError:
    """The error for ``setting`` given for ``port``, a link of another transport."""
    scheme = port.partition("://")[0].lower()
    return UsageError(setting.misplaced.format(option=setting.option, scheme=scheme, port=port))


def not_for_tls(option: str, whose: str, rest: str) -> UsageError:
    """A certificate option where no side is tls://: ``whose`` the option is for (tls://
    targets, a tls:// server), ``rest`` what the user gave instead."""
    return UsageError(f"{option} is for {whose} {SECURITY_WORDS}{rest}")


def check_tls_framing(framing: str) -> None:
    """tls:// carries MBAP, whoever listens or connects."""
    if framing != "tcp":
        raise UsageError(f"Modbus/TCP Security carries MBAP: tls:// takes no --framer {framing}")


def check_data_bits(bytesize: int, framings) -> None:
    """An RTU character has 8 data bits (spec §2): a server or a gateway's serial side in RTU
    with 7 would answer nothing any master reads."""
    if bytesize == 7 and "rtu" in framings:
        raise UsageError("RTU frames carry 8 data bits (spec §2); 7 data bits are for --framer ascii")
