"""``mbtool serve -p tls://``: Modbus/TCP Security's server side, against pymodbus's TLS client
and mbtool's own: mutual authentication (a client certificate required, signed by --ca), the
clients' roles from their certificates and the write-role rule (exception 01), a handshake a
client stalls holding nobody up, and the options refused where they do not fit (issue 33).
"""

from __future__ import annotations

import socket
import ssl
import time

import pytest
from helpers.checks import assert_one_error_line, expect_ok, plain_pairs, wait_until
from helpers.run import run_cli, run_mbtool
from helpers.served import serve

pytestmark = pytest.mark.timeout(90)


def server_args(pki, *more: str) -> list[str]:
    return ["--cert", str(pki.server.cert), "--key", str(pki.server.key), "--ca", str(pki.ca.cert), *more]


def tls_serve(pki, *more: str, quiet: bool = False):
    return serve(*server_args(pki, *more), target="tls://127.0.0.1:0", quiet=quiet)


def pymodbus_client(server, pki, who: str | None = "operator"):
    from pymodbus.client import ModbusTlsClient

    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False  # pymodbus's sync client wraps without a server name
    context.load_verify_locations(pki.ca.cert)
    if who is not None:
        pair = getattr(pki, who)
        context.load_cert_chain(pair.cert, pair.key)
    return ModbusTlsClient(server.host, port=server.port, sslctx=context, timeout=3, retries=0)


def identity(pki, who: str) -> list[str]:
    pair = getattr(pki, who)
    return ["--cert", str(pair.cert), "--key", str(pair.key), "--ca", str(pki.ca.cert)]


def test_pymodbus_tls_client_reads_and_writes(tmp_path, pki):
    with tls_serve(pki) as server:
        assert server.first_line.startswith("serving tls://127.0.0.1:")
        client = pymodbus_client(server, pki)
        assert client.connect()
        try:
            reply = client.write_registers(10, [7, 8, 9], device_id=1)
            assert not reply.isError(), reply
            reply = client.read_holding_registers(10, count=3, device_id=1)
            assert reply.registers == [7, 8, 9]
        finally:
            client.close()
        assert wait_until(lambda: "open TLS TLSv1.3, role operator" in server.log(), 5), server.log()


def test_mbtool_reads_its_own_tls_server_and_hex_shows_plaintext(tmp_path, pki):
    with tls_serve(pki, quiet=True) as server:
        res = expect_ok(
            run_cli(
                "read-holding-registers", "0", "2", "-p", server.target, *identity(pki, "viewer"), "--hex"
            )
        )
        assert plain_pairs(res) == [(0, "0"), (1, "1")]
        assert "TX 00 01 00 00 00 06 01 03 00 00 00 02" in res.stderr


def test_mutual_tls_refuses_a_client_without_a_certificate(tmp_path, pki):
    with tls_serve(pki) as server:
        client = pymodbus_client(server, pki, who=None)
        try:
            connected = client.connect()
            if connected:  # TLS 1.3: the server's verdict comes after the client's handshake
                from pymodbus.exceptions import ModbusException

                # pymodbus lets the TLS alert through as it is (ssl.SSLError, an OSError)
                with pytest.raises((ModbusException, OSError)):
                    client.read_holding_registers(0, count=1, device_id=1)
        finally:
            client.close()
        res = run_cli("read-holding-registers", "0", "-p", server.target, "--ca", str(pki.ca.cert))
        line = assert_one_error_line(res, 6)
        assert line == (
            f"mbtool: TLS handshake with {server.host}:{server.port} failed: the server requires a client "
            "certificate (Modbus/TCP Security is mutual: give --cert FILE --key FILE, signed by a CA the "
            "server trusts)"
        )
        assert wait_until(
            lambda: server.log().count("TLS handshake failed: the client sent no certificate") == 2, 5
        )


def test_a_client_certificate_from_another_ca_is_refused(tmp_path, pki):
    with tls_serve(pki) as server:
        res = run_cli("read-holding-registers", "0", "-p", server.target, *identity(pki, "stranger"))
        line = assert_one_error_line(res, 6)
        assert line == (
            f"mbtool: TLS handshake with {server.host}:{server.port} failed: the server refused mbtool's "
            "client certificate: it does not trust the CA that signed it"
        )
        assert wait_until(
            lambda: "the client's certificate does not verify: unable to get local issuer" in server.log(), 5
        )


def test_a_plain_modbus_tcp_client_is_told_apart(tmp_path, pki):
    with tls_serve(pki) as server:
        res = run_cli("read-holding-registers", "0", "-p", f"tcp://{server.host}:{server.port}", "-t", "1")
        assert res.returncode == 3, str(res)
        assert wait_until(
            lambda: "TLS handshake failed: not TLS (a plain Modbus TCP client?)" in server.log(), 5
        )


WRITES = [
    ("write-register", "5", "1"),
    ("write-coil", "5", "on"),
    ("write-registers", "5", "1", "2"),
    ("diag", "clear-counters"),
]


