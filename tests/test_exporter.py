"""mbtool exporter: a Prometheus exporter in two modes (issue 32).

Multi-target: GET /modbus?target=...&module=...&unit=... reads a register map from the
target on each scrape, within the deadline the scraper sends; a device that fails is HTTP
200 with modbus_up 0 and the reason, a target no --allow-target pattern allows is refused
with nothing opened.  Inventory: the plant is polled as `mbtool poll` polls it, and
/metrics serves the latest values from memory.  Every exposition here is read back with
prometheus_client's own parser; tests/test_exporter_prometheus.py has Prometheus itself
scrape the exporter.
"""

from __future__ import annotations

import math

from mbtool.plant.stats import RTT_BUCKETS, Stats

# --- the round-trip histogram's buckets -------------------------------------------------------


def test_round_trips_land_in_the_fixed_buckets_each_counted_up_to_its_bound():
    assert RTT_BUCKETS[0] == 0.001 and RTT_BUCKETS[-1] == 10.0  # 1 ms ... 10 s, fixed
    stats = Stats()
    for seconds in (0.0004, 0.001, 0.0011, 0.3, 12.0):
        stats.round_trip(seconds)
    buckets = dict(stats.rtt_histogram())
    assert buckets[0.001] == 2  # "le": up to the bound, the bound itself included
    assert buckets[0.0025] == 3
    assert buckets[0.25] == 3 and buckets[0.5] == 4
    assert buckets[10.0] == 4 and buckets[math.inf] == 5  # past 10 s only in +Inf
    link = Stats()
    link.add(stats)
    link.add(stats)
    assert dict(link.rtt_histogram())[math.inf] == 10 and link.rtt_count == 10
