"""Prepare the LLFF captures of docs/REAL_DATA.md from a fetched snapshot of Javlon3002/For_NeX.

Development tool, not part of the package: it writes input folders outside the repo (the images
are third-party data and are never committed). The snapshot is a bare git directory (the search
tool's `fetch` gives its path); `git archive` stops at the first blob the snapshot lacks, so every
file is read with `git cat-file`.

    .venv/bin/python scripts/prepare_llff_fornex.py GITDIR room   OUT/ROOM41
    .venv/bin/python scripts/prepare_llff_fornex.py GITDIR room   OUT/ROOM21 --every 2
    .venv/bin/python scripts/prepare_llff_fornex.py GITDIR horns  OUT/HORNS

room: COLMAP model kept (poses unchanged), camera and keypoints scaled by 0.5 (COLMAP's pixel
corners: xy * 0.5 is exact), images halved (PIL LANCZOS, JPEG q95); --every 2 keeps img001,
img003, ... (the other frames deregistered). horns: the snapshot has no images.bin, so only the
images (last odd row dropped, then halved): the pipeline's own SfM runs.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

from PIL import Image


def git_files(gitdir: Path, tree: str) -> list[tuple[str, str]]:
    out = subprocess.run(["git", "--git-dir", str(gitdir), "ls-tree", "-r", "HEAD", tree],
                         check=True, capture_output=True, text=True).stdout
    rows = []
    for line in out.splitlines():
        meta, path = line.split("\t", 1)
        rows.append((meta.split()[2], path))
    return rows


def extract(gitdir: Path, tree: str, into: Path) -> None:
    for sha, path in git_files(gitdir, tree):
        dst = into / Path(path).relative_to(tree)
        dst.parent.mkdir(parents=True, exist_ok=True)
        with open(dst, "wb") as f:
            subprocess.run(["git", "--git-dir", str(gitdir), "cat-file", "blob", sha], check=True,
                           stdout=f)


def halve(src: Path, dst: Path, crop_odd: bool) -> tuple[int, int]:
    im = Image.open(src).convert("RGB")
    w, h = im.size
    if crop_odd:
        im = im.crop((0, 0, w, h - h % 2))
        h -= h % 2
    im = im.resize((w // 2, h // 2), Image.LANCZOS)
    dst.parent.mkdir(parents=True, exist_ok=True)
    im.save(dst, quality=95)
    return im.size


def prepare_room(src: Path, out: Path, every: int) -> None:
    import numpy as np
    import pycolmap

    rec = pycolmap.Reconstruction(str(src / "sparse/0"))
    names = sorted(img.name for img in rec.images.values())
    keep = set(names[::every])
    for img in list(rec.images.values()):
        if img.name not in keep:
            rec.deregister_frame(img.frame_id)
    for cam in rec.cameras.values():
        cam.rescale(0.5)
    for img in rec.images.values():
        if img.name in keep:
            for p in img.points2D:
                p.xy = np.asarray(p.xy) * 0.5
    (out / "sparse/0").mkdir(parents=True, exist_ok=True)
    rec.write(str(out / "sparse/0"))
    for n in sorted(keep):
        halve(src / "images" / n, out / "images" / n, crop_odd=False)
    print(f"{out}: {rec.num_reg_images()} registered, {rec.num_points3D()} points, mean "
          f"reprojection error {rec.compute_mean_reprojection_error():.3f} px")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("gitdir", type=Path)
    ap.add_argument("scene", choices=("room", "horns"))
    ap.add_argument("out", type=Path)
    ap.add_argument("--every", type=int, default=1, help="keep every N-th photo (room only)")
    a = ap.parse_args(argv)
    if a.out.exists():
        print(f"{a.out}: exists; give a new folder", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        src = Path(tmp)
        extract(a.gitdir, f"dataset/{a.scene}/images", src / "images")
        if a.scene == "room":
            extract(a.gitdir, "dataset/room/sparse/0", src / "sparse/0")
            prepare_room(src, a.out, a.every)
        else:
            for p in sorted((src / "images").iterdir()):
                halve(p, a.out / "images" / p.name, crop_odd=True)
            print(f"{a.out}: {len(list((a.out / 'images').iterdir()))} images")
    return 0


if __name__ == "__main__":
    sys.exit(main())
