from __future__ import annotations

import time

import pytest


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The `tiny` scene generated once per session: (folder, summary, seconds taken)."""
    from ibr_pipeline.synthetic.generate import SynthOptions, generate

    out = tmp_path_factory.mktemp("synth") / "tiny"
    t0 = time.perf_counter()
    summary = generate(SynthOptions("tiny", seed=3, progress=False), out)
    return out, summary, time.perf_counter() - t0
