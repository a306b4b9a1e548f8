import os
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).parent
# Worker processes (spawned pools, Dask workers, subprocesses) must import tests/toy_stages.py too.
os.environ["PYTHONPATH"] = os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))


def make_toy_workspace(root: Path, n_views: int = 6) -> Path:
    """An input folder with n text 'views' and a workspace pointing at it."""
    data = root / "input" / "data"
    data.mkdir(parents=True)
    for i in range(n_views):
        (data / f"v{i:02d}.txt").write_text(f"view number {i}\n")
    ws = root / "ws"
    ws.mkdir()
    (ws / "ibr.toml").write_text(f'[input]\npath = "{(root / "input").as_posix()}"\n')
    return ws


@pytest.fixture
def toy_ws(tmp_path):
    return make_toy_workspace(tmp_path)
