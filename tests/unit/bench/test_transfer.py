"""The transfer policy's cost harness (``scmbridge bench transfer``) measures every figure it names, with the paper's
store and with change detection (``--adapt``), and says which store it measured."""

from __future__ import annotations

import argparse
import json

import pytest

from bench import transfer


@pytest.mark.parametrize("adapt", [False, True])
def test_the_harness_times_every_step_of_a_full_store(capsys, adapt: bool) -> None:
    ap = argparse.ArgumentParser()
    transfer.arguments(ap)
    assert transfer.run(ap.parse_args(["--n", "60"] + (["--adapt"] if adapt else []))) == 0
    text = capsys.readouterr().out
    out = json.loads(text[text.index("{\n"):])
    assert out["adapt"] is adapt and out["refined_pairs"] == 121  # every cell of the 11 x 11 grid
    for key in ("map_hit_us", "map_rebuild_us", "ingest_us", "map_stream_us", "map_holes_us"):
        assert out[key]["n"] > 0 and 0 < out[key]["median"] <= out[key]["p99"], key
    assert out["ingest_us"]["n"] == 5 * 121 and sum(out["methods"].values()) == 60
