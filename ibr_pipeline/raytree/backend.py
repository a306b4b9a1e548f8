"""Which implementation runs the ray-tree warper: "torch" (the eager, vectorised reference; CPU or
CUDA) or "numba" (fused compiled kernels, CPU only: nbkernels.py, nbsearch.py, warp_nb.py).
"auto" picks numba for CPU tensors when numba imports, else torch."""
from __future__ import annotations

import functools
import os
import sys

BACKENDS = ("auto", "torch", "numba")


@functools.lru_cache(maxsize=1)
def numba_available() -> bool:
    try:
        import numba  # noqa: F401
    except ImportError:
        return False
    return True


def resolve(backend: str, device) -> str:
    """"torch" or "numba" for `backend` on `device`; InputError for an impossible choice."""
    import torch

    from ..errors import InputError
    if backend not in BACKENDS:
        raise InputError(f"backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    cpu = torch.device(device).type == "cpu"
    if backend == "torch":
        return "torch"
    if backend == "numba":
        if not cpu:
            raise InputError(f"backend numba runs on the CPU only, not on {device}")
        if not numba_available():
            raise InputError("backend numba: numba is not installed (pip install numba)")
        return "numba"
    return "numba" if cpu and numba_available() else "torch"


def set_threads(n: int) -> None:
    """CPU threads of both backends: torch's intra-op pool and numba's parallel kernels."""
    import torch
    torch.set_num_threads(n)
    if numba_available():
        import numba
        numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))


def passive_omp_wait() -> bool:
    """Set OMP_WAIT_POLICY=PASSIVE unless the user set a policy, if no OpenMP runtime is loaded
    yet (call before importing torch; True when set). torch and numba's "omp" layer share one
    libgomp, which reads the policy once at load; its default spinning workers took the core
    the other worker or the serial glue needed on this shared 2-core machine (bench.raytree,
    2 threads, load ~3-4: 979 ms/frame wall spinning, 235 ms passive). On a quiet machine spinning
    is the faster one (docs/RAYTREE.md): set OMP_WAIT_POLICY=ACTIVE there."""
    if "OMP_WAIT_POLICY" in os.environ or "torch" in sys.modules or "numba" in sys.modules:
        return False
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
    return True
