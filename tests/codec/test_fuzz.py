"""A short run of scripts/fuzz.py (the long one is run by hand): random and mutated reply frames
through every framer and the client's receive path end in a reply or one of mbtool's own errors, never a crash."""

from __future__ import annotations

import importlib.util

import pytest
from helpers.run import REPO_ROOT


def load_fuzz():
    spec = importlib.util.spec_from_file_location("fuzz", REPO_ROOT / "scripts" / "fuzz.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


fuzz = load_fuzz()


@pytest.mark.parametrize("framing", ["rtu", "ascii", "tcp"])
def test_fuzzed_frames_never_crash(framing):
    result = fuzz.run(framing, frames=2000, seed=20261122)
    assert result["crashes"] == []
    for kind in ("random", "mutated"):
        for path in ("decoder", "client"):
            assert sum(result["outcomes"][f"{kind} {path}"].values()) == 2000
    # The mutations keep enough valid replies that the happy path is exercised too.
    assert result["outcomes"]["mutated client"]["reply"] > 0


def test_every_seed_reply_is_decoded_by_every_framer():
    for framing in ("rtu", "ascii", "tcp"):
        for request, reply in fuzz.seeds():
            adu = fuzz.make_framer(framing).build(fuzz.UNIT, reply, fuzz.TRANSACTION_ID)
            outcome = fuzz.through_client(framing, request, [adu])
            assert outcome in ("reply", "ModbusException"), (framing, request, outcome)
