"""mbtool.durations: the one histogram of round-trip and response times (issue 32), its fixed
buckets, the figures a summary prints and the percentile rule."""

from __future__ import annotations

import math
import sys
import threading

import pytest

from mbtool.durations import BUCKETS, WINDOW, Durations, percentile


def test_the_buckets_run_from_1_ms_to_10_s_and_a_duration_on_a_bound_is_in_that_bucket():
    # The bounds an exporter will show as modbus_request_duration_seconds's "le" labels.
    assert BUCKETS == (0.001, 0.0025, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)
    durations = Durations()
    for seconds in (0.0004, 0.001, 0.0011, 0.3, 10.0, 12.5):
        durations.add(seconds)
    cumulative = dict(durations.buckets())
    assert cumulative[0.001] == 2  # 0.4 ms and exactly 1 ms
    assert cumulative[0.0025] == 3
    assert cumulative[0.25] == 3 and cumulative[0.5] == 4
    assert cumulative[10.0] == 5  # exactly 10 s is in the last bounded bucket
    assert cumulative[math.inf] == 6  # 12.5 s only in the one past it
    assert [bound for bound, _ in durations.buckets()] == [*BUCKETS, math.inf]


def test_min_avg_p95_max_and_mdev_as_ping_prints_them():
    durations = Durations()
    assert durations.figures() is None and durations.text() == "-"
    for ms in range(100, 0, -1):  # 1..100 ms, in no particular order
        durations.add(ms / 1000)
    figures = durations.figures()
    assert figures["min"] == pytest.approx(0.001) and figures["max"] == pytest.approx(0.1)
    assert figures["avg"] == pytest.approx(0.0505)
    assert figures["p95"] == pytest.approx(0.095)  # nearest rank: the 95th of 100
    three = Durations()
    for ms in (1, 2, 3):
        three.add(ms / 1000)
    # ping(8): sqrt(mean of squares - square of the mean) = sqrt(14/3 - 4) ms
    assert three.mdev() == pytest.approx(math.sqrt(14 / 3 - 4) / 1000)
    assert three.text(("min", "avg", "max", "mdev")) == "min/avg/max/mdev 1.000/2.000/3.000/0.816 ms"


def test_the_percentile_is_of_the_most_recent_window_and_every_duration_is_in_the_histogram():
    durations = Durations()
    for _ in range(WINDOW):
        durations.add(2.0)  # a slow spell long ago...
    for _ in range(WINDOW):
        durations.add(0.002)  # ...and the device as it is now
    assert len(durations.recent) == WINDOW
    assert durations.figures()["p95"] == pytest.approx(0.002)
    assert durations.figures()["max"] == pytest.approx(2.0)
    assert durations.buckets()[-1][1] == 2 * WINDOW


def test_merged_durations_are_the_sum_of_both():
    a, b, both = Durations(), Durations(), Durations()
    for seconds in (0.003, 0.04):
        a.add(seconds)
        both.add(seconds)
    for seconds in (0.0007, 6.0):
        b.add(seconds)
        both.add(seconds)
    a.merge(b)
    assert a.buckets() == both.buckets()
    assert a.figures() == pytest.approx(both.figures())
    assert a.mdev() == pytest.approx(both.mdev())


@pytest.mark.parametrize(
    "values, fraction, expected",
    [([5], 0.95, 5), ([1, 2], 0.5, 1), ([1, 2], 0.95, 2), (list(range(1, 21)), 0.95, 19)],
)
def test_the_percentile_is_the_nearest_rank(values, fraction, expected):
    assert percentile(values, fraction) == expected


def test_a_thread_that_reads_while_another_adds_loses_none_and_counts_none_twice():
    # A plant's live view and its exporter read a device's round trips while the device's
    # link thread adds them; every read folds what is batched.
    durations, added, seen, failed = Durations(), 100 * WINDOW, [], []
    done = threading.Event()

    def read():
        try:
            while not done.is_set():
                seen.append(durations.count)
                durations.buckets()
                figures = durations.figures()
                assert figures is None or figures["min"] <= figures["p95"] <= figures["max"]
        except Exception as error:  # a thread's exception would not fail the test by itself
            failed.append(error)

    switch = sys.getswitchinterval()
    sys.setswitchinterval(1e-6)  # threads take turns as often as they can
    reader = threading.Thread(target=read)
    reader.start()
    try:
        for step in range(added):
            durations.add(0.0005 + (step % 7) / 1000)
    finally:
        done.set()
        reader.join()
        sys.setswitchinterval(switch)
    assert not failed, failed
    assert len(seen) > 10, "the reader read while the adder added"
    assert seen == sorted(seen), "a count never goes back"
    assert durations.count == added and durations.buckets()[-1][1] == added
    assert dict(durations.buckets())[0.001] == sum(1 for step in range(added) if step % 7 == 0)  # the 0.5 ms


def test_a_copy_has_every_figure_as_it_was_and_later_durations_are_not_in_it():
    durations = Durations()
    for seconds in (0.002, 0.004, 0.3):
        durations.add(seconds)
    copy = durations.copy()
    durations.add(7.0)
    assert (copy.count, copy.total) == (3, pytest.approx(0.306))
    assert copy.figures() == pytest.approx({**durations_of(0.002, 0.004, 0.3).figures()})
    assert copy.buckets() == durations_of(0.002, 0.004, 0.3).buckets()
    assert durations.count == 4


def durations_of(*seconds: float) -> Durations:
    made = Durations()
    for each in seconds:
        made.add(each)
    return made
