"""`ibr warp`: warp an RGBZ ray tree to a new camera (Lochmann et al. 2014).

  ibr warp TREE --out new.png                       a synthetic pair file (gt/raytree/pair_NN.npz)
                                                   warps to its own new camera and prints PSNR
  ibr warp TREE --move 5 --yaw 3 --out new.png      the old camera moved 5 cm right, yawed 3 deg
  ibr warp TREE --camera cams.json --camera-name X  a camera from a cameras.json file
  ibr warp TREE --app stereo|dof|motion ...         Fig. 10 applications from one tree
  ibr warp TREE --save-tree tree.npz                convert to our one-file encoding (§3.2)
Imports nothing heavy at module level (`ibr --help` stays fast).
"""
from __future__ import annotations

import json
from pathlib import Path

from ..errors import InputError


def register(sub) -> None:
    p = sub.add_parser("warp", help="warp an RGBZ ray tree to a new camera (Lochmann et al. 2014)",
                       description="Warp an RGBZ ray tree (our .npz encoding, or a synthetic "
                       "gt/raytree/pair_NN.npz) to a new camera with diffuse, reflective and "
                       "refractive flows (Lochmann et al. 2014). Output: 8-bit linear PNG.")
    p.add_argument("tree", type=Path, help="ray tree file (.npz)")
    p.add_argument("--out", type=Path, help="output PNG (stereo: _left/_right are appended)")
    cam = p.add_argument_group("new camera (default: the pair's new camera, else --move/--yaw)")
    cam.add_argument("--camera", type=Path, help="cameras.json ({name: camera}) or one camera dict")
    cam.add_argument("--camera-name", help="which camera of --camera (default: the first)")
    cam.add_argument("--move", type=float, metavar="CM", help="move the old camera right by CM cm")
    cam.add_argument("--up", type=float, default=0.0, metavar="CM", help="and up by CM cm")
    cam.add_argument("--yaw", type=float, metavar="DEG", help="and yaw it by DEG degrees")
    app = p.add_argument_group("applications (Fig. 10)")
    app.add_argument("--app", choices=("warp", "stereo", "dof", "motion"), default="warp")
    app.add_argument("--baseline", type=float, default=0.064, help="stereo baseline, m (0.064)")
    app.add_argument("--aperture", type=float, default=0.02, help="lens radius, m (0.02)")
    app.add_argument("--focus", type=float, default=2.0, help="focus z-depth, m (2.0)")
    app.add_argument("--samples", type=int, default=12, help="dof / motion samples (12)")
    alg = p.add_argument_group("algorithm")
    alg.add_argument("--naive", action="store_true", help="baseline: warp everything with the first-hit depth")
    alg.add_argument("--normals", choices=("reconstruct", "exact"), default="reconstruct",
                     help="normals from depth (§3.3, default) or the tree's exact normals")
    alg.add_argument("--steps", type=int, default=10, help="gradient-descent steps (10, §3.4)")
    alg.add_argument("--eps-deg", type=float, default=1.0, help="undefined above this Delta (1 deg)")
    alg.add_argument("--no-fill", action="store_true", help="no push-pull hole filling (§3.5)")
    alg.add_argument("--fill-radius", type=int, default=3,
                     help="our extension: undefined specular pixels take the flow of an affine fit of "
                          "their defined neighbours within this radius (3); 0: the paper's push-pull only")
    alg.add_argument("--device", default="cpu", help="torch device: cpu (default) or cuda")
    alg.add_argument("--threads", type=int, default=2, help="CPU threads, torch and numba (2: this 2-core machine)")
    alg.add_argument("--backend", choices=("auto", "torch", "numba"), default="auto",
                     help="auto: fused numba kernels on the CPU when installed, else torch (CUDA: torch)")
    p.add_argument("--save-tree", type=Path, help="also write the tree in our encoding (§3.2)")
    p.add_argument("--json", action="store_true", help="print the result summary as JSON")
    p.set_defaults(func=main)


def _pick_camera(args, tree, target):
    from ..scene import Camera, cameras_from_json
    from ..scene import moved_camera
    if args.camera is not None:
        if not args.camera.is_file():
            raise InputError(f"--camera {args.camera}: file not found")
        try:
            data = json.loads(args.camera.read_text())
        except json.JSONDecodeError as e:
            raise InputError(f"--camera {args.camera}: invalid JSON ({e.msg})") from None
        if isinstance(data, dict) and "K" in data:
            return Camera.from_dict(data, str(args.camera))
        cams = cameras_from_json(args.camera)
        if not cams:
            raise InputError(f"--camera {args.camera}: no cameras")
        name = args.camera_name or next(iter(cams))
        if name not in cams:
            raise InputError(f"--camera-name {name}: not in {args.camera}")
        return cams[name]
    if args.move is not None or args.yaw is not None or args.up:
        return moved_camera(tree.camera(), args.move or 0.0, args.yaw or 0.0, args.up)
    if target is not None:
        return target[0]
    return moved_camera(tree.camera(), 5.0, 3.0)


