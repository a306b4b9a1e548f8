"""Fixture workspaces for the view_depth tests, built from synthetic ground truth
(gt_workspace.py): global/cameras.json = the synthetic cameras, global/mesh.ply = an honestly
imperfect mesh (TSDF fusion of the exact gt/geom depth at 3 cm voxels), so the rendered initial
depth has rounded, misplaced occlusion edges."""
from __future__ import annotations

from pathlib import Path

from ibr_pipeline.gt_workspace import gt_depth, tsdf_mesh, write_gt_workspace  # noqa: F401


def make_view_ws(scene_dir: Path, root: Path, voxel: float = 0.03) -> Path:
    write_gt_workspace(Path(scene_dir), Path(root), "global_mesh", global_mesh="tsdf", voxel=voxel,
                       check_pixels=False)
    return Path(root)
