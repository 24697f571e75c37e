"""The bus monitor's statistics (mbtool.monitor.stats) in-process."""

from __future__ import annotations

from helpers.frames import ascii_frame

from mbtool.monitor.bus import BusMonitor
from mbtool.monitor.stats import BusStats


def test_the_counts_in_process_with_an_ascii_bus_have_no_t35():
    # ASCII has no t3.5 (spec §2): frames end at CR LF, and no break is counted.
    monitor = BusMonitor("ascii", silence=1.0)
    stats = BusStats(None, 10 / 9600, started=100.0)
    for when, data in [
        (100.0, ascii_frame(1, bytes.fromhex("0300000001"))),
        (100.0, ascii_frame(1, bytes.fromhex("03020007"))),
    ]:
        for item in monitor.feed(when, data):
            stats.count(item)
    for item in monitor.finish(101.0):
        stats.count(item)
    record = stats.as_dict(101.0)
    assert record["t35_breaks"] is None and record["units"][0]["t35_breaks"] is None
    assert (record["units"][0]["requests"], record["units"][0]["replies"]) == (1, 1)
    assert record["seconds"] == 1.0