def _check_args(args) -> None:
    if not (0 <= args.steps <= 1000):
        raise InputError(f"--steps must be in [0, 1000], got {args.steps}")
    if not (1e-4 <= args.eps_deg <= 90):
        raise InputError(f"--eps-deg must be in [1e-4, 90], got {args.eps_deg}")
    if not (1 <= args.samples <= 256):
        raise InputError(f"--samples must be in [1, 256], got {args.samples}")
    if args.baseline < 0 or args.aperture < 0 or args.focus <= 0:
        raise InputError("--baseline and --aperture must be >= 0 and --focus > 0")
    if args.out is None and args.save_tree is None:
        raise InputError("give --out (and/or --save-tree)")
    if args.out is not None and args.out.suffix.lower() != ".png":
        raise InputError(f"--out {args.out}: must be a .png file")
    if not 1 <= args.threads <= 256:
        raise InputError(f"--threads must be in [1, 256], got {args.threads}")
    import torch
    if args.device == "cpu":
        from ..raytree.backend import set_threads
        set_threads(args.threads)
    if args.device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise InputError(f"--device {args.device}: CUDA is not available")
    elif args.device != "cpu":
        raise InputError(f"--device must be cpu or cuda[:N], got {args.device}")
    from ..raytree.backend import resolve
    resolve(args.backend, args.device)   # e.g. --backend numba --device cuda: one-line error


def main(args) -> int:
    from ..raytree.backend import passive_omp_wait
    passive_omp_wait()   # before torch loads libgomp (see backend.passive_omp_wait)
    import numpy as np

    from ..io.images import write_image
    from ..metrics import psnr
    from ..raytree import apps
    from ..raytree.decode import DecodeOptions, decode
    from ..raytree.encoding import read_pair_target, read_tree, transmitted_bits, write_tree
    from ..raytree.specular import SpecularOptions
    from ..raytree.warp import WarpOptions, naive_warp, warp_decoded

    _check_args(args)
    tree = read_tree(args.tree)
    target = read_pair_target(args.tree)
    cam = _pick_camera(args, tree, target)
    opts = WarpOptions(decode=DecodeOptions(normals=args.normals),
                       specular=SpecularOptions(steps=args.steps, eps_deg=args.eps_deg,
                                                fill_radius=args.fill_radius),
                       fill=not args.no_fill, backend=args.backend)
    opts.validate()
    if args.normals == "exact" and tree.normal is None:
        raise InputError(f"{args.tree}: --normals exact needs a tree with exact normals")
    summary = {"tree": str(args.tree), "size": list(tree.size), "nodes": tree.n_nodes,
               "transmitted_bits": transmitted_bits(tree)}
    if args.save_tree is not None:
        write_tree(args.save_tree, tree)
        summary["saved_tree"] = str(args.save_tree)
    if args.out is not None:
        dec = decode(tree, args.device, opts.decode, backend=args.backend)
        if args.app == "stereo":
            left, right = apps.stereo_pair(dec, cam, args.baseline, opts, args.naive)
            outs = {args.out.with_name(args.out.stem + "_left.png"): left,
                    args.out.with_name(args.out.stem + "_right.png"): right}
        elif args.app == "dof":
            outs = {args.out: apps.depth_of_field(dec, cam, args.aperture, args.focus, args.samples,
                                                  opts, args.naive)}
        elif args.app == "motion":
            outs = {args.out: apps.motion_blur(dec, tree.camera(), cam, args.samples, opts, args.naive)}
        else:
            if args.naive:
                img = naive_warp(dec, cam, opts)
            else:
                res = warp_decoded(dec, cam, opts)
                img = res.image
                summary["timings_ms"] = {k: round(v * 1e3, 2) for k, v in res.timings.items()}
                summary["disocclusion_holes"] = int((~res.diffuse_ok).sum())
            outs = {args.out: img}
            same = (target is not None and cam.size == target[0].size
                    and np.allclose(cam.cam_from_world, target[0].cam_from_world))
            if same:
                summary["psnr_vs_gt"] = round(psnr(np.clip(img, 0, 1), target[1]), 3)
        for path, img in outs.items():
            write_image(path, np.clip(img, 0, 1))
        summary["written"] = [str(p) for p in outs]
    if args.json:
        print(json.dumps(summary, indent=1))
    else:
        for k, v in summary.items():
            print(f"{k}: {v}")
    return 0

