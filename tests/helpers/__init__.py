"""The helpers the tests share, one module a kind:

* ``helpers.run``: running mbtool: a process, or in this process;
* ``helpers.checks``: the assertions and waits in common;
* ``helpers.frames``: frames written without mbtool's codec; a framer's events drained;
* ``helpers.devices``: pymodbus's device as a subprocess, a libmodbus peer;
* ``helpers.ptys``: pseudo-terminal pairs as serial lines;
* ``helpers.sockets``: misbehaving loopback servers, free ports;
* ``helpers.served``: ``mbtool serve`` and ``mbtool bridge`` as a user runs them, pymodbus's client before them;
* ``helpers.exporter``: ``mbtool exporter`` and a GET of it;
* ``helpers.monitor``: ``mbtool monitor`` on a pty, and the frames put on its bus;
* ``helpers.prometheus``: promtool's check, expositions cut apart;
* ``helpers.mqtt``: a plant publishing to mosquitto (the broker, pymodbus's device, poll and a subscriber together);
* ``helpers.fakes``: a fake clock, a scripted link, a device's ``execute`` for the unit tests.

A test imports what it uses from the module of its kind (``from helpers.served import serve``;
pyproject's ``pythonpath = ["tests"]``); tests/conftest.py holds the fixtures built on them.
Every wait has a deadline.
"""
