"""What ``serve`` and ``bridge --listen`` share about the port they listen on: a tls:// port's
TLS context and the roles that may write (Modbus/TCP Security's authorization), a UDP port's
--udp-rate and what it dropped."""

from __future__ import annotations

from mbtool.device.datafile import load_write_roles
from mbtool.device.serving import Stats
from mbtool.errors import UsageError
from mbtool.link.settings import SETTINGS, check_tls_framing, not_for_tls
from mbtool.link.transport import Target
from mbtool.words import counted

DATAGRAM_SCHEMES = ("udp", "rtu+udp")


def parse_roles(text: str) -> frozenset[str]:
    """--write-roles operator,engineer: the roles, each as the certificates spell it."""
    roles = [role.strip() for role in text.split(",")]
    if not all(roles):
        raise UsageError(f"--write-roles {text}: an empty role (give ROLE,ROLE...)")
    return frozenset(roles)


def tls_server_settings(
    where: Target,
    framer: str,
    cert: str | None,
    key: str | None,
    ca: str | None,
    write_roles: str | None,
    data_file: str | None = None,
):
    """(the SSLContext, the roles that may write or None for any) of a server on ``where``;
    (None, None) off tls://, where the options are refused (UsageError, exit 2)."""
    given = [SETTINGS[name].option for name, value in (("cert", cert), ("key", key), ("ca", ca)) if value]
    if write_roles is not None:
        given.append("--write-roles")
    if where.scheme != "tls":
        if given:
            raise not_for_tls(given[0], "a tls:// server", f"; {where} is not one")
        return None, None
    check_tls_framing(framer)
    from mbtool.link.tls import server_context  # noqa: PLC0415 - ssl, 6 ms: tls:// only

    roles = parse_roles(write_roles) if write_roles is not None else None
    if roles is None and data_file:
        roles = load_write_roles(data_file)
    return server_context(cert, key, ca), roles


def check_udp_rate(where: Target, udp_rate: int | None) -> None:
    """--udp-rate only where datagrams come: UsageError (exit 2) elsewhere."""
    if udp_rate is not None and where.scheme not in DATAGRAM_SCHEMES:
        raise UsageError(f"--udp-rate is for a udp:// or rtu+udp:// server; {where} is not one")


def datagrams_dropped(stats: Stats) -> list[str]:
    """What a UDP server dropped, for the summary on exit: nothing when it dropped nothing."""
    parts = []
    if stats.trailing:
        parts.append(
            f"{counted(stats.trailing, 'datagram')} held more than one ADU: "
            f"{counted(stats.trailing_bytes, 'byte')} dropped"
        )
    if stats.limited:
        parts.append(f"{counted(stats.limited, 'datagram')} over --udp-rate dropped")
    return parts
