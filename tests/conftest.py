import os
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).parent
# Worker processes (spawned pools, Dask workers, subprocesses) must import tests/toy_stages.py too.
os.environ["PYTHONPATH"] = os.pathsep.join([str(TESTS), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
if str(TESTS) not in sys.path:
    sys.path.insert(0, str(TESTS))

from toy_stages import make_toy_workspace  # noqa: E402  (needs the path above)


@pytest.fixture
def toy_ws(tmp_path):
    return make_toy_workspace(tmp_path)
