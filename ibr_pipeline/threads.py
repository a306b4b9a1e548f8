"""Thread pinning of worker processes: every native library's pool sized to the worker's share
of the cores. Used by the stage executors (`executors.LocalExecutor`) and by `ibr synth`'s pool,
so it sits below both."""
from __future__ import annotations


# thread-pool sizes every native library reads from the environment when it loads
# (LP_NUM_THREADS: Mesa llvmpipe's rasteriser threads, read when a GL context is created)
_THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
               "LP_NUM_THREADS")


def worker_threads(jobs: int) -> int:
    """Threads per worker when `jobs` workers share this machine's cores."""
    import os
    return max(1, (os.cpu_count() or 1) // max(1, jobs))


def limit_threads(n: int) -> None:
    """Pin this worker process's thread pools to `n` threads: OpenMP and BLAS through the
    environment (read when the libraries load) and threadpoolctl (for any already loaded), OpenCV
    too. Workers that share the cores otherwise spin against each other: a matmul of the
    reflection stage took 0.9 ms with one OpenBLAS thread and 19 ms with two beside another worker
    (issue #28). torch reads OMP_NUM_THREADS when it loads; stages that want other torch or OpenCV
    counts set them from their own `threads` field."""
    import os

    from threadpoolctl import threadpool_limits
    for var in _THREAD_ENV:
        os.environ[var] = str(n)
    threadpool_limits(limits=n)
    import cv2
    cv2.setNumThreads(n)
