"""Per-view rendering tasks of `ibr synth`, run serially or in a process pool.

Every task is a pure function of (scene, seed, camera, index): the output bytes do not depend on
which worker runs it or in which order, so generation is bit-for-bit deterministic.
"""
from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..io.images import write_depth_png, write_image
from .writers import GEOM_COMPRESSION, compose_8bit, round_depth, save_npz

log = logging.getLogger("ibr_pipeline.synthetic")
_TRACER = None  # per-process tracer, built once by _init


def _init(name: str, seed: int) -> None:
    global _TRACER
    from .scenes import build_world
    from .tracer import Tracer

    _TRACER = Tracer(build_world(name, seed))


def _init_worker(name: str, seed: int, threads: int) -> None:
    """A pool worker's initializer: its share of the cores first (`threads.limit_threads`:
    unpinned BLAS and open3d threads of two workers spin against each other), then the world."""
    from ..threads import limit_threads
    limit_threads(threads)
    _init(name, seed)


def _geom(render: dict) -> dict:
    return {"depth": round_depth(render["depth"]),
            "normal": render["normal"].astype(np.float16),
            "material": render["material"].astype(np.int16)}


def _run(args) -> dict:
    kind, i, name, cam, out, seed, sensor_wh, gt_layers = args
    out = Path(out)
    stem = Path(name).stem
    tr = _TRACER
    if kind == "raytree":
        from .raytree import composite_ray_tree, ray_tree_from_render, write_ray_tree

        old, new = cam
        r_old, r_new = tr.trace(old), tr.trace(new)
        tree = ray_tree_from_render(r_old, old)
        err = float(np.abs(composite_ray_tree(tree) - r_old["image"]).max())
        write_ray_tree(out / "gt" / "raytree" / name, tree, r_old["image"], new, r_new["image"],
                       r_new["depth"])
        return {"kind": kind, "raytree_err": err}
    r = tr.trace(cam)
    q0, q1, qb, img = compose_8bit(r["I0"], r["I1"], r["beta"])
    # Xu Eq. 3 in the stored values (by construction <= 0.5/255; checked, not assumed)
    eq3 = float(np.abs(img / 255.0 - (q0 / 255.0 + (qb / 255.0)[..., None] * q1 / 255.0)).max())
    stats = {"kind": kind, "eq3_err": eq3, "reflective": float((r["beta"] > 0).mean())}
    if kind == "capture":
        write_image(out / "images" / name, img)
        save_npz(out / "gt" / "geom" / f"{stem}.npz", GEOM_COMPRESSION, **_geom(r))
        if gt_layers:
            write_image(out / "gt" / "I0" / f"{stem}.png", q0)
            write_image(out / "gt" / "I1" / f"{stem}.png", q1)
            write_image(out / "gt" / "beta" / f"{stem}.png", qb)
        from .sensor import simulate_depth

        sw, sh = sensor_wh
        s = tr.sensor_range(cam.resized(sw, sh))
        noisy = simulate_depth(s["depth"], s["cos"], np.random.default_rng([seed, 303, i]))
        write_depth_png(out / "depth" / f"{stem}.png", noisy)
    elif kind == "test":
        write_image(out / "gt" / "test" / "images" / name, img)
        save_npz(out / "gt" / "test" / "geom" / f"{stem}.npz", GEOM_COMPRESSION, **_geom(r))
    elif kind == "fly":
        write_image(out / "gt" / "flythrough" / "images" / name, img)
    return stats


def run_jobs(opts, out: Path, jobs: list[tuple], sensor_wh: tuple[int, int]) -> list[dict]:
    """Run every (kind, index, name, camera) job; returns their stats in job order."""
    args = [(k, i, n, c, str(out), opts.seed, sensor_wh, opts.gt_layers) for k, i, n, c in jobs]
    return run_tasks(opts, _run, args, f"synth {opts.name}")


def run_tasks(opts, task, args: list[tuple], desc: str) -> list[dict]:
    """`task(a)` for every a of `args` (a module-level function: it crosses to spawned workers,
    each initialised with the scene's world by `_init`), in order, with a progress bar."""
    from tqdm import tqdm

    bar = dict(total=len(args), desc=desc, unit="view", disable=not opts.progress, leave=False)
    n_jobs = min(opts.jobs, len(args))
    if n_jobs <= 1 or len(args) < 12:  # small scenes: a pool's start-up costs more than it saves
        _init(opts.name, opts.seed)
        return [task(a) for a in tqdm(args, **bar)]
    import multiprocessing as mp

    from ..threads import worker_threads

    # spawn, not fork: open3d/embree thread pools do not survive a fork reliably
    ctx = mp.get_context("spawn")
    with ctx.Pool(n_jobs, initializer=_init_worker,
                  initargs=(opts.name, opts.seed, worker_threads(n_jobs))) as pool:
        return list(tqdm(pool.imap(task, args, chunksize=1), **bar))


