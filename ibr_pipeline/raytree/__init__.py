"""Lochmann et al. 2014: warping an RGBZ ray tree (diffuse / reflective / refractive nodes) to a
new camera. encoding (§3.2), decode (§3.3), diffuse + specular (§3.4), fill + warp (§3.5),
apps (Fig. 10); `ibr warp` in cli.py. Submodules import torch; this package file imports nothing.
See docs/RAYTREE.md."""
