"""A test PKI for Modbus/TCP Security, made with the ``openssl`` command at run time.

Nothing here is committed: ``make_pki(folder)`` writes a CA and the certificates the TLS
tests need into ``folder`` (a pytest tmp dir) and returns their paths.  EC P-256 keys, so
making them all takes a fraction of a second.

* ``ca``: the plant's CA; ``other_ca``: a CA nobody trusts.
* ``server``: for 127.0.0.1 and localhost, signed by ``ca``; ``server_expired`` (valid in
  2020 only), ``server_other_name`` (for plc7.plant.example only), ``server_self_signed``
  (its own issuer), ``server_unknown_ca`` (signed by ``other_ca``).
* ``operator``, ``viewer``: client certificates signed by ``ca`` carrying the role
  extension of the Modbus/TCP Security specification (OID 1.3.6.1.4.1.50316.802.1, a
  UTF8String); ``no_role``: one without it; ``stranger``: a client signed by ``other_ca``;
  ``locked``: the operator's role with its key encrypted under ``KEY_PASSWORD``.

Each entry is a ``Pair(cert, key)`` of paths (the CAs' too).
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

ROLE_OID = "1.3.6.1.4.1.50316.802.1"
KEY_PASSWORD = "correct horse"
OPENSSL_DEADLINE = 30.0  # seconds for one openssl command


@dataclass(frozen=True)
class Pair:
    cert: Path
    key: Path


def _openssl(*args: str, cwd: Path) -> None:
    done = subprocess.run(
        ["openssl", *args], cwd=cwd, capture_output=True, text=True, timeout=OPENSSL_DEADLINE
    )
    if done.returncode != 0:
        raise RuntimeError(f"openssl {' '.join(args)}: {done.stderr.strip()}")


def _key(folder: Path, name: str, password: str | None = None) -> Path:
    path = folder / f"{name}.key"
    cipher = ["-aes-256-cbc", "-pass", f"pass:{password}"] if password else []
    _openssl(
        "genpkey", "-algorithm", "EC", "-pkeyopt", "ec_paramgen_curve:P-256", *cipher, "-out", str(path),
        cwd=folder,
    )  # fmt: skip
    return path


def _ca(folder: Path, name: str, subject: str) -> Pair:
    key = _key(folder, name)
    cert = folder / f"{name}.pem"
    _openssl(
        "req", "-x509", "-new", "-key", str(key), "-subj", f"/CN={subject}", "-days", "3650",
        "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
        "-out", str(cert), cwd=folder,
    )  # fmt: skip
    return Pair(cert, key)


def _leaf(
    folder: Path,
    name: str,
    signer: Pair,
    extensions: str,
    password: str | None = None,
    dates: tuple[str, str] | None = None,
) -> Pair:
    """A certificate for ``name`` signed by ``signer`` with the extensions (an openssl config
    section's lines); ``dates``: its validity (YYYYMMDDHHMMSSZ), else ten years from now."""
    key = _key(folder, name, password)
    request = folder / f"{name}.csr"
    passin = ["-passin", f"pass:{password}"] if password else []
    _openssl(
        "req", "-new", "-key", str(key), *passin, "-subj", f"/CN={name}", "-out", str(request), cwd=folder
    )
    config = folder / f"{name}.cnf"
    cert = folder / f"{name}.pem"
    if dates is None:
        config.write_text(f"[ext]\n{extensions}\n")
        _openssl(
            "x509", "-req", "-in", str(request), "-CA", str(signer.cert), "-CAkey", str(signer.key),
            "-CAcreateserial", "-days", "3650", "-extfile", str(config), "-extensions", "ext",
            "-out", str(cert), cwd=folder,
        )  # fmt: skip
    else:
        # `openssl x509` of OpenSSL 3.0 sets no start date: `openssl ca` does, with a database.
        database = folder / f"{name}.db"
        database.mkdir()
        (database / "index.txt").write_text("")
        config.write_text(
            "[ca]\ndefault_ca = this\n"
            f"[this]\ndir = {database}\ndatabase = $dir/index.txt\nnew_certs_dir = $dir\n"
            "serial = $dir/serial\ndefault_md = sha256\npolicy = anything\ncopy_extensions = none\n"
            "[anything]\ncommonName = supplied\n"
            f"[ext]\n{extensions}\n"
        )
        (database / "serial").write_text("01\n")
        _openssl(
            "ca", "-batch", "-config", str(config), "-extensions", "ext", "-cert", str(signer.cert),
            "-keyfile", str(signer.key), "-startdate", dates[0], "-enddate", dates[1], "-notext",
            "-in", str(request), "-out", str(cert), cwd=folder,
        )  # fmt: skip
    return Pair(cert, key)


SERVER = "subjectAltName=DNS:localhost,IP:127.0.0.1\nextendedKeyUsage=serverAuth"


def _client(role: str | None) -> str:
    lines = ["extendedKeyUsage=clientAuth"]
    if role is not None:
        lines.append(f"{ROLE_OID}=ASN1:UTF8String:{role}")
    return "\n".join(lines)


@dataclass(frozen=True)
class Pki:
    folder: Path
    ca: Pair
    other_ca: Pair
    server: Pair
    server_expired: Pair
    server_other_name: Pair
    server_self_signed: Pair
    server_unknown_ca: Pair
    operator: Pair
    viewer: Pair
    no_role: Pair
    stranger: Pair
    locked: Pair


def make_pki(folder: Path) -> Pki:
    folder.mkdir(parents=True, exist_ok=True)
    ca = _ca(folder, "ca", "mbtool test CA")
    other_ca = _ca(folder, "other-ca", "nobody's CA")
    self_signed_key = _key(folder, "self-signed")
    self_signed = folder / "self-signed.pem"
    _openssl(
        "req", "-x509", "-new", "-key", str(self_signed_key), "-subj", "/CN=127.0.0.1", "-days", "3650",
        "-addext", "subjectAltName=DNS:localhost,IP:127.0.0.1", "-out", str(self_signed), cwd=folder,
    )  # fmt: skip
    return Pki(
        folder=folder,
        ca=ca,
        other_ca=other_ca,
        server=_leaf(folder, "server", ca, SERVER),
        server_expired=_leaf(folder, "expired", ca, SERVER, dates=("20200101000000Z", "20201231000000Z")),
        server_other_name=_leaf(
            folder, "plc7", ca, "subjectAltName=DNS:plc7.plant.example\nextendedKeyUsage=serverAuth"
        ),
        server_self_signed=Pair(self_signed, self_signed_key),
        server_unknown_ca=_leaf(folder, "unknown-ca-server", other_ca, SERVER),
        operator=_leaf(folder, "operator", ca, _client("operator")),
        viewer=_leaf(folder, "viewer", ca, _client("viewer")),
        no_role=_leaf(folder, "no-role", ca, _client(None)),
        stranger=_leaf(folder, "stranger", other_ca, _client("operator")),
        locked=_leaf(folder, "locked", ca, _client("operator"), password=KEY_PASSWORD),
    )
