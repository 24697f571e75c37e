"""Modbus/TCP Security (``tls://HOST[:802]``): MBAP inside TLS 1.2 or newer.

The MODBUS/TCP Security specification (MB-TCP-Security-v21) puts the Modbus TCP ADU, as it
is, inside TLS on port 802, asks for TLS 1.2 at least, and makes authentication mutual: the
client presents an X.509 certificate too, and the server may read a role from it
(``mbtool.link.x509``) to decide what the client may do.

Here: the contexts both sides use (``client_context``, ``server_context``, built from files
the user names, an encrypted key's password read from ``MBTOOL_KEY_PASSWORD`` or asked on the
terminal), the master's transport (``TlsTransport``), and the one line that says why a
handshake failed (``handshake_failure``).  A file that cannot be used is the user's to fix
(UsageError, exit 2, nothing sent); a handshake that fails is the link's (ConnectionFailed,
exit 6).
"""

from __future__ import annotations

import functools
import os
import select
import socket
import ssl
import sys

from mbtool.errors import ConnectionFailed, UsageError
from mbtool.link import x509
from mbtool.link.base import (
    READ_CHUNK,
    WRITE_TIMEOUT,
    ConnectionClosed,
    Transport,
    connect,
    host_text,
    reason,
)
from mbtool.link.settings import TlsSettings

KEY_PASSWORD_VARIABLE = "MBTOOL_KEY_PASSWORD"

# OpenSSL's X509_V_ERR_* codes (x509_vfy.h) that a server's certificate fails with.
UNABLE_TO_GET_ISSUER_CERT = 2
CERT_NOT_YET_VALID = 9
CERT_HAS_EXPIRED = 10
DEPTH_ZERO_SELF_SIGNED_CERT = 18
SELF_SIGNED_CERT_IN_CHAIN = 19
UNABLE_TO_GET_ISSUER_CERT_LOCALLY = 20
HOSTNAME_MISMATCH = 62
IP_ADDRESS_MISMATCH = 64

NOT_TLS = "(a plain Modbus TCP port? use tcp://)"
MUTUAL = "Modbus/TCP Security is mutual: give --cert FILE --key FILE, signed by a CA the server trusts"
# The alerts a server sends when it refuses the client's certificate, by OpenSSL's reason.
REFUSALS = {
    "TLSV13_ALERT_CERTIFICATE_REQUIRED": f"the server requires a client certificate ({MUTUAL})",
    "SSLV3_ALERT_HANDSHAKE_FAILURE": "the server refused the handshake (it may require a client "
    f"certificate: {MUTUAL})",
    "TLSV1_ALERT_UNKNOWN_CA": "the server refused mbtool's client certificate: "
    "it does not trust the CA that signed it",
    "SSLV3_ALERT_BAD_CERTIFICATE": "the server refused mbtool's client certificate",
    "SSLV3_ALERT_CERTIFICATE_UNKNOWN": "the server refused mbtool's client certificate",
    "SSLV3_ALERT_UNSUPPORTED_CERTIFICATE": "the server refused mbtool's client certificate (unsupported)",
    "SSLV3_ALERT_CERTIFICATE_EXPIRED": "the server refused mbtool's client certificate: it has expired",
    "SSLV3_ALERT_CERTIFICATE_REVOKED": "the server refused mbtool's client certificate: it is revoked",
    "TLSV1_ALERT_ACCESS_DENIED": "the server denied access to mbtool's client certificate",
    "TLSV1_ALERT_PROTOCOL_VERSION": "the server speaks no TLS version mbtool does (1.2 or newer)",
    "UNSUPPORTED_PROTOCOL": "the server speaks no TLS version mbtool does (1.2 or newer)",
}
# What OpenSSL says when the bytes that come back are no TLS record at all.
NOT_TLS_REASONS = ("WRONG_VERSION_NUMBER", "RECORD_LAYER_FAILURE", "PACKET_LENGTH_TOO_LONG", "HTTP_REQUEST")


