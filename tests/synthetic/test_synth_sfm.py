"""Slow: pycolmap SfM (SIFT, sequential matching, incremental mapping) registers >= 95 % of
mirror_room's capture views, as the global-mesh stage will need."""
from __future__ import annotations

import logging
from pathlib import Path

import pytest

log = logging.getLogger(__name__)


def register_fraction(scene_dir: Path, work: Path) -> float:
    """Run SIFT SfM on scene_dir/images; return the fraction of images in the largest model."""
    import pycolmap

    from ibr_pipeline.scene import cameras_from_json

    images = sorted(p.name for p in (scene_dir / "images").glob("*.png"))
    db = work / "database.db"
    # one PINHOLE camera with the known focal length as prior (a phone's EXIF gives as much);
    # COLMAP's principal point is ours + 0.5 px
    K = next(iter(cameras_from_json(scene_dir / "cameras.json").values())).K
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{K[0, 0]},{K[1, 1]},{K[0, 2] + 0.5},{K[1, 2] + 0.5}"
    pycolmap.extract_features(db, scene_dir / "images", camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, device=pycolmap.Device.cpu)
    pycolmap.match_sequential(db, device=pycolmap.Device.cpu)
    models = pycolmap.incremental_mapping(db, scene_dir / "images", work / "sparse")
    best = max((len([i for i in m.images.values() if i.has_pose]) for m in models.values()),
               default=0)
    return best / len(images)


@pytest.mark.slow
def test_mirror_room_sfm_registers_95_percent(tmp_path_factory):
    from ibr_pipeline.synthetic.generate import SynthOptions, generate

    root = tmp_path_factory.mktemp("mirror_room_sfm")
    generate(SynthOptions("mirror_room", progress=False, test_views=0, flythrough=0,
                          raytree_pairs=0), root / "scene")
    frac = register_fraction(root / "scene", root)
    log.warning("SfM registered %.1f %% of mirror_room capture views", 100 * frac)
    assert frac >= 0.95
