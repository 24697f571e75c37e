"""mbtool as a Modbus/TCP Security client (``tls://``) against pymodbus's TLS server: mutual
authentication, a pinned self-signed device, --insecure, an encrypted key, the plaintext
--hex trace, and every handshake failure as one line with exit 6 (issue 33).

The certificates are made by openssl at run time (the ``pki`` fixture, tests/peers/certs.py).
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import select
import subprocess
import sys
import termios
import time

import pytest
from helpers.checks import assert_one_error_line, expect_ok, parse_hex_lines, plain_pairs
from helpers.devices import HOLDING, start_device
from helpers.run import REPO_ROOT, mbtool_env, run_cli, run_mbtool
from helpers.sockets import SilentServer
from peers.certs import KEY_PASSWORD

pytestmark = pytest.mark.timeout(90)


@pytest.fixture(scope="module")
def tls_devices(pki):
    """pymodbus TLS servers by the certificate they present, started on first use; each
    requires a client certificate signed by the test CA."""
    started: dict[str, object] = {}
    with contextlib.ExitStack() as stack:

        def device(name: str = "server"):
            if name not in started:
                pair = getattr(pki, name)
                started[name] = stack.enter_context(
                    start_device(
                        tcp=True,
                        framer="socket",
                        units="1",
                        tls=("--cert", str(pair.cert), "--key", str(pair.key), "--ca", str(pki.ca.cert)),
                    )
                )
            return started[name]

        yield device


def identity(pki, who: str = "operator", ca: str = "ca") -> list[str]:
    pair = getattr(pki, who)
    return ["--cert", str(pair.cert), "--key", str(pair.key), "--ca", str(getattr(pki, ca).cert)]


def test_reads_and_writes_over_mutual_tls(pki, tls_devices):
    device = tls_devices()
    assert device.target.startswith("tls://127.0.0.1:")
    res = expect_ok(run_cli("read-holding-registers", "0", "5", "-p", device.target, *identity(pki)))
    assert plain_pairs(res) == [(i, str(v)) for i, v in enumerate(HOLDING[:5])]
    expect_ok(run_cli("write-register", "30", "4711", "-p", device.target, *identity(pki)))
    res = expect_ok(run_cli("read-holding-registers", "30", "-p", device.target, *identity(pki)))
    assert plain_pairs(res) == [(30, "4711")]


def test_the_host_may_be_a_name_the_certificate_has(pki, tls_devices):
    target = tls_devices().target.replace("127.0.0.1", "localhost")
    expect_ok(run_cli("read-holding-registers", "0", "-p", target, *identity(pki)))


def test_hex_shows_the_plaintext_adus(pki, tls_devices):
    res = expect_ok(
        run_cli("read-holding-registers", "0", "2", "-p", tls_devices().target, *identity(pki), "--hex")
    )
    frames = parse_hex_lines(res.stderr)
    assert [f.direction for f in frames] == ["TX", "RX"]
    assert frames[0].data[2:] == bytes.fromhex("0000 0006 01 03 0000 0002")
    assert frames[1].data[2:] == bytes.fromhex("0000 0007 01 03 04 0064 0065")


def test_ca_may_be_the_devices_own_certificate_to_pin_one_self_signed_device(pki, tls_devices):
    device = tls_devices("server_self_signed")
    pinned = [*identity(pki)[:4], "--ca", str(pki.server_self_signed.cert)]
    expect_ok(run_cli("read-holding-registers", "0", "-p", device.target, *pinned))


def test_ca_may_pin_a_devices_certificate_whoever_signed_it(pki, tls_devices):
    pinned = [*identity(pki)[:4], "--ca", str(pki.server.cert)]  # the leaf alone, not its CA
    expect_ok(run_cli("read-holding-registers", "0", "-p", tls_devices().target, *pinned))
    other = [*identity(pki)[:4], "--ca", str(pki.server_other_name.cert)]  # another device's
    line = assert_one_error_line(
        run_cli("read-holding-registers", "0", "-p", tls_devices().target, *other), 6
    )
    assert "signed by a CA not among the --ca given" in line


def test_insecure_skips_the_check_with_a_warning_each_run(pki, tls_devices):
    device = tls_devices("server_self_signed")
    for _ in range(2):
        res = expect_ok(
            run_cli("read-holding-registers", "0", "-p", device.target, *identity(pki)[:4], "--insecure")
        )
        assert res.stderr == (
            f"mbtool: warning: --insecure: the certificate of {device.target} is not checked, so anyone "
            "on the way can read and change the traffic\n"
        )


def test_server_name_accepts_a_certificate_for_another_name(pki, tls_devices):
    device = tls_devices("server_other_name")
    expect_ok(
        run_cli(
            "read-holding-registers",
            "0",
            "-p",
            device.target,
            *identity(pki),
            "--server-name",
            "plc7.plant.example",
        )
    )


# --- handshake failures: one line, exit 6 -------------------------------------------------


@pytest.mark.parametrize(
    "server, words",
    [
        (
            "server_self_signed",
            "the server's certificate is self-signed and not among the --ca given ({ca}): to trust this "
            "device, give its certificate with --ca FILE",
        ),
        (
            "server_unknown_ca",
            "the server's certificate is signed by a CA not among the --ca given ({ca}): give the "
            "certificate of the CA that signed it with --ca FILE",
        ),
        (
            "server_expired",
            "the server's certificate has expired (renew it on the device, or check this machine's clock)",
        ),
        (
            "server_other_name",
            "the server's certificate is for plc7.plant.example, not 127.0.0.1: give --server-name "
            "plc7.plant.example to accept the name it has",
        ),
    ],
)
def test_a_server_certificate_that_does_not_verify_says_why(pki, tls_devices, server, words):
    device = tls_devices(server)
    line = assert_one_error_line(
        run_cli("read-holding-registers", "0", "-p", device.target, *identity(pki)), 6
    )
    host_port = device.target.removeprefix("tls://")
    assert line == f"mbtool: TLS handshake with {host_port} failed: " + words.format(ca=pki.ca.cert)


def test_without_ca_the_systems_cas_are_trusted_and_the_test_ca_is_not_one(pki, tls_devices):
    device = tls_devices()
    res = run_cli("read-holding-registers", "0", "-p", device.target, *identity(pki)[:4])
    line = assert_one_error_line(res, 6)
    assert "signed by a CA not among this system's CAs: give the certificate of the CA" in line


@pytest.mark.parametrize(
    "who, words",
    [
        (
            None,
            "the server may require a client certificate (Modbus/TCP Security is mutual: give --cert FILE --key FILE",
        ),
        (
            "stranger",
            "the server may have refused mbtool's certificate ({cert}): is it signed by a CA the server trusts",
        ),
    ],
)
def test_a_client_certificate_pymodbus_refuses_is_exit_6(pki, tls_devices, who, words):
    """pymodbus closes the connection without an alert (asyncio's TLS): the client can only
    say that the server left right after the handshake, and what may be why."""
    device = tls_devices()
    given = identity(pki, who) if who else ["--ca", str(pki.ca.cert)]
    res = run_cli("read-holding-registers", "0", "-p", device.target, *given, "--retries", "1")
    line = assert_one_error_line(res, 6)
    cert = getattr(pki, who).cert if who else ""
    assert line.startswith(
        f"mbtool: {device.target} closed the connection after the TLS handshake, before any reply: "
    )
    assert words.format(cert=cert) in line


def test_a_plain_modbus_tcp_port_does_not_speak_tls(pki, tcp_device):
    target = f"tls://127.0.0.1:{tcp_device.port}"
    line = assert_one_error_line(run_cli("read-holding-registers", "0", "-p", target, *identity(pki)), 6)
    assert line.startswith(f"mbtool: TLS handshake with 127.0.0.1:{tcp_device.port} failed: ")
    assert line.endswith("(a plain Modbus TCP port? use tcp://)")


def test_a_port_that_says_nothing_to_the_hello_times_out_as_not_tls(pki):
    silent = SilentServer()
    try:
        res = run_cli(
            "read-holding-registers", "0", "-p", f"tls://127.0.0.1:{silent.port}", *identity(pki), "-t", "0.5"
        )
    finally:
        silent.close()
    line = assert_one_error_line(res, 6)
    assert line.endswith("failed: no TLS handshake within 0.5 s (a plain Modbus TCP port? use tcp://)")


# --- the client's own files: exit 2, nothing sent -------------------------------------------


@pytest.mark.parametrize(
    "options, words",
    [
        (
            ["--cert", "missing.pem", "--key", "missing.key"],
            "cannot read --cert missing.pem: No such file or directory",
        ),
        (
            ["--key", "{operator.key}"],
            "--key {operator.key} goes with --cert FILE, the certificate it is the key of",
        ),
        (
            ["--cert", "{operator.cert}", "--key", "{viewer.key}"],
            "--key {viewer.key} is not the key of --cert {operator.cert}",
        ),
        (["--cert", "{ca_serial}"], "--cert {ca_serial}: not a certificate and its private key in PEM"),
        (["--ca", "{ca_serial}"], "--ca {ca_serial} holds no certificate in PEM"),
        (["--ca", "missing.pem"], "cannot read --ca missing.pem: No such file or directory"),
        (
            ["--insecure", "--ca", "{ca.cert}"],
            "--insecure checks no certificate: --ca would have nothing to check",
        ),
    ],
)
def test_a_file_that_cannot_be_used_is_exit_2_and_nothing_is_sent(pki, options, words):
    values = {
        "operator": pki.operator,
        "viewer": pki.viewer,
        "ca": pki.ca,
        "ca_serial": pki.folder / "ca.srl",
    }
    silent = SilentServer()
    try:
        given = [option.format(**values) for option in options]
        res = run_cli("read-holding-registers", "0", "-p", f"tls://127.0.0.1:{silent.port}", *given)
        line = assert_one_error_line(res, 2)
        assert line == "mbtool: " + words.format(**values)
        assert silent.connections == 0
    finally:
        silent.close()


def test_tls_options_need_a_tls_target():
    line = assert_one_error_line(run_cli("read-holding-registers", "0", "-p", "sim://", "--insecure"), 2)
    assert line == "mbtool: --insecure is for tls:// targets (Modbus/TCP Security); sim:// is not one"
    line = assert_one_error_line(
        run_cli("read-holding-registers", "0", "-p", "tls://h", "--framer", "rtu"), 2
    )
    assert line == "mbtool: Modbus/TCP Security carries MBAP: tls:// takes no --framer rtu"


# --- an encrypted key ---------------------------------------------------------------------------


def test_an_encrypted_key_reads_its_password_from_the_environment(pki, tls_devices):
    # Processes of their own: link.tls.client_context keeps a decrypted key as long as the process
    # lives, so a second run in this one would not ask for the password again.
    target = tls_devices().target
    locked = identity(pki, "locked")
    expect_ok(
        run_mbtool(
            "read-holding-registers", "0", "-p", target, *locked, env={"MBTOOL_KEY_PASSWORD": KEY_PASSWORD}
        )
    )
    line = assert_one_error_line(
        run_mbtool(
            "read-holding-registers", "0", "-p", target, *locked, env={"MBTOOL_KEY_PASSWORD": "wrong"}
        ),
        2,
    )
    assert line == f"mbtool: cannot decrypt {pki.locked.key}: wrong password ($MBTOOL_KEY_PASSWORD)"
    line = assert_one_error_line(run_mbtool("read-holding-registers", "0", "-p", target, *locked), 2)
    assert line == (
        f"mbtool: the key {pki.locked.key} is encrypted and there is no terminal to ask its password on: "
        "set MBTOOL_KEY_PASSWORD"
    )


def _controlling_terminal(slave: int):
    def become() -> None:
        os.setsid()
        fcntl.ioctl(slave, termios.TIOCSCTTY, 0)

    return become


def test_an_encrypted_key_asks_its_password_on_the_terminal(pki, tls_devices):
    """As a user at a terminal sees it: a prompt, the password typed (not echoed), the read."""
    master, slave = os.openpty()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "mbtool",
            "read-holding-registers",
            "0",
            "-p",
            tls_devices().target,
            *identity(pki, "locked"),
        ],
        cwd=REPO_ROOT,
        env=mbtool_env(),
        stdin=slave,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        preexec_fn=_controlling_terminal(slave),
    )
    os.close(slave)
    try:
        seen = b""
        deadline = time.monotonic() + 20
        while b"password for" not in seen and time.monotonic() < deadline:
            if select.select([master], [], [], 0.2)[0]:
                seen += os.read(master, 1024)
        assert seen.startswith(f"password for {pki.locked.key}: ".encode()), seen
        os.write(master, KEY_PASSWORD.encode() + b"\n")
        out, err = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate(timeout=5)
        os.close(master)
    assert proc.returncode == 0, err
    assert out == "0 100\n"