@functools.lru_cache(maxsize=8)
def client_context(settings: TlsSettings) -> ssl.SSLContext:
    """The context of a master's connections, made once a run (a poll's reconnects ask for
    a key's password once)."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.minimum_version = ssl.TLSVersion.TLSv1_2  # the specification's floor
    if settings.insecure:
        context.check_hostname = False
        context.verify_mode = ssl.CERT_NONE
    elif settings.ca:
        _trust(context, settings.ca)
        # A device's own certificate in --ca is trusted as it is, whoever signed it (pinning):
        # the chain may end at any certificate the user gave, not only at a root.
        context.verify_flags |= ssl.VERIFY_X509_PARTIAL_CHAIN
    else:
        context.load_default_certs(ssl.Purpose.SERVER_AUTH)
    if settings.key and not settings.cert:
        raise UsageError(f"--key {settings.key} goes with --cert FILE, the certificate it is the key of")
    if settings.cert:
        _identity(context, settings.cert, settings.key)
    return context


def server_context(cert: str | None, key: str | None, ca: str | None) -> ssl.SSLContext:
    """The context of ``serve`` and ``bridge --listen`` on tls://: a certificate of its own,
    and clients' certificates required, signed by ``ca`` (the specification's mutual
    authentication)."""
    if not cert:
        raise UsageError("serving on tls:// needs --cert FILE and --key FILE: the server's certificate")
    if not ca:
        raise UsageError(
            "serving on tls:// needs --ca FILE: the CA that signs the clients' certificates "
            "(Modbus/TCP Security is mutual)"
        )
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.verify_mode = ssl.CERT_REQUIRED
    _trust(context, ca)
    _identity(context, cert, key)
    return context


def _trust(context: ssl.SSLContext, ca: str) -> None:
    try:
        context.load_verify_locations(cafile=ca)
    except ssl.SSLError:
        raise UsageError(f"--ca {ca} holds no certificate in PEM") from None
    except OSError as error:
        raise UsageError(f"cannot read --ca {ca}: {reason(error)}") from None


def _identity(context: ssl.SSLContext, cert: str, key: str | None) -> None:
    for option, path in (("--cert", cert), ("--key", key)):
        if path is not None and not os.path.isfile(path):
            why = "not a file" if os.path.exists(path) else "No such file or directory"
            raise UsageError(f"cannot read {option} {path}: {why}")
    asked: list[str] = []

    def password() -> str:
        asked.append(key or cert)
        return key_password(key or cert)

    try:
        context.load_cert_chain(cert, key, password=password)
    except OSError as error:
        if isinstance(error, ssl.SSLError) and error.reason == "KEY_VALUES_MISMATCH":
            raise UsageError(f"--key {key} is not the key of --cert {cert}") from None
        if isinstance(error, ssl.SSLError) and asked:
            raise UsageError(
                f"cannot decrypt {asked[0]}: wrong password (${KEY_PASSWORD_VARIABLE})"
            ) from None
        if isinstance(error, ssl.SSLError):
            where = f"--cert {cert}" + (f" and --key {key}" if key else "")
            raise UsageError(f"{where}: not a certificate and its private key in PEM") from None
        raise UsageError(f"cannot read --cert {cert}: {reason(error)}") from None


def key_password(key: str) -> str:
    """An encrypted key's password: $MBTOOL_KEY_PASSWORD, else asked on the terminal."""
    given = os.environ.get(KEY_PASSWORD_VARIABLE)
    if given is not None:
        return given
    if not sys.stdin.isatty():
        raise UsageError(
            f"the key {key} is encrypted and there is no terminal to ask its password on: "
            f"set {KEY_PASSWORD_VARIABLE}"
        )
    import getpass  # noqa: PLC0415 - with termios, 0.4 ms: an encrypted key only

    try:
        return getpass.getpass(f"password for {key}: ")
    except EOFError:
        raise UsageError(f"no password given for {key}") from None


