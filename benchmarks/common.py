"""What several benchmarks share: the sample scene, the machine record, a tiny scene, the logger."""
from __future__ import annotations

import logging
import os
import platform
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO / "sample_data" / "mirror_room"   # 24 views, 320x240, with depth/ and gt/


def machine() -> dict:
    """The machine a result was measured on (recorded with every JSON line)."""
    return {"cpu_count": os.cpu_count(), "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "python": sys.version.split()[0]}


def tiny_scene(folder: Path, seed: int = 3) -> Path:
    """The `tiny` synthetic scene in `folder` (generated once: reused when already there)."""
    from ibr_pipeline.synthetic.generate import SynthOptions, generate
    folder = Path(folder)
    if not (folder / "gt" / "scene.json").is_file():
        generate(SynthOptions("tiny", seed=seed, progress=False), folder)
    return folder


def logger():
    """The benchmarks' logger: a child of the package's, so `ibr -v` / `-q` apply to it."""
    return logging.getLogger("ibr_pipeline").getChild("benchmarks")
