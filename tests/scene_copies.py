"""Variants of the synthetic test scenes, made on disk."""
from pathlib import Path


def srgb_copy(scene: Path, dst: Path) -> Path:
    """A copy of synthetic `scene` with its photographs stored sRGB-encoded, as a camera stores
    them (the same light; gt/scene.json says so)."""
    import json
    import shutil

    from ibr_pipeline.io.images import read_image, write_image
    shutil.copytree(scene, dst)
    for d in ("images", "gt/test/images", "gt/flythrough/images"):
        for p in sorted((dst / d).glob("*.png")):
            write_image(p, read_image(p), "srgb")
    meta = json.loads((dst / "gt" / "scene.json").read_text())
    meta["image_encoding"] = "srgb"
    (dst / "gt" / "scene.json").write_text(json.dumps(meta))
    return dst