class TlsTransport(Transport):
    """A TLS connection to a Modbus/TCP Security server: its reads and writes carry
    plaintext ADUs (the --hex trace shows them), every wait bounded by the client's time."""

    serial_line = False

    def __init__(self, host: str, port: int, timeout: float, settings: TlsSettings) -> None:
        self.address = f"{host_text(host)}:{port}"
        self.description = f"tls://{self.address}"
        self.settings = settings
        context = client_context(settings)  # the files first: a bad one sends nothing
        raw = _connected(host, port, timeout)
        try:
            self.sock = context.wrap_socket(raw, server_hostname=settings.server_name or host)
        except (OSError, ValueError) as error:
            raw.close()
            raise ConnectionFailed(handshake_failure(error, host, port, timeout, settings)) from None
        self._timeout: float | None = None  # what the socket's timeout is set to
        self._replied = False  # bytes have come since the handshake

    def _wait(self, seconds: float | None) -> None:
        if seconds != self._timeout:
            self.sock.settimeout(seconds)
            self._timeout = seconds

    def _lost(self, error: BaseException | None) -> ConnectionFailed | ConnectionClosed:
        """What the end of the connection (``error``, or None for a clean one) means."""
        refusal = _refusal(error)
        if refusal:
            return ConnectionFailed(f"TLS handshake with {self.address} failed: {refusal}")
        if not self._replied:
            # TLS 1.3 has the server judge the client's certificate after the client's side of
            # the handshake is done; a server that drops the connection then, its alert lost
            # to the reset or never sent, looks like this from here.
            if self.settings.cert:
                maybe = (
                    f"the server may have refused mbtool's certificate ({self.settings.cert}): "
                    "is it signed by a CA the server trusts, and valid?"
                )
            else:
                maybe = f"the server may require a client certificate ({MUTUAL})"
            return ConnectionFailed(
                f"{self.description} closed the connection after the TLS handshake, before any reply: {maybe}"
            )
        if error is None or isinstance(error, ssl.SSLEOFError):
            return ConnectionClosed(f"{self.description} closed the connection")
        return ConnectionClosed(f"{self.description}: {_ssl_reason(error)}")

    def write(self, data: bytes) -> None:
        self._wait(WRITE_TIMEOUT)
        try:
            self.sock.sendall(data)
        except TimeoutError:
            raise ConnectionFailed(
                f"cannot send to {self.description}: the peer has not read for {WRITE_TIMEOUT:g} s"
            ) from None
        except (ssl.SSLError, ConnectionResetError, BrokenPipeError) as error:
            lost = self._lost(error)
            raise (lost if isinstance(lost, ConnectionFailed) else ConnectionFailed(str(lost))) from None
        except OSError as error:
            raise ConnectionFailed(f"cannot send to {self.description}: {reason(error)}") from None

    def read(self, timeout: float) -> bytes:
        try:
            if not self.sock.pending():  # else a record already decrypted: no wait
                self._wait(max(timeout, 0.0))
            data = self.sock.recv(READ_CHUNK)
        except (TimeoutError, ssl.SSLWantReadError, ssl.SSLWantWriteError):
            return b""
        except (ssl.SSLError, ConnectionResetError) as error:
            raise self._lost(error) from None
        except OSError as error:
            raise ConnectionClosed(f"{self.description}: {reason(error)}") from None
        if not data:
            raise self._lost(None)
        self._replied = True
        return data

    def input_waiting(self) -> bool:
        try:
            return bool(self.sock.pending()) or bool(select.select([self.sock], [], [], 0)[0])
        except (OSError, ValueError):
            return True

    def discard_input(self) -> bytes:
        stale = bytearray()
        self._wait(0.0)
        try:
            while len(stale) < READ_CHUNK:
                chunk = self.sock.recv(READ_CHUNK)
                if not chunk:
                    break
                stale += chunk
        except (ssl.SSLWantReadError, ssl.SSLWantWriteError):
            pass  # nothing more now
        except ssl.SSLError as error:
            if _refusal(error):  # the server's verdict on the certificate, come in the meantime
                raise self._lost(error) from None
        except OSError:  # the next read reports it
            pass
        return bytes(stale)

    def close(self) -> None:
        self.sock.close()


