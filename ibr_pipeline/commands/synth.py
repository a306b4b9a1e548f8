"""`ibr synth NAME OUT`: a synthetic scene with exact ground truth."""
from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import InputError

SCENE_NAMES = ("mirror_room", "glass_room", "curved", "tiny")


def register(sub) -> None:
    p = sub.add_parser("synth", help="generate a synthetic scene with exact ground truth")
    add_synth_arguments(p)
    p.set_defaults(func=synth_main)


def add_synth_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("name", metavar="NAME", choices=SCENE_NAMES,
                        help=f"scene to generate: {', '.join(SCENE_NAMES)}")
    parser.add_argument("out", metavar="OUT", type=Path,
                        help="output folder (an input folder for `ibr init`; created if missing)")
    parser.add_argument("--seed", type=int, default=0,
                        help="random seed for furniture, textures and camera wobble (default 0)")
    parser.add_argument("--width", type=int, default=None,
                        help="image width in pixels (default 640; 160 for tiny)")
    parser.add_argument("--height", type=int, default=None,
                        help="image height in pixels (default 480; 120 for tiny)")
    parser.add_argument("--views", type=int, default=None,
                        help="number of capture views on the hand-held path (default 120; 8 for tiny)")
    parser.add_argument("--test-views", type=int, default=None,
                        help="held-out test views from a second path (default 15; 2 for tiny)")
    parser.add_argument("--flythrough", type=int, default=None,
                        help="frames of the smooth fly-through path (default 48; 4 for tiny)")
    parser.add_argument("--depth-scale", type=float, default=0.5,
                        help="RGB-D sensor resolution relative to colour, same aspect (default 0.5)")
    parser.add_argument("--no-gt-layers", action="store_true",
                        help="skip the Xu Eq. 3 layers gt/I0, gt/I1, gt/beta")
    parser.add_argument("--raytree-pairs", type=int, default=1,
                        help="number of Lochmann ray-tree camera pairs in gt/raytree (default 1)")
    parser.add_argument("--jobs", type=int, default=None,
                        help="worker processes (default: min(2, CPU count))")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    real = parser.add_argument_group(
        "realistic capture", "simulate a phone's photographs (docs/SYNTHETIC.md, 'Realistic captures')")
    real.add_argument("--realistic", action="store_true",
                      help="write only images/ (sRGB, noisy, vignetted, auto-exposed), no depth, "
                           "cameras or reflectors: those go to gt/ for scoring")
    real.add_argument("--noise-scale", type=float, default=1.0, metavar="S",
                      help="sensor-noise standard deviation relative to the phone preset "
                           "(0 = noiseless; default 1)")
    real.add_argument("--vignetting", type=float, default=None, metavar="A",
                      help="light lost in the image corners, 0-0.9 (default 0.25)")
    real.add_argument("--exposure-range", type=float, default=None, metavar="R",
                      help="auto-exposure gain varies smoothly within 1 +- R, 0-0.9 (default 0.3)")
    real.add_argument("--distortion", type=float, default=None, metavar="K1",
                      help="radial lens distortion k1, negative = barrel (default 0: the pipeline "
                           "does not undistort images yet)")


def _options(args: argparse.Namespace):
    from ..synthetic.generate import SynthOptions

    return SynthOptions(name=args.name, seed=args.seed, width=args.width, height=args.height,
                        views=args.views, test_views=args.test_views, flythrough=args.flythrough,
                        depth_scale=args.depth_scale, gt_layers=not args.no_gt_layers,
                        raytree_pairs=args.raytree_pairs, jobs=args.jobs,
                        progress=not args.no_progress, realistic=args.realistic,
                        noise_scale=args.noise_scale, vignetting=args.vignetting,
                        exposure_range=args.exposure_range, distortion=args.distortion)


def synth_main(args: argparse.Namespace) -> int:
    if getattr(args, "name", None) not in SCENE_NAMES:
        raise InputError(f"NAME: unknown scene {getattr(args, 'name', None)!r} "
                         f"(choose from {', '.join(SCENE_NAMES)})")
    from ..synthetic.generate import generate

    opts = _options(args)
    opts.validate()  # before touching OUT
    generate(opts, Path(args.out))
    return 0
