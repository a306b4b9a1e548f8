"""Frame time and held-out PSNR of one workspace's IBR model: run by `ibr bench speed` as a
script, with the source tree being timed first on PYTHONPATH, so it uses only what every version
of the package has (IBRModel.load / render, cameras_from_json, read_image, metrics.psnr) and
imports nothing from benchmarks/.

    python benchmarks/speed_frames.py WS SCENE   ->  one JSON line on stdout
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np


def main(ws_path: str, scene_path: str) -> dict:
    from ibr_pipeline import metrics
    from ibr_pipeline.io.images import read_image
    from ibr_pipeline.render.ibr import IBRModel
    from ibr_pipeline.scene import cameras_from_json
    from ibr_pipeline.workspace import Workspace

    scene = Path(scene_path)
    model = IBRModel.load(Workspace(ws_path), layers=True)
    fly = list(cameras_from_json(scene / "gt" / "flythrough_cameras.json").values())
    passes = []
    for _ in range(2):  # the first pass compiles shaders and uploads textures
        prev, rows = None, []
        for cam in fly:
            f = model.render(cam, previous=prev)
            prev = f
            rows.append((f.ms, f.timings["gl_ms"], f.timings["post_ms"], len(f.selected)))
        passes.append(np.array(rows))
    t = passes[-1]
    test = cameras_from_json(scene / "gt" / "test_cameras.json")
    psnr, held = [], []
    for rep in range(3):  # held-out cameras: PSNR once, time over the last two passes
        for name, cam in test.items():
            f = model.render(cam)
            if rep == 0:
                psnr.append(metrics.psnr(read_image(scene / "gt" / "test" / "images" / name),
                                         f.color))
            else:
                held.append((f.ms, f.timings["gl_ms"], f.timings["post_ms"],
                             1 - float(f.covered.mean())))
    h = np.array(held)
    return {"median_ms": float(np.median(t[:, 0])), "p90_ms": float(np.percentile(t[:, 0], 90)),
            "median_gl_ms": float(np.median(t[:, 1])), "median_post_ms": float(np.median(t[:, 2])),
            "mean_selected_views": float(t[:, 3].mean()), "frames": len(fly),
            "psnr": float(np.mean(psnr)), "test_views": len(psnr),
            "heldout_median_ms": float(np.median(h[:, 0])),
            "heldout_median_gl_ms": float(np.median(h[:, 1])),
            "heldout_median_post_ms": float(np.median(h[:, 2])),
            "heldout_holes": float(np.mean(h[:, 3]))}


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], sys.argv[2])))
