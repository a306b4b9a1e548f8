"""Procedural indoor scenes rendered by a Whitted ray tracer: the ground truth of every test.

Entry points: `generate.generate(SynthOptions(...), out)` (the `ibr synth` command),
`scenes.build_world`, `tracer.Tracer`, `raytree` (Lochmann et al. ray trees). Heavy imports
(open3d) happen inside those modules, not here. Conventions: docs/SYNTHETIC.md.
"""
