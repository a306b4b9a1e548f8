"""`ibr bench synth`: timing of synthetic scene generation, one JSON line per scene."""
from __future__ import annotations

import argparse
import json

import pytest

from benchmarks import synth
from ibr_pipeline.errors import InputError


def _parse(argv):
    p = argparse.ArgumentParser()
    synth.add_arguments(p)
    return p.parse_args(argv)


def test_synth_bench_records_a_line(tmp_path):
    bargs = _parse(["tiny", "--repeats", "1", "--views", "2", "--width", "32", "--height", "24",
                    "--output", str(tmp_path / "b.jsonl")])
    assert synth.main(bargs) == 0
    rec = json.loads((tmp_path / "b.jsonl").read_text().splitlines()[-1])
    assert rec["scene"] == "tiny" and rec["median_s"] > 0
    assert {"cpu_count", "platform", "python"} <= set(rec["machine"])
    with pytest.raises(InputError, match="--repeats"):
        synth.main(_parse(["tiny", "--repeats", "0"]))


def test_unknown_scene_is_a_clear_error():
    with pytest.raises(InputError, match="NAME"):
        synth.main(_parse(["nope", "--repeats", "1"]))
