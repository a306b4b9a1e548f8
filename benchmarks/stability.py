"""The stability sweeps of `ibr bench pipeline SCENE --stability`: one degraded input at a time.

Amounts span these ranges: pose noise 0-1 degree and 0-5 cm, depth noise and holes, down to
25 % of the views, textureless walls, a missed and a wrongly given reflector, and held-out cameras
pulled out of the captured region. See degrade.py for what each kind does.
"""
from __future__ import annotations

from .grid import Setting

SWEEPS = {
    "pose_rot": (0.25, 0.5, 1.0),          # degrees
    "pose_trans": (0.01, 0.025, 0.05),     # metres
    "depth_noise": (0.01, 0.03),           # metres (sigma), on top of the sensor model
    "depth_holes": (0.1, 0.3),             # fraction of 8x8 blocks dropped
    "views": (0.75, 0.5, 0.25),            # fraction of capture views kept
    "textureless": (1.0,),                 # walls flattened to their mean colour
    "reflector_missing": (1.0,),           # reflectors.json emptied
    "reflector_wrong": (0.1, 0.3),         # plane shifted (m) and tilted (rad) by this much
    "far_camera": (0.5, 1.5),              # held-out cameras pulled back (m)
}
# chart axis per kind: (label, the amount that means "not degraded", i.e. where `default` sits)
AXES = {"pose_rot": ("rotation noise per view (°)", 0.0),
        "pose_trans": ("position noise per view (m)", 0.0),
        "depth_noise": ("depth noise σ (m)", 0.0), "depth_holes": ("depth blocks dropped (fraction)", 0.0),
        "views": ("capture views kept (fraction)", 1.0), "textureless": ("walls flattened (0/1)", 0.0),
        "reflector_missing": ("reflectors.json emptied (0/1)", 0.0),
        "reflector_wrong": ("plane shift (m) and tilt (rad)", 0.0),
        "far_camera": ("test cameras pulled back (m)", 0.0)}


def stability_settings() -> list[Setting]:
    return [Setting(f"{kind}_{amount:g}", f"{kind} = {amount:g}", group="stability",
                    degrade=(kind, float(amount)))
            for kind, amounts in SWEEPS.items() for amount in amounts]
