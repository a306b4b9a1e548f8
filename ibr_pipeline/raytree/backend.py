"""Which implementation runs the ray-tree warper: "torch" (the eager, vectorised reference; CPU or
CUDA) or "numba" (fused compiled kernels, CPU only: nbkernels.py, nbsearch.py, warp_nb.py).
"auto" picks numba for CPU tensors when numba imports, else torch."""
from __future__ import annotations

import functools

import torch

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
    torch.set_num_threads(n)
    if numba_available():
        import numba
        numba.set_num_threads(max(1, min(n, numba.config.NUMBA_NUM_THREADS)))