@pytest.mark.parametrize("write", WRITES, ids=lambda w: w[0])
def test_only_the_write_roles_may_write_others_get_exception_01(tmp_path, pki, write):
    with tls_serve(pki, "--write-roles", "operator,engineer", quiet=True) as server:
        assert server.first_line.endswith("writes by role engineer,operator only")
        for who in ("viewer", "no_role"):
            res = run_cli(*write, "-p", server.target, *identity(pki, who))
            line = assert_one_error_line(res, 4)
            assert line.startswith("mbtool: exception 01 Illegal Function"), line
            expect_ok(run_cli("read-holding-registers", "5", "-p", server.target, *identity(pki, who)))
        expect_ok(run_cli(*write, "-p", server.target, *identity(pki, "operator")))


def test_a_refused_write_changes_nothing_and_pymodbus_sees_exception_01(tmp_path, pki):
    with tls_serve(pki, "--write-roles", "operator") as server:
        viewer = pymodbus_client(server, pki, "viewer")
        assert viewer.connect()
        try:
            reply = viewer.write_register(3, 999, device_id=1)
            assert reply.isError() and reply.exception_code == 1
            reply = viewer.readwrite_registers(
                read_address=3, read_count=1, write_address=3, values=[999], device_id=1
            )
            assert reply.isError() and reply.exception_code == 1
            assert viewer.read_holding_registers(3, count=1, device_id=1).registers == [3]
        finally:
            viewer.close()
        assert wait_until(
            lambda: "write refused: role viewer may not write (exception 01)" in server.log(), 5
        )


def test_a_data_file_names_the_write_roles(tmp_path, pki):
    data = tmp_path / "plant.toml"
    data.write_text('write_roles = ["operator"]\n[holding_registers]\n0 = 42\n')
    with tls_serve(pki, "--data", str(data), quiet=True) as server:
        assert server.first_line.endswith("writes by role operator only")
        res = run_cli("write-register", "0", "1", "-p", server.target, *identity(pki, "viewer"))
        assert_one_error_line(res, 4)
        expect_ok(run_cli("write-register", "0", "1", "-p", server.target, *identity(pki, "operator")))
    # --write-roles beats the file, as the command line beats a file everywhere
    with tls_serve(pki, "--data", str(data), "--write-roles", "viewer", quiet=True) as server:
        expect_ok(run_cli("write-register", "0", "1", "-p", server.target, *identity(pki, "viewer")))


def test_without_write_roles_every_authenticated_client_may_write(tmp_path, pki):
    with tls_serve(pki, quiet=True) as server:
        expect_ok(run_cli("write-register", "0", "1", "-p", server.target, *identity(pki, "no_role")))


def test_a_client_that_stalls_its_handshake_holds_nobody_up(tmp_path, pki):
    with tls_serve(pki, "--first-request-timeout", "1") as server:
        stalled = socket.create_connection((server.host, server.port), timeout=5)
        stalled.sendall(bytes.fromhex("16 03 01 02 00 01 00 01 fc 03 03"))  # the start of a ClientHello
        silent = socket.create_connection((server.host, server.port), timeout=5)
        try:
            started = time.monotonic()
            expect_ok(
                run_mbtool("read-holding-registers", "0", "-p", server.target, *identity(pki, "viewer"))
            )
            assert time.monotonic() - started < 10
            assert wait_until(lambda: server.log().count("first-request timeout") == 2, 5), server.log()
        finally:
            stalled.close()
            silent.close()


@pytest.mark.parametrize(
    "args, words",
    [
        (
            ["-p", "tls://127.0.0.1:0", "--cert", "{server.cert}", "--key", "{server.key}"],
            "serving on tls:// needs --ca FILE",
        ),
        (
            ["-p", "tls://127.0.0.1:0", "--ca", "{ca.cert}"],
            "serving on tls:// needs --cert FILE and --key FILE",
        ),
        (
            ["-p", "tcp://127.0.0.1:0", "--ca", "{ca.cert}"],
            "--ca is for a tls:// server (Modbus/TCP Security); tcp://127.0.0.1:0 is not one",
        ),
        (["-p", "udp://127.0.0.1:0", "--write-roles", "x"], "--write-roles is for a tls:// server"),
        (
            ["-p", "tls://127.0.0.1:0", "--framer", "rtu"],
            "Modbus/TCP Security carries MBAP: tls:// takes no --framer rtu",
        ),
        (
            [
                "-p",
                "tls://127.0.0.1:0",
                "--cert",
                "{server.cert}",
                "--key",
                "{server.key}",
                "--ca",
                "{ca.cert}",
                "--write-roles",
                "a,,b",
            ],
            "--write-roles a,,b: an empty role",
        ),
    ],
)
def test_tls_options_that_do_not_fit_are_exit_2(pki, args, words):
    values = {"server": pki.server, "ca": pki.ca}
    res = run_cli("serve", *[arg.format(**values) for arg in args])
    line = assert_one_error_line(res, 2)
    assert words in line, line
