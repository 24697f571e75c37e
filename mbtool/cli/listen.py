"""What ``serve`` and ``bridge --listen`` share about a tls:// port: the server's TLS context
and the roles that may write (Modbus/TCP Security's authorization)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from mbtool.codec.errors import RequestError
from mbtool.device.datafile import load_write_roles

if TYPE_CHECKING:
    from mbtool.link.transport import Target


def parse_roles(text: str) -> frozenset[str]:
    """--write-roles operator,engineer: the roles, each as the certificates spell it."""
    roles = [role.strip() for role in text.split(",")]
    if not all(roles):
        raise RequestError(f"--write-roles {text}: an empty role (give ROLE,ROLE...)")
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
    (None, None) off tls://, where the options are refused (RequestError, exit 2)."""
    given = [option for option, value in (("--cert", cert), ("--key", key), ("--ca", ca)) if value]
    if write_roles is not None:
        given.append("--write-roles")
    if where.scheme != "tls":
        if given:
            raise RequestError(f"{given[0]} is for a tls:// server (Modbus/TCP Security); {where} is not one")
        return None, None
    if framer != "tcp":
        raise RequestError(f"Modbus/TCP Security carries MBAP: tls:// takes no --framer {framer}")
    from mbtool.link.tls import server_context  # noqa: PLC0415 - ssl, 6 ms: tls:// only

    roles = parse_roles(write_roles) if write_roles is not None else None
    if roles is None and data_file:
        roles = load_write_roles(data_file)
    return server_context(cert, key, ca), roles
