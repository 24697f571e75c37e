"""The DER walk that reads a client's Modbus role and a server certificate's names
(mbtool/link/x509.py), on certificates openssl makes, checked against openssl's own reading."""

from __future__ import annotations

import ssl
import subprocess

import pytest
from peers.certs import ROLE_OID, _client, _leaf

from mbtool.link import x509


def der(path) -> bytes:
    return ssl.PEM_cert_to_DER_cert(path.read_text())


def test_the_role_is_the_utf8string_of_the_modbus_security_extension(pki):
    assert x509.role(der(pki.operator.cert)) == "operator"
    assert x509.role(der(pki.viewer.cert)) == "viewer"
    assert x509.role(der(pki.locked.cert)) == "operator"


def test_a_certificate_without_the_extension_has_no_role(pki):
    assert x509.role(der(pki.no_role.cert)) is None
    assert x509.role(der(pki.server.cert)) is None
    assert x509.role(der(pki.ca.cert)) is None


def test_a_long_role_takes_the_long_form_of_a_der_length(pki, tmp_path):
    long_role = "maintenance-" + "x" * 300  # past 127 bytes: a length of two octets
    pair = _leaf(tmp_path, "long", pki.ca, _client(long_role))
    assert x509.role(der(pair.cert)) == long_role


def test_a_role_that_is_not_a_utf8string_is_refused(pki, tmp_path):
    pair = _leaf(tmp_path, "printable", pki.ca, f"{ROLE_OID}=ASN1:PRINTABLESTRING:operator")
    with pytest.raises(ValueError, match="UTF8String"):
        x509.role(der(pair.cert))


def test_the_names_are_those_openssl_reads_in_subject_alt_name(pki):
    for pair, expected in (
        (pki.server, ["localhost", "127.0.0.1"]),
        (pki.server_other_name, ["plc7.plant.example"]),
    ):
        shown = subprocess.run(
            ["openssl", "x509", "-in", str(pair.cert), "-noout", "-ext", "subjectAltName"],
            capture_output=True,
            text=True,
            timeout=30,
            check=True,
        ).stdout
        openssl_names = [part.split(":", 1)[1] for part in shown.splitlines()[-1].strip().split(", ")]
        assert x509.names(der(pair.cert)) == openssl_names == expected
    assert x509.names(der(pki.operator.cert)) == []


def test_the_oid_is_encoded_as_openssl_encodes_it(tmp_path):
    out = tmp_path / "oid.der"
    subprocess.run(
        ["openssl", "asn1parse", "-genstr", f"OID:{ROLE_OID}", "-out", str(out), "-noout"],
        capture_output=True,
        timeout=30,
        check=True,
    )
    encoded = out.read_bytes()
    assert encoded[0] == 0x06 and encoded[1] == len(encoded) - 2
    assert x509.encode_oid(ROLE_OID) == encoded[2:] == bytes.fromhex("2B0601040183890C862201")


@pytest.mark.parametrize(
    "data, why",
    [
        (b"", "ends inside"),
        (b"\x30", "ends inside"),
        (b"\x30\x05\x30\x00", "run past"),
        (b"\x30\x85\x00\x00\x00\x00\x00", "no definite form"),
        (b"\x30\x80\x00\x00", "no definite form"),  # BER's indefinite length: not DER
        (b"\x02\x01\x00", "a SEQUENCE"),
        (b"\x30\x02\x1f\x00", "tag number above 30"),
    ],
)
def test_what_is_not_der_of_a_certificate_raises_value_error(data, why):
    with pytest.raises(ValueError, match=why):
        x509.extension(data, ROLE_OID)


def test_every_truncation_of_a_certificate_raises_value_error_or_finds_nothing(pki):
    whole = der(pki.operator.cert)
    for size in range(len(whole)):
        try:
            found = x509.role(whole[:size])
        except ValueError:
            continue
        assert found in (None, "operator")
