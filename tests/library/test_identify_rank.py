"""identify's judgement (mbtool.library.identify), in-process: what each read gave, the
time budget, and the order of the candidates."""

from __future__ import annotations

import math

from helpers.fakes import device_executor

from mbtool.codec.errors import FrameError
from mbtool.device.datafile import load_data
from mbtool.device.device import Device
from mbtool.library import load_named_map, twin_path
from mbtool.library.identify import probe, rank

HEADERS = {name: load_named_map(name).header for name in ("sdm630", "sdm72", "em24")}


def twin_executor(name: str, requests: list):
    model, _ = load_data(str(twin_path(name)), frozenset({1}))
    return device_executor(Device(model), requests)


def test_each_register_is_read_once_and_the_twins_map_ranks_first():
    requests: list = []
    answers = probe(twin_executor("sdm72", requests), HEADERS, deadline=math.inf)
    asked = [(r.function_code, r.address, r.count) for r in requests]
    assert len(asked) == len(set(asked)) == len(answers)
    candidates = rank(HEADERS, answers, {})
    assert [c.name for c in candidates][:2] == ["sdm72", "sdm630"]
    assert candidates[0].complete and not candidates[1].complete


def test_a_spent_budget_reads_nothing_more_and_says_so():
    requests: list = []
    answers = probe(twin_executor("sdm630", requests), HEADERS, deadline=0.0)
    assert requests == []
    assert {answer.missing for answer in answers.values()} == {"not read: time budget spent"}
    assert rank(HEADERS, answers, {}) == []


def test_a_garbled_reply_is_an_answer_of_its_own_and_the_walk_goes_on():
    requests: list = []
    execute = twin_executor("sdm630", requests)

    def garbling(request):
        if request.address == 0:
            raise FrameError("bad CRC")
        return execute(request)

    answers = probe(garbling, HEADERS, deadline=math.inf)
    assert answers[("input", 0, 2)].missing == "a bad reply: bad CRC"
    assert len(requests) == len(answers) - 1  # every other register was still read
    sdm630 = next(c for c in rank(HEADERS, answers, {}) if c.name == "sdm630")
    assert not sdm630.complete and "not: 30001 float32 in 80..300: a bad reply: bad CRC" in sdm630.evidence


def test_a_vendor_and_model_named_in_fc43_outrank_a_signature():
    answers = probe(twin_executor("sdm630", []), HEADERS, deadline=math.inf)
    objects = {"VendorName": "Eastron", "ProductCode": "SDM72D-M-2"}
    first = rank(HEADERS, answers, objects)[0]
    assert first.name == "sdm72" and first.evidence[0].startswith('FC 43/14 VendorName "Eastron"')
