"""The procedural indoor scenes: mirror_room, glass_room, curved, tiny.

World frame: right-handed, +z up, floor at z = 0, metres. The room is the box
[0, 5] x [0, 4] x [0, 2.7] with a partition wall (an alcove behind x = 3.6, y < 1.5) and a doorway
into a short corridor (y > 4), so views have occlusions. The seed jitters furniture sizes and
positions and every texture; the layout of the reflective objects is fixed so that tests can
reason about it.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .geometry import MeshBuilder, TriangleSoup
from .materials import Material
from .textures import Texture

SCENES = ("mirror_room", "glass_room", "curved", "tiny")
ROOM = (5.0, 4.0, 2.7)
GLASS_IOR = 1.5


@dataclass(frozen=True, eq=False)
class World:
    name: str
    seed: int
    soup: TriangleSoup
    lights: np.ndarray           # (L, 3) point-light positions
    light_power: np.ndarray      # (L,) intensity (radiance units at 1 m)
    ambient: float
    reflectors: tuple[dict, ...]  # planar reflectors, reflectors.json format
    objects: tuple[dict, ...] = ()  # curved reflective/refractive objects (spheres)
    path_center: tuple[float, float] = (2.3, 2.0)
    path_radius: float = 0.7
    eye_height: float = 1.45
    max_depth: int = 6
    info: dict = field(default_factory=dict)


def _tex(rng: np.random.Generator, kind: str, a, b, freq: float, contrast: float = 1.0) -> Texture:
    jit = lambda c: tuple(float(np.clip(x * rng.uniform(0.85, 1.15), 0.02, 0.9)) for x in c)  # noqa: E731
    return Texture(kind, jit(a), jit(b), freq * float(rng.uniform(0.8, 1.25)),
                   int(rng.integers(0, 2 ** 31 - 1)), contrast)


def _diffuse(name, tex) -> Material:
    return Material(name, "diffuse", tex)


def _frame(b: MeshBuilder, x: float, y0: float, y1: float, z0: float, z1: float, mat, w=0.05):
    """A picture frame on the wall x = 0 around [y0, y1] x [z0, z1]."""
    b.box((x, y0 - w, z0 - w), (x + 0.04, y0, z1 + w), mat)
    b.box((x, y1, z0 - w), (x + 0.04, y1 + w, z1 + w), mat)
    b.box((x, y0, z0 - w), (x + 0.04, y1, z0), mat)
    b.box((x, y0, z1), (x + 0.04, y1, z1 + w), mat)


def _room(b: MeshBuilder, rng: np.random.Generator) -> None:
    W, D, H = ROOM
    floor = _diffuse("floor", _tex(rng, "planks", (0.35, 0.2, 0.1), (0.75, 0.55, 0.35), 5.0))
    ceiling = _diffuse("ceiling", _tex(rng, "plaster", (0.8, 0.8, 0.78), (0.8, 0.8, 0.78), 1.0))
    wall_x0 = _diffuse("wall_west", _tex(rng, "noise", (0.35, 0.45, 0.6), (0.85, 0.8, 0.65), 6.0))
    wall_x1 = _diffuse("wall_east", _tex(rng, "plaster", (0.75, 0.7, 0.6), (0.75, 0.7, 0.6), 1.5))
    wall_y0 = _diffuse("wall_south", _tex(rng, "tiles", (0.55, 0.35, 0.3), (0.85, 0.75, 0.6), 3.0))
    wall_y1 = _diffuse("wall_north", _tex(rng, "plaster", (0.6, 0.72, 0.6), (0.6, 0.72, 0.6), 1.5))
    b.quad((0, 0, 0), (W, 0, 0), (W, D, 0), (0, D, 0), (0, 0, 1), floor)
    b.quad((0, 0, H), (0, D, H), (W, D, H), (W, 0, H), (0, 0, -1), ceiling)
    b.quad((0, 0, 0), (0, D, 0), (0, D, H), (0, 0, H), (1, 0, 0), wall_x0)
    b.quad((W, 0, 0), (W, 0, H), (W, D, H), (W, D, 0), (-1, 0, 0), wall_x1)
    b.quad((0, 0, 0), (0, 0, H), (W, 0, H), (W, 0, 0), (0, 1, 0), wall_y0)
    # north wall with a doorway x in [0.6, 1.5], z < 2.05 leading into a corridor y in [4, 5.2]
    dx0, dx1, dz = 0.6, 1.5, 2.05
    for (xa, xb, za, zb) in ((0, dx0, 0, H), (dx1, W, 0, H), (dx0, dx1, dz, H)):
        b.quad((xa, D, za), (xb, D, za), (xb, D, zb), (xa, D, zb), (0, -1, 0), wall_y1)
    corridor = _diffuse("corridor", _tex(rng, "noise", (0.5, 0.5, 0.45), (0.8, 0.75, 0.7), 4.0, 0.7))
    b.box((dx0, D, 0), (dx1, D + 1.2, dz), corridor, inward=True)
    b.quad((dx0, D, 0), (dx1, D, 0), (dx1, D + 1.2, 0), (dx0, D + 1.2, 0), (0, 0, 1), floor)
    # partition wall making an alcove behind x = 3.6, y < 1.5
    brick = _diffuse("partition", _tex(rng, "tiles", (0.6, 0.3, 0.2), (0.8, 0.55, 0.4), 5.0))
    b.box((3.55, 0.0, 0.0), (3.67, 1.5, H), brick)


def _furniture(b: MeshBuilder, rng: np.random.Generator, crates: bool = True) -> list[dict]:
    """Tables, cabinets, shelves, posters. Returns the planar glossy reflectors it placed."""
    j = lambda s=0.05: float(rng.uniform(-s, s))  # noqa: E731
    wood = _tex(rng, "noise", (0.3, 0.18, 0.1), (0.6, 0.4, 0.25), 7.0)
    table_top = Material("table_top", "glossy", wood, kr=0.15)
    legs = _diffuse("table_legs", _tex(rng, "noise", (0.15, 0.1, 0.08), (0.35, 0.25, 0.2), 8.0))
    tx, ty, tz = 1.15 + j(), 3.05 + j(), 0.76
    hx, hy = 0.6, 0.35
    b.box((tx - hx, ty - hy, tz - 0.04), (tx + hx, ty + hy, tz), legs, top=table_top)
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = tx + sx * (hx - 0.06), ty + sy * (hy - 0.06)
            b.box((cx - 0.03, cy - 0.03, 0), (cx + 0.03, cy + 0.03, tz - 0.04), legs)
    top_poly = [[tx - hx, ty - hy, tz], [tx + hx, ty - hy, tz], [tx + hx, ty + hy, tz],
                [tx - hx, ty + hy, tz]]
    reflectors = [{"name": "table_top", "plane": [0.0, 0.0, 1.0, -tz], "beta": table_top.kr,
                   "polygon": top_poly}]
    # TV: stand, body, glossy screen on the south wall (y = 0)
    stand = _diffuse("tv_stand", _tex(rng, "noise", (0.25, 0.25, 0.3), (0.55, 0.5, 0.5), 9.0))
    b.box((1.3, 0.0, 0.0), (2.7, 0.42, 0.5), stand)
    body = _diffuse("tv_body", Texture("flat", (0.04, 0.04, 0.045), (0, 0, 0)))
    b.box((1.45, 0.0, 0.85), (2.55, 0.06, 1.55), body)
    screen_tex = _tex(rng, "noise", (0.05, 0.1, 0.25), (0.6, 0.45, 0.2), 9.0, 1.2)
    screen = Material("tv_screen", "glossy", screen_tex, kr=0.3)
    sy = 0.065
    poly = [[1.5, sy, 0.9], [2.5, sy, 0.9], [2.5, sy, 1.5], [1.5, sy, 1.5]]
    b.quad(*poly, normal=(0, 1, 0), mat=screen)
    reflectors.append({"name": "tv_screen", "plane": [0.0, 1.0, 0.0, -sy], "beta": screen.kr,
                       "polygon": poly})
    # cabinet by the north wall, shelf by the east wall, ottoman, rug
    cab = _diffuse("cabinet", _tex(rng, "noise", (0.5, 0.2, 0.15), (0.9, 0.7, 0.4), 5.0))
    b.box((2.45 + j(), 3.55 + j(0.03), 0), (3.7 + j(), 4.0, 0.9 + j()), cab)
    shelf = _diffuse("shelf", _tex(rng, "tiles", (0.2, 0.3, 0.6), (0.9, 0.6, 0.2), 8.0))
    b.box((4.6 + j(0.03), 2.0 + j(), 0), (5.0, 3.4 + j(), 1.9 + j()), shelf)
    ott = _diffuse("ottoman", _tex(rng, "noise", (0.2, 0.45, 0.3), (0.75, 0.8, 0.5), 10.0))
    b.box((4.0 + j(), 1.75 + j(), 0), (4.5 + j(), 2.25 + j(), 0.45 + j()), ott)
    rug = _diffuse("rug", _tex(rng, "noise", (0.6, 0.15, 0.15), (0.9, 0.8, 0.5), 12.0))
    b.box((1.5, 1.2, 0), (3.1, 2.8, 0.01), rug)
    alc = _diffuse("alcove_cabinet", _tex(rng, "tiles", (0.3, 0.5, 0.55), (0.8, 0.85, 0.7), 6.0))
    b.box((4.2 + j(), 0.1, 0), (4.9, 0.75 + j(), 1.1 + j()), alc)
    if crates:
        crate = _diffuse("crates", _tex(rng, "planks", (0.45, 0.35, 0.2), (0.8, 0.7, 0.45), 8.0))
        b.box((0.2, 0.2, 0), (0.75 + j(), 0.75 + j(), 0.5 + j()), crate)
        b.box((0.3, 0.3, 0.5), (0.6, 0.6, 0.8 + j()), crate)
    # posters: thin boxes on the walls, colourful high-frequency prints
    for i, (lo, hi) in enumerate((((1.9, 3.985, 1.2), (2.45, 4.0, 1.9)),
                                  ((4.985, 0.35, 1.2), (5.0, 1.25, 1.95)),
                                  ((4.985, 3.5, 1.0), (5.0, 3.95, 1.7)),
                                  ((3.67, 0.3, 1.1), (3.685, 1.2, 1.8)))):
        tex = _tex(rng, "noise", tuple(rng.uniform(0.05, 0.5, 3)), tuple(rng.uniform(0.5, 0.9, 3)),
                   float(rng.uniform(8, 16)), 1.3)
        b.box(lo, hi, _diffuse(f"poster{i}", tex))
    return reflectors


def _lights() -> tuple[np.ndarray, np.ndarray]:
    pos = np.array([[1.4, 1.6, 2.35], [3.1, 2.8, 2.35], [4.3, 0.8, 2.3], [1.05, 4.7, 1.9]])
    power = np.array([1.8, 1.6, 0.9, 0.45])
    return pos, power


def build_world(name: str, seed: int = 0) -> World:
    """Build scene `name` (one of SCENES) deterministically from `seed`."""
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose from {', '.join(SCENES)}")
    rng = np.random.default_rng([seed, SCENES.index(name)])
    b = MeshBuilder()
    _room(b, rng)
    reflectors = _furniture(b, rng, crates=name != "curved")
    objects: list[dict] = []
    frame = _diffuse("frame", _tex(rng, "noise", (0.3, 0.25, 0.15), (0.55, 0.45, 0.3), 14.0))
    if name in ("mirror_room", "tiny"):
        y0, y1, z0, z1, x = 1.4, 2.6, 0.7, 2.0, 0.025
        mirror = Material("mirror", "mirror", kr=1.0)
        poly = [[x, y0, z0], [x, y1, z0], [x, y1, z1], [x, y0, z1]]
        b.quad(*poly, normal=(1, 0, 0), mat=mirror)
        _frame(b, 0.0, y0, y1, z0, z1, frame)
        reflectors.insert(0, {"name": "mirror", "plane": [1.0, 0.0, 0.0, -x], "beta": 1.0,
                              "polygon": poly})
    if name == "glass_room":  # glass partition continuing the alcove wall, in a thin frame
        glass = Material("glass", "glass_pane", ior=GLASS_IOR)
        x, y0, y1, z1 = 3.61, 1.55, 3.0, 2.3
        poly = [[x, y0, 0.0], [x, y1, 0.0], [x, y1, z1], [x, y0, z1]]
        b.quad(*poly, normal=(-1, 0, 0), mat=glass)
        b.box((3.55, 1.5, z1), (3.67, y1 + 0.05, 2.7), frame)
        b.box((3.55, y1, 0), (3.67, y1 + 0.05, z1), frame)
        r0 = ((1 - GLASS_IOR) / (1 + GLASS_IOR)) ** 2
        reflectors.insert(0, {"name": "glass", "plane": [-1.0, 0.0, 0.0, x],
                              "beta": round(2 * r0 / (1 + r0), 6), "polygon": poly,
                              "material": "glass"})
    if name == "curved":
        chrome = Material("chrome", "mirror", kr=0.85)
        crystal = Material("crystal", "dielectric", ior=GLASS_IOR, tint=(0.92, 0.97, 0.95))
        ped = _diffuse("pedestal", _tex(rng, "tiles", (0.7, 0.7, 0.72), (0.4, 0.4, 0.45), 10.0))
        for (cx, cy), r, mat in (((0.9, 1.2), 0.3, chrome), ((3.1, 3.1), 0.28, crystal)):
            b.box((cx - 0.2, cy - 0.2, 0), (cx + 0.2, cy + 0.2, 0.7), ped)
            b.sphere((cx, cy, 0.7 + r), r, mat)
            objects.append({"name": mat.name, "type": "sphere", "center": [cx, cy, 0.7 + r],
                            "radius": r, "material": mat.kind, "kr": mat.kr,
                            "ior": mat.ior if mat.kind == "dielectric" else None})
    lights, power = _lights()
    return World(name, seed, b.build(), lights, power, ambient=0.4,
                 reflectors=tuple(reflectors), objects=tuple(objects))
