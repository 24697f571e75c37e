"""The spool of QoS 1 messages while the broker is away (mbtool/mqtt/spool.py): bounded,
the oldest dropped and counted, kept on disk for the next run, in order."""

from __future__ import annotations

from mbtool.mqtt.spool import Message, Spool


def _message(n: int) -> Message:
    return Message(f"t/{n}", f"payload {n}".encode(), 1, False)


def test_past_its_bound_the_spool_drops_the_oldest_and_counts_them():
    spool = Spool(3)
    for n in range(10):
        spool.add(_message(n))
    assert (spool.kept, spool.dropped, len(spool)) == (10, 7, 3)
    assert spool.take() == [_message(7), _message(8), _message(9)]
    assert (len(spool), spool.sent) == (0, 3)


def test_a_spool_file_keeps_the_messages_for_the_next_run_and_stays_bounded(tmp_path):
    path = tmp_path / "mqtt.spool"
    spool = Spool(4, str(path))
    for n in range(11):  # past twice the bound: the file is rewritten, not grown for ever
        spool.add(_message(n))
    assert len(path.read_text().splitlines()) <= 8
    # A run killed here: the next one finds the newest 4, in order, and sends them.
    again = Spool(4, str(path))
    assert again.take() == [_message(n) for n in range(7, 11)]
    assert path.read_text() == ""
    assert Spool(4, str(path)).take() == []


def test_a_line_cut_short_by_a_crash_is_skipped_and_the_rest_kept(tmp_path):
    path = tmp_path / "mqtt.spool"
    spool = Spool(10, str(path))
    spool.add(_message(1))
    spool.add(_message(2))
    with path.open("a") as file:
        file.write('["t/3", "cGF5')  # the write a kill interrupted
    assert Spool(10, str(path)).take() == [_message(1), _message(2)]
