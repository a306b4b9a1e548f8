import os
import sys
import time
from pathlib import Path

import pytest

TESTS = Path(__file__).parent
# Worker processes (spawned pools, Dask workers, subprocesses) must import tests/toy_stages.py too.
os.environ["PYTHONPATH"] = os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))
sys.path.insert(1, str(TESTS.parent))  # the repo root, for the top-level benchmarks/ package

from toy_stages import make_toy_workspace  # noqa: E402  (needs the path above)


@pytest.fixture
def toy_ws(tmp_path):
    return make_toy_workspace(tmp_path)


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The `tiny` synthetic scene (8 views, 160x120, a mirror) generated once per session:
    (folder, summary, seconds taken). Read-only for tests: copy what you modify."""
    from ibr_pipeline.synthetic.generate import SynthOptions, generate

    out = tmp_path_factory.mktemp("synth") / "tiny"
    t0 = time.perf_counter()
    summary = generate(SynthOptions("tiny", seed=3, progress=False), out)
    return out, summary, time.perf_counter() - t0


@pytest.fixture(scope="session")
def sample_scene():
    """sample_data/mirror_room (24 views, 320x240, with depth/ and gt/). Read-only."""
    return Path(__file__).parent.parent / "sample_data" / "mirror_room"


def chromium() -> str:
    from ibr_pipeline.viewer.browser import EXECUTABLES, chromium_path
    path = chromium_path()
    if path:
        return path
    if os.environ.get("IBR_SKIP_BROWSER") == "1":
        pytest.skip("IBR_SKIP_BROWSER=1 and no Chromium")
    pytest.fail(f"no {' or '.join(EXECUTABLES)} on PATH: `make install` installs Debian's "
                "chromium-headless-shell (scripts/install_system_deps.sh)")


@pytest.fixture(scope="session")
def browser():
    from playwright.sync_api import sync_playwright

    from ibr_pipeline.viewer.browser import launch
    chromium()
    with sync_playwright() as p:
        b = launch(p)
        yield b
        b.close()
