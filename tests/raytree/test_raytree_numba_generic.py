"""The numba-vs-torch agreement tests once more on other floating-point details than this CPU's:
numba compiled for its generic x86-64 target (no FMA contraction, no AVX) and torch's scalar
(DEFAULT) kernels. A margin that holds only for this machine's vector width or contraction
shows up here on any machine, CI's included."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("numba")

HERE = Path(__file__).parent
ENV = {"NUMBA_CPU_NAME": "generic", "ATEN_CPU_CAPABILITY": "default"}


def test_numba_agreement_on_generic_cpu():
    env = dict(os.environ, **ENV)
    probe = ("import numba.core.config as c, torch; "
             "print(c.CPU_NAME, torch.backends.cpu.get_cpu_capability())")
    seen = subprocess.run([sys.executable, "-c", probe], env=env, capture_output=True, text=True,
                          check=True).stdout.split()
    assert seen == ["generic", "DEFAULT"], seen   # the settings took effect
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-m", "not slow",
                        str(HERE / "test_raytree_numba.py")], env=env, capture_output=True, text=True,
                       timeout=1200)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]
