#!/usr/bin/env python3
"""Independent Modbus device for mbtool's end-to-end tests, built on pymodbus 3.16.

Run as a subprocess by tests/helpers/devices.py (start_device):

    python tests/peers/pymodbus_device.py --tcp 127.0.0.1:15020 --framer socket --units 1
    python tests/peers/pymodbus_device.py --tcp 127.0.0.1:15021 --framer rtu
    python tests/peers/pymodbus_device.py --serial /dev/pts/7 --framer ascii
    python tests/peers/pymodbus_device.py --tls 127.0.0.1:15802 --cert S.pem --key S.key --ca CA.pem
    python tests/peers/pymodbus_device.py --udp 127.0.0.1:15020 --framer rtu

--tls: Modbus/TCP Security (MBAP inside TLS), with --ca the clients' certificates required
and checked against it.  --udp: one ADU a datagram, MBAP (--framer socket) or RTU.

Data served (per unit, separate blocks for the four tables, addresses 0..TABLE_SIZE-1):
    holding registers 0..19 = 100..119, input registers 0..19 = 200..219,
    coils 0..19 alternate True/False starting True, discrete inputs 0..19 all True,
    everything else 0/False.  Reads beyond the table answer exception 02.

Prints "READY" (flushed) on stdout once listening; exits cleanly on SIGTERM/SIGINT.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys

TABLE_SIZE = 1000

HOLDING = [100 + i for i in range(20)]
INPUT = [200 + i for i in range(20)]
COILS = [i % 2 == 0 for i in range(20)]
DISCRETE = [True] * 20


# --holes: a device with gaps in its address map, as real ones have (reads that touch a
# gap answer exception 02): (first address, values) blocks per table.
HOLED = {
    "coils": [(0, [True, False] * 8), (40, [True] * 5)],
    "discrete": [(3, [False, True, True])],
    "holding": [(0, list(range(100, 110))), (20, list(range(200, 210))), (500, [7]), (502, [8, 9])],
    "input": [(10, [1, 2, 3]), (300, [4] * 40)],
}


def build_holed_device(unit: int):
    from pymodbus.simulator import DataType, SimData, SimDevice

    def blocks(name, datatype):
        return [SimData(first, values=list(values), datatype=datatype) for first, values in HOLED[name]]

    return SimDevice(
        id=unit,
        simdata=(
            blocks("coils", DataType.BITS),
            blocks("discrete", DataType.BITS),
            blocks("holding", DataType.REGISTERS),
            blocks("input", DataType.REGISTERS),
        ),
    )


def build_device(unit: int):
    from pymodbus.simulator import DataType, SimData, SimDevice

    def bits(first):
        return [SimData(0, values=list(first) + [False] * (TABLE_SIZE - len(first)), datatype=DataType.BITS)]

    def regs(first):
        return [SimData(0, values=list(first) + [0] * (TABLE_SIZE - len(first)), datatype=DataType.REGISTERS)]

    # (<coils>, <discrete inputs>, <holding registers>, <input registers>): non-shared blocks,
    # coils/discrete inputs addressed bit by bit.
    return SimDevice(id=unit, simdata=(bits(COILS), bits(DISCRETE), regs(HOLDING), regs(INPUT)))


# FC43/14 objects: the seven standard ones, and extended ones long enough that the
# extended stream needs more than one reply (more-follows, spec §3).
IDENTITY = {
    0x00: "Pymodbus",
    0x01: "PM-TEST",
    0x02: "3.16",
    0x03: "https://example.invalid/pymodbus",
    0x04: "pymodbus test device",
    0x05: "peer",
    0x06: "mbtool e2e",
}
EXTENDED = {0x80 + i: f"extended object {i} " + "x" * 60 for i in range(5)}


def build_identity():
    from pymodbus.pdu.device import ModbusDeviceIdentification

    identity = ModbusDeviceIdentification()
    for object_id, value in {**IDENTITY, **EXTENDED}.items():
        identity[object_id] = value
    return identity


def parse_args(argv):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--tcp", metavar="HOST:PORT")
    where.add_argument("--serial", metavar="PATH")
    where.add_argument("--tls", metavar="HOST:PORT")
    where.add_argument("--udp", metavar="HOST:PORT")
    p.add_argument("--cert", help="--tls: the server's certificate (PEM)")
    p.add_argument("--key", help="--tls: its key (PEM)")
    p.add_argument("--ca", help="--tls: require client certificates signed by this CA")
    p.add_argument("--framer", choices=["socket", "rtu", "ascii"], default=None)
    p.add_argument("--units", default="1", help="comma separated device ids (default 1)")
    p.add_argument("--baud", type=int, default=19200)
    # Default N: Linux pseudo-terminals (kernel 6.x) reject PARENB and CS7 with EINVAL, and the
    # e2e tests run the serial device on a pty.  Parity does not exist on a pty anyway.
    p.add_argument("--parity", default="N", choices=["N", "E", "O"])
    p.add_argument("--verbose", action="store_true")
    p.add_argument("--holes", action="store_true", help="the HOLED address map instead of full tables")
    args = p.parse_args(argv)
    if args.framer is None:
        args.framer = "socket" if args.tcp or args.tls or args.udp else "rtu"
    if args.serial and args.framer == "socket":
        p.error("--framer socket needs --tcp")
    if args.tls and not (args.cert and args.key):
        p.error("--tls needs --cert and --key")
    args.unit_list = [int(u, 0) for u in args.units.split(",") if u.strip()]
    return args


async def run(args) -> int:
    from pymodbus import FramerType
    from pymodbus.server import ModbusSerialServer, ModbusTcpServer, ModbusTlsServer, ModbusUdpServer

    build = build_holed_device if args.holes else build_device
    devices = [build(u) for u in args.unit_list]
    framer = {"socket": FramerType.SOCKET, "rtu": FramerType.RTU, "ascii": FramerType.ASCII}[args.framer]
    if args.tls:
        import ssl

        host, _, port = args.tls.rpartition(":")
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        context.load_cert_chain(args.cert, args.key)
        if args.ca:
            context.load_verify_locations(args.ca)
            context.verify_mode = ssl.CERT_REQUIRED
        server = ModbusTlsServer(
            devices, address=(host or "127.0.0.1", int(port)), sslctx=context, identity=build_identity()
        )
    elif args.udp:
        host, _, port = args.udp.rpartition(":")
        server = ModbusUdpServer(
            devices, framer=framer, address=(host or "127.0.0.1", int(port)), identity=build_identity()
        )
    elif args.tcp:
        host, _, port = args.tcp.rpartition(":")
        server = ModbusTcpServer(
            devices, framer=framer, address=(host or "127.0.0.1", int(port)), identity=build_identity()
        )
    else:
        server = ModbusSerialServer(
            devices,
            framer=framer,
            identity=build_identity(),
            port=args.serial,
            baudrate=args.baud,
            parity=args.parity,
            bytesize=8,
            stopbits=1,
            timeout=1,
            reconnect_delay=0.1,
        )

    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, stop.set)

    await server.serve_forever(background=True)
    print("READY", flush=True)
    await stop.wait()
    await server.shutdown()
    return 0


def main(argv=None) -> int:
    args = parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.ERROR, stream=sys.stderr)
    from pymodbus import pymodbus_apply_logging_config

    # pymodbus logs through its own logger; keep the device quiet unless asked
    pymodbus_apply_logging_config(logging.DEBUG if args.verbose else logging.CRITICAL)
    try:
        return asyncio.run(run(args))
    except Exception as exc:  # startup failure: say so on stderr, never print READY
        print(f"pymodbus_device: {exc!r}", file=sys.stderr, flush=True)
        return 1


if __name__ == "__main__":
    sys.exit(main())
