"""The two things mbtool reads from an X.509 certificate: a client's Modbus role, and the names
a server's certificate is for.

Python's ssl module hands over the peer's certificate as DER (``getpeercert(binary_form=True)``)
and, for a certificate it did not verify, nothing else.  Reading one extension needs no more
than a walk over DER's tag-length-value triples (ITU-T X.690 §8.1, the definite form DER
requires, §10.1), through the structure of RFC 5280 §4.1:

    Certificate    ::= SEQUENCE { tbsCertificate, signatureAlgorithm, signatureValue }
    TBSCertificate ::= SEQUENCE { [0] version, serialNumber, signature, issuer, validity,
                                  subject, subjectPublicKeyInfo, [1] issuerUniqueID,
                                  [2] subjectUniqueID, [3] extensions }
    Extensions     ::= SEQUENCE OF Extension
    Extension      ::= SEQUENCE { extnID OBJECT IDENTIFIER, critical BOOLEAN DEFAULT FALSE,
                                  extnValue OCTET STRING }

The role is the MODBUS/TCP Security specification's (MB-TCP-Security-v21, "Role"): the
extension 1.3.6.1.4.1.50316.802.1 whose value is one UTF8String.  The names are those of
subjectAltName (RFC 5280 §4.2.1.6): dNSName [2] and iPAddress [7].

Anything that is not DER of that shape raises ValueError; the certificates come from a
TLS handshake, so OpenSSL has parsed them already and that means an extension of another
shape, never a broken certificate.
"""

from __future__ import annotations

import ipaddress

ROLE_OID = "1.3.6.1.4.1.50316.802.1"
SUBJECT_ALT_NAME_OID = "2.5.29.17"

SEQUENCE = 0x30
OBJECT_IDENTIFIER = 0x06
BOOLEAN = 0x01
OCTET_STRING = 0x04
UTF8_STRING = 0x0C
EXTENSIONS = 0xA3  # [3] EXPLICIT, constructed
DNS_NAME = 0x82  # [2] IMPLICIT IA5String
IP_ADDRESS = 0x87  # [7] IMPLICIT OCTET STRING


def role(der: bytes) -> str | None:
    """The Modbus role a certificate carries, or None when it carries none.

    ValueError when the role extension is there but not one UTF8String."""
    value = extension(der, ROLE_OID)
    if value is None:
        return None
    tag, start, end = _tlv(value, 0)
    if tag != UTF8_STRING or end != len(value):
        raise ValueError("the role extension is not one UTF8String")
    try:
        return value[start:end].decode("utf-8")
    except UnicodeDecodeError:
        raise ValueError("the role extension is not UTF-8") from None


def names(der: bytes) -> list[str]:
    """The DNS names and IP addresses of a certificate's subjectAltName, in its order."""
    value = extension(der, SUBJECT_ALT_NAME_OID)
    if value is None:
        return []
    tag, start, end = _tlv(value, 0)
    if tag != SEQUENCE:
        raise ValueError("subjectAltName is not a SEQUENCE")
    found = []
    for tag, first, last in _children(value, start, end):
        if tag == DNS_NAME:
            found.append(value[first:last].decode("ascii", "replace"))
        elif tag == IP_ADDRESS and last - first in (4, 16):
            found.append(str(ipaddress.ip_address(value[first:last])))
    return found


def extension(der: bytes, oid: str) -> bytes | None:
    """The extnValue (the OCTET STRING's contents) of extension ``oid``, or None."""
    wanted = encode_oid(oid)
    tag, start, end = _tlv(der, 0)
    if tag != SEQUENCE:
        raise ValueError("a certificate is a SEQUENCE")
    tag, start, end = _tlv(der, start)
    if tag != SEQUENCE:
        raise ValueError("tbsCertificate is a SEQUENCE")
    for tag, first, last in _children(der, start, end):
        if tag != EXTENSIONS:
            continue
        tag, first, last = _tlv(der, first)
        if tag != SEQUENCE:
            raise ValueError("extensions are a SEQUENCE")
        for tag, at, stop in _children(der, first, last):
            if tag != SEQUENCE:
                raise ValueError("an extension is a SEQUENCE")
            fields = list(_children(der, at, stop))
            if len(fields) not in (2, 3) or fields[0][0] != OBJECT_IDENTIFIER:
                raise ValueError("an extension is extnID, [critical,] extnValue")
            if fields[-1][0] != OCTET_STRING or (len(fields) == 3 and fields[1][0] != BOOLEAN):
                raise ValueError("an extension is extnID, [critical,] extnValue")
            if der[fields[0][1] : fields[0][2]] == wanted:
                return der[fields[-1][1] : fields[-1][2]]
    return None


def encode_oid(dotted: str) -> bytes:
    """An OBJECT IDENTIFIER's contents octets (X.690 §8.19): the first two arcs in one
    subidentifier (40 × first + second), each in base 128, high bit set on all but its last."""
    arcs = [int(arc) for arc in dotted.split(".")]
    if len(arcs) < 2 or arcs[0] > 2 or (arcs[0] < 2 and arcs[1] >= 40):
        raise ValueError(f"{dotted} is not an object identifier")
    out = bytearray()
    for number in [40 * arcs[0] + arcs[1], *arcs[2:]]:
        chunk = [number & 0x7F]
        number >>= 7
        while number:
            chunk.append(0x80 | (number & 0x7F))
            number >>= 7
        out += bytes(reversed(chunk))
    return bytes(out)


def _tlv(data: bytes, at: int) -> tuple[int, int, int]:
    """(tag, where the contents start, where they end) of the triple at ``at`` (X.690 §8.1)."""
    if at + 2 > len(data):
        raise ValueError("DER ends inside a tag or length")
    tag = data[at]
    if tag & 0x1F == 0x1F:
        raise ValueError("a tag number above 30, which no field read here has")
    length = data[at + 1]
    at += 2
    if length & 0x80:  # the long form: the next (length & 0x7F) bytes, big-endian
        count = length & 0x7F
        if not 1 <= count <= 4 or at + count > len(data):
            raise ValueError("a DER length of no definite form")
        length = int.from_bytes(data[at : at + count], "big")
        at += count
    if at + length > len(data):
        raise ValueError("DER contents run past their end")
    return tag, at, at + length


def _children(data: bytes, start: int, end: int):
    """The triples inside a constructed value's contents, ``data[start:end]``."""
    at = start
    while at < end:
        tag, first, last = _tlv(data, at)
        if last > end:
            raise ValueError("DER contents run past their end")
        yield tag, first, last
        at = last
