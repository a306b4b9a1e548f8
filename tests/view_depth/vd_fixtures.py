"""Fixture workspaces for issue #5 tests, built from synthetic ground truth before `global_mesh`
(#4) exists: global/cameras.json = the synthetic cameras, global/mesh.ply = an honestly imperfect
mesh (TSDF fusion of the exact gt/geom depth with open3d's VoxelBlockGrid at 3 cm voxels), so the
rendered initial depth has rounded, misplaced occlusion edges. Code shared with the benchmark."""
from __future__ import annotations

from pathlib import Path

from ibr_pipeline.bench.view_depth import gt_depth, make_workspace, tsdf_mesh  # noqa: F401


def make_view_ws(scene_dir: Path, root: Path, voxel: float = 0.03) -> Path:
    make_workspace(Path(scene_dir), Path(root), voxel)
    return Path(root)