def handshake_failure(
    error: BaseException, host: str, port: int, timeout: float, settings: TlsSettings
) -> str:
    """One line saying why the handshake with ``host:port`` failed, and what to do."""
    return f"TLS handshake with {host_text(host)}:{port} failed: {_why(error, host, port, timeout, settings)}"


def _why(error: BaseException, host: str, port: int, timeout: float, settings: TlsSettings) -> str:
    if isinstance(error, ssl.SSLCertVerificationError):
        return _unverified(error, host, port, timeout, settings)
    if isinstance(error, TimeoutError):
        return f"no TLS handshake within {timeout:g} s {NOT_TLS}"
    if isinstance(error, ssl.SSLEOFError | ConnectionResetError | BrokenPipeError) or (
        isinstance(error, OSError) and error.errno is None and "EOF" in str(error)
    ):
        return f"the server closed the connection without a TLS answer {NOT_TLS}"
    if isinstance(error, ssl.SSLError):
        refusal = _refusal(error)
        if refusal:
            return refusal
        if error.reason in NOT_TLS_REASONS:
            return f"what came back is not TLS {NOT_TLS}"
    return _ssl_reason(error)


def _unverified(
    error: ssl.SSLCertVerificationError, host: str, port: int, timeout: float, settings: TlsSettings
) -> str:
    code = error.verify_code
    trusted = f"the --ca given ({settings.ca})" if settings.ca else "this system's CAs"
    if code == DEPTH_ZERO_SELF_SIGNED_CERT:
        return (
            f"the server's certificate is self-signed and not among {trusted}: to trust this device, "
            "give its certificate with --ca FILE"
        )
    if code in (UNABLE_TO_GET_ISSUER_CERT, UNABLE_TO_GET_ISSUER_CERT_LOCALLY, SELF_SIGNED_CERT_IN_CHAIN):
        return (
            f"the server's certificate is signed by a CA not among {trusted}: "
            "give the certificate of the CA that signed it with --ca FILE"
        )
    if code == CERT_HAS_EXPIRED:
        return "the server's certificate has expired (renew it on the device, or check this machine's clock)"
    if code == CERT_NOT_YET_VALID:
        return "the server's certificate is not valid yet (check this machine's clock and the device's)"
    if code in (HOSTNAME_MISMATCH, IP_ADDRESS_MISMATCH):
        name = settings.server_name or host
        names = _names_of(host, port, timeout, settings)
        if names:
            return (
                f"the server's certificate is for {', '.join(names)}, not {name}: "
                f"give --server-name {names[0]} to accept the name it has"
            )
        return f"the server's certificate is not for {name}: give --server-name NAME with a name it has"
    return f"the server's certificate does not verify: {error.verify_message}"


def _connected(host: str, port: int, timeout: float) -> socket.socket:
    """link.base.connect's connection as the socket module's socket, which ssl wraps, with the
    connect's timeout for the handshake."""
    raw = socket.socket(fileno=connect(host, port, timeout).detach())
    raw.settimeout(timeout)
    return raw


def _names_of(host: str, port: int, timeout: float, settings: TlsSettings) -> list[str]:
    """The names the server's certificate is for, from a second handshake that checks nothing
    and sends nothing but the handshake; [] if that fails too."""
    context = client_context(TlsSettings(insecure=True))  # no certificate of ours: nothing sent
    try:
        with _connected(host, port, timeout) as raw, context.wrap_socket(raw) as sock:
            der = sock.getpeercert(binary_form=True)
        return x509.names(der) if der else []
    except (OSError, ValueError, ConnectionFailed):
        return []


def _refusal(error: BaseException | None) -> str:
    """What an alert the server sent means, if it refused the client's certificate."""
    return REFUSALS.get(getattr(error, "reason", None) or "", "")


def _ssl_reason(error: BaseException) -> str:
    """OpenSSL's reason in words (its errno is no system error: reason() would misname it)."""
    code = getattr(error, "reason", None)
    if isinstance(error, ssl.SSLError) and code:
        return code.lower().replace("_", " ")
    return reason(error)
