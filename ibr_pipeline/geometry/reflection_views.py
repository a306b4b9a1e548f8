"""The views of a workspace seen for each planar reflector, and the per-view, per-reflector
two-layer decomposition (Xu et al. §4.3): what the `reflection` stage runs, as library code
(the stage reads, calls and writes; the benchmarks call the same functions).

* `Loader(ws, scene, cfg)`: reads every registered view at working resolution and builds the
  reflector masks, mirror-world footprints (M1 depth, §4.3.1) and full `ViewGeom`s on demand.
* `compute_planes`: the user's reflectors plus planes of G detected by the multi-view cue.
* `decompose_reflector`: neighbour selection, the reflected-scene prior, one or two passes of
  geometry.decompose (§4.3.3).

The mathematics is in planes.py, grid_warp.py, decompose.py, reflector_detect.py,
reflection_prior.py; docs/REFLECTION.md explains the choices.
"""
from __future__ import annotations

from dataclasses import dataclass

from .. import layout as L
from ..config import StageConfig, param
from ..errors import ConfigError, InputError
from .decompose import DecomposeOptions
from .user_reflectors import user_reflectors


@dataclass(frozen=True)
class ReflectorViewsConfig(StageConfig):
    """What a `Loader` reads views with: shared by the `reflectors` stage (detection) and the
    `reflection` stage (decomposition), each from its own table, so detection may run at its own
    working resolution."""

    work_scale: float = param(1.0, "working resolution as a fraction of the image size (demo budget; "
                              "1.0 = full quality)",
                              min=0.1, max=1.0)
    min_mask_pixels: int = param(100, "smaller reflector masks (at working size) are ignored",
                                 min=1, max=10**7)
    min_gap: float = param(0.03, "M1: reflected-ray hits closer than this to the plane (noise of a "
                           "fused G) are skipped (scene-frame units: docs/DESIGN.md)",
                           min=0.0, max=1.0)
    prior_tol: float = param(0.03, "depth tolerance (x depth) of the prior's visibility test",
                             min=1e-4, max=1.0)
    prior_views: int = param(16, "the reflected-scene colour prior is the median over at most "
                             "this many views: those that see most of the reflected points",
                             min=1, max=10000)


@dataclass(frozen=True)
class ReflectorsConfig(ReflectorViewsConfig):
    """Stage `reflectors`: which planes are reflectors (user-given + detected)."""

    use_user_reflectors: bool = param(True, "use input/reflectors.json planes (the paper's UI)")
    detect: str = param("auto", "detect reflective planes of G by the multi-view consistency cue: "
                        "'auto' = only when no input/reflectors.json is given (or it is not used), "
                        "'on' = always (user planes win on overlap), 'off' = never",
                        choices=("auto", "on", "off"))
    ransac_distance: float = param(0.008, "RANSAC inlier distance for planes of G (scene-frame units)",
                                   min=1e-4, max=0.5)
    max_planes: int = param(30, "RANSAC planes extracted from G (detection candidates)", min=1, max=500)
    detect_threshold: float = param(0.02, "median surface-warp error above which a plane is a "
                                    "reflector (linear intensity)", min=1e-4, max=1.0)
    detect_beta: float = param(0.05, "a plane whose Eq. 3 reflectance fit from view differences "
                               "(reflector_detect.reflectance_cue) is at least this, with "
                               "correlation >= detect_corr, is a reflector (weak reflectors); "
                               "0 = off", min=0.0, max=1.0)
    detect_corr: float = param(0.4, "see detect_beta (synthetic reflectors fit 0.51-0.88, diffuse "
                               "planes of a real capture up to 0.33: docs/REFLECTION.md)",
                               min=0.0, max=1.0)
    detect_min_pairs: int = param(4, "view pairs a detected reflector must be scored on",
                                  min=1, max=1000)
    detect_min_fit: float = param(0.005, "the Eq. 3 fit (detect_beta) counts only over at least "
                                  "this fraction of one view's pixels, on a candidate covering "
                                  "as much of one view (the synthetic table top: 7 %; a false "
                                  "wall of llff_horns: 0.05 %; a sliver of llff_room21: 0.12 % "
                                  "per view)", min=0.0, max=1.0)
    mirror_ratio: float = param(0.5, "mirror-warp / surface-warp error below which a detected "
                                "reflector is a mirror (beta = 1, I0 = 0)", min=0.0, max=10.0)
    detect_explained: bool = param(True, "a surface-warp error above detect_threshold makes a "
                                   "reflector only when a reflection explains it (mirror warp "
                                   "below mirror_ratio, or the Eq. 3 fit); false: the error alone")


@dataclass(frozen=True)
class ReflectionConfig(ReflectorViewsConfig):
    """Stage `reflection`: the per-view two-layer decomposition of the planes `reflectors` wrote."""

    mesh_step: int = param(2, "M1 grid mesh: one vertex every N working pixels", min=1, max=64)
    m1_simplify: bool = param(True, "quadric-simplify M1 like the per-view surface mesh (§4.2.3, "
                              "view_mesh's adaptive target): flat reflected walls need few "
                              "triangles, and llvmpipe's frame time grows with them")
    m1_max_vertices_640x480: int = param(20000, "M1 vertex budget per view, scaled by pixel count "
                                         "(view_mesh's default)", min=3, max=10_000_000)
    m1_tol_score: float = param(0.002, "M1 adaptive target: accept a coarser mesh while its mean "
                                "relative depth error grows by at most this (view_mesh's default)",
                                min=0.0, max=1.0)
    accept_test: bool = param(True, "keep a view's decomposition of a reflector only when its two "
                              "layers predict other captures of the reflector better than the "
                              "unsplit photo (reflection_layers.predict_views); else that "
                              "reflector is single layer in the view")
    accept_views: int = param(2, "captures predicted by accept_test (nearest first, not the "
                              "decomposition's neighbours when others see the reflector)",
                              min=1, max=100)

    decompose: DecomposeOptions = param(DecomposeOptions(), "the two-layer decomposition (§4.3)")


def split_overrides(over: dict) -> dict[str, dict]:
    """{field: value} for either stage -> {"reflectors": ..., "reflection": ...}: each field to
    the stage that has it, the Loader's shared fields to both. A field neither stage has is a
    ConfigError naming it."""
    import dataclasses
    tables = {}
    for stage, cls in (("reflectors", ReflectorsConfig), ("reflection", ReflectionConfig)):
        names = {f.name for f in dataclasses.fields(cls)}
        tables[stage] = {k: v for k, v in over.items() if k in names}
    for k in over:
        if not any(k in t for t in tables.values()):
            raise ConfigError(f"reflection.{k}", "no such field in stage reflectors or reflection")
    return tables


def stage_configs(*layers: dict) -> tuple["ReflectorsConfig", "ReflectionConfig"]:
    """Both stages' configs from layers of overrides applied in turn (benchmarks, tests),
    `split_overrides` of each; validated."""
    from ..config import build_config
    split = [split_overrides(d) for d in layers]
    return (build_config(ReflectorsConfig, "reflectors", *(t["reflectors"] for t in split)),
            build_config(ReflectionConfig, "reflection", *(t["reflection"] for t in split)))


# --- loading ------------------------------------------------------------------------------------
class Loader:
    """Reads views at working resolution and builds ViewGeoms; caches within one process.

    Memory stays bounded with the number of views (a 120-view 640x480 capture grew two workers to
    9 GB each when every view's full ViewGeom was kept): every view keeps only its images and, per
    reflector, a `Footprint` (beta support + M1 depth, what neighbour selection reads); full
    ViewGeoms (surface and mirror-world points) are rebuilt on demand and kept in a small LRU."""

    GEOM_CACHE = 16  # full ViewGeoms kept: a view + its <= 6 neighbours, with room to spare

    def __init__(self, ws, scene, cfg: "ReflectorViewsConfig"):
        from collections import OrderedDict

        from ..io.mesh import read_ply
        from .raycast import build_scene

        self.ws, self.scene_manifest, self.cfg = ws, scene, cfg
        self.cams = L.registered_cameras(ws)
        self.names = registered_views(ws, scene)
        G = read_ply(ws.path(L.GLOBAL_MESH))
        if len(G.faces) == 0:
            raise InputError(f"{ws.path(L.GLOBAL_MESH)}: global mesh has no triangles")
        self.G = G
        self.scene = build_scene(G.vertices, G.faces)
        self._raw: dict = {}
        self.bounds = (G.vertices.min(0), G.vertices.max(0))  # rays leaving G end on its box
        self._masks: dict = {}
        self._fp: dict = {}    # footprints
        self._full: OrderedDict = OrderedDict()  # LRU of full ViewGeoms
        self.first: dict = {}  # first-pass R of views (multi-view pass only)

    def camera(self, name):
        cam = self.cams[name]
        s = self.cfg.work_scale
        if s >= 1.0:
            return cam
        return cam.resized(max(8, round(cam.width * s)), max(8, round(cam.height * s)))

    def raw(self, name):
        """(full image, full depth, working camera, working image, working depth)."""
        if name in self._raw:
            return self._raw[name]
        import cv2
        import numpy as np

        from ..io.images import read_image
        cam = self.cams[name]
        img = read_image(self.ws.path(self.scene_manifest.view(name).image),
                         self.scene_manifest.image_encoding)
        dkey = self.ws.view_file(name, L.DEPTH)
        try:
            depth = np.load(self.ws.path(dkey)).astype(np.float64)
        except (OSError, ValueError) as e:
            raise InputError(f"{self.ws.path(dkey)}: cannot read depth ({e})") from None
        if depth.shape != (cam.height, cam.width) or img.shape[:2] != depth.shape:
            raise InputError(f"{self.ws.path(dkey)}: depth is {depth.shape}, image is "
                             f"{img.shape[:2]}, camera is {cam.height}x{cam.width}")
        if not np.all(np.isfinite(depth)):
            raise InputError(f"{self.ws.path(dkey)}: depth has NaN/inf (0 means no depth)")
        wc = self.camera(name)
        img = np.asarray(img, np.float32)  # kept for every view: float32 (ViewGeoms: float64)
        if wc is cam:
            wi, wd = img, depth
        else:
            wi = cv2.resize(img, (wc.width, wc.height), interpolation=cv2.INTER_AREA)
            wd = cv2.resize(depth, (wc.width, wc.height), interpolation=cv2.INTER_NEAREST)
        self._raw[name] = (img, depth, wc, wi, wd)
        return self._raw[name]

    def mask(self, name, refl):
        key = (name, refl["name"])
        if key not in self._masks:
            self._masks[key] = self._mask(name, refl)
        return self._masks[key]

    def forget(self, refl_name: str) -> None:
        """Drop every cached mask, footprint and ViewGeom of reflector `refl_name`."""
        for cache in (self._masks, self._fp, self._full):
            for key in [k for k in cache if k[1] == refl_name]:
                del cache[key]

    def prior(self, name, refl, reflectors, geom=None):
        """beta * reflected-scene colour (H, W, 3), NaN where unobserved (reflection_prior.py),
        from the views whose frustum holds some of the reflected points (the others cannot see
        them: their images and masks are not needed), at most `prior_views` of them. `geom`:
        the view's ViewGeom for `refl` when the caller holds it."""
        import numpy as np

        from .reflection_prior import (reflected_points, reflected_scene_colour, sample_points,
                                       views_in_frustum)
        g = geom if geom is not None else self.geom(name, refl)
        X1 = np.where(g.mask[..., None], g.X1, np.nan)
        Xr, _ = reflected_points(X1, refl["plane"])
        views = []
        for i in views_in_frustum(sample_points(Xr), [self.camera(o) for o in self.names]):
            _, _, wc, wi, wd = self.raw(self.names[i])
            masks = [self.mask(self.names[i], r) for r in reflectors]  # read, not written
            ex = (np.zeros(wd.shape, bool) if not masks else masks[0] if len(masks) == 1
                  else np.logical_or.reduce(masks))
            views.append((wc, wi, wd, ex))
        C = reflected_scene_colour(X1, refl["plane"], views, tol=self.cfg.prior_tol,
                                   max_views=self.cfg.prior_views)
        return float(refl.get("beta") or 1.0) * C

    def _mask(self, name, refl):
        import cv2
        import numpy as np

        from .planes import reflector_mask
        _, _, wc, _, wd = self.raw(name)
        if refl.get("masks", {}).get(name):  # a user mask overrides the projected extent
            from ..io.images import read_image
            m = read_image(self.ws.path(refl["masks"][name])).mean(2) > 0.5
            m = cv2.resize(m.astype(np.uint8), (wc.width, wc.height),
                           interpolation=cv2.INTER_NEAREST) > 0
            return m & (wd > 0)
        poly = None if refl.get("polygon") is None else np.asarray(refl["polygon"])
        return reflector_mask(wc, refl["plane"], poly, wd, rel_tol=0.02,
                              transmits=refl.get("material") == "glass")

    def footprint(self, name, refl) -> "Footprint":
        """The view's beta support and M1 depth for `refl` (mirror points cast into G, §4.3.1)."""
        key = (name, refl["name"])
        if key not in self._fp:
            import numpy as np

            from .planes import mirror_points
            _, _, wc, _, _ = self.raw(name)
            m = self.mask(name, refl)
            _, D1 = mirror_points(wc, refl["plane"], m, self.scene, min_gap=self.cfg.min_gap,
                                  bounds=self.bounds)
            self._fp[key] = Footprint(name, wc, m, D1.astype(np.float32))
        return self._fp[key]

    def transmitted(self, g, refl):
        """ViewGeom `g` with X1 / D1 replaced by the geometry behind the plane on each mask
        pixel's camera ray (`mirror_points(transmit=True)`): what glass would show."""
        import dataclasses

        from .planes import mirror_points
        Xt, Dt = mirror_points(g.camera, refl["plane"], g.mask, self.scene,
                               min_gap=self.cfg.min_gap, bounds=self.bounds, transmit=True)
        return dataclasses.replace(g, X1=Xt, D1=Dt)

    def geom(self, name, refl, masked: bool = False):
        """The full ViewGeom (LRU-cached). M1's points are rebuilt from the footprint's depth:
        `mirror_points` puts every mirror-world point on its pixel's camera ray. `masked`: the
        surface points X0 only inside the reflector mask (NaN elsewhere), all that detection
        reads of them."""
        key = (name, refl["name"]) + (("masked",) if masked else ())
        if key in self._full:
            self._full.move_to_end(key)
            return self._full[key]
        import numpy as np

        from .decompose_terms import ViewGeom
        from .planes import depth_points
        _, _, wc, wi, wd = self.raw(name)
        fp = self.footprint(name, refl)
        D1 = fp.D1.astype(np.float64)
        X0 = depth_points(wc, np.where(fp.mask, wd, 0.0) if masked else wd)
        g = ViewGeom(name, wc, wi.astype(np.float64), wd, fp.mask, X0, depth_points(wc, D1), D1)
        self._full[key] = g
        while len(self._full) > self.GEOM_CACHE:
            self._full.popitem(last=False)
        return g


@dataclass
class Footprint:
    """What neighbour selection (`decompose.select_neighbours`) reads of another view."""

    name: str
    camera: object
    mask: object  # (H, W) bool beta support
    D1: object    # (H, W) float32 z-depth of M1 (0 = none)


# --- reflector planes (shared by every view) ------------------------------------------------------
def registered_views(ws, scene) -> list[str]:
    """The views `global_mesh` registered, in scene order."""
    cams = L.registered_cameras(ws)
    return [n for n in scene.names if n in cams]


def user_reflectors_key(ws, scene) -> list[str]:
    """The user's reflectors in the scene frame (written by `poses` from input/reflectors.json),
    the depth maps their outlines are placed with, and the reflectors `global_mesh` found."""
    found = [L.FOUND_REFLECTORS] if ws.exists(L.FOUND_REFLECTORS) else []
    if not ws.exists(L.USER_REFLECTORS):
        return found
    return [L.SCENE_REFLECTORS] + L.outline_keys(ws, scene) + found


def found_reflectors(ws) -> tuple[list[dict], list[dict]]:
    """(reflectors, candidates) that `global_mesh` found behind planes of the MVS depth
    (global/found_reflectors.json; none when it is absent)."""
    if not ws.exists(L.FOUND_REFLECTORS):
        return [], []
    import json
    data = json.loads(ws.path(L.FOUND_REFLECTORS).read_text())
    out = []
    for d in data.get("reflectors", []):
        d = dict(d)
        d["source"] = "depth"
        out.append(d)
    cands = [{"name": c["name"], "plane": c["plane"], "score": c.get("score", {}),
              "views": len(c.get("views", [])), "kept": c["kept"],
              "reason": "global_mesh: " + c["reason"]} for c in data.get("candidates", [])]
    return out, cands


def detect_enabled(ws, cfg: "ReflectorsConfig") -> bool:
    """`detect`: 'on' / 'off', or 'auto' = detect only when no user reflectors are used."""
    if cfg.detect == "auto":
        return not (cfg.use_user_reflectors and ws.exists(L.USER_REFLECTORS))
    return cfg.detect == "on"


def plane_candidates(loader: Loader) -> list[dict]:
    """The planar pieces of G (RANSAC on an area-proportional sample), normals towards the
    cameras: what detection scores."""
    import numpy as np

    from .planes import ransac_planes, sample_mesh
    cfg, G = loader.cfg, loader.G
    V, F = G.vertices.astype(np.float64), np.asarray(G.faces)
    area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]),
                                axis=1).sum()
    pts = sample_mesh(V, F, int(min(200000, max(20000, area * 2000))), seed=0)
    centres = np.array([loader.cams[v].center for v in loader.names])
    out = []
    for i, c in enumerate(ransac_planes(pts, distance=cfg.ransac_distance, seed=0,
                                        max_planes=cfg.max_planes, min_points=200)):
        pl = np.asarray(c["plane"])
        if np.median(centres @ pl[:3] + pl[3]) < 0:
            pl = -pl
        out.append({"name": f"detected_{i}", "plane": [float(x) for x in pl],
                    "polygon": c["polygon"].tolist(), "beta": None, "masks": {}})
    return out


def score_plane(loader: Loader, cand: dict) -> dict:
    """One candidate's evidence (multi-view warp errors, Eq. 3 fit, and the transmission warp
    where the surface warp fails unexplained) and verdict: the candidate with `score`, `views`,
    `kept`, `reason` and, when kept, `beta`, `material`, `source`. The loader's caches of this
    candidate are dropped afterwards (each is scored once)."""
    import numpy as np

    from .reflector_detect import decision, reflectance_cue, score_candidate
    cfg = loader.cfg
    cand = dict(cand)
    try:
        views = [loader.geom(v, cand, masked=True) for v in loader.names  # mask first (cheap)
                 if loader.mask(v, cand).sum() >= cfg.min_mask_pixels]
        score = score_candidate(views) if len(views) >= 2 else {"surface_error": None, "pairs": 0}
        score["mask_pixels"] = max((int(g.mask.sum()) for g in views), default=0)
        # the Eq. 3 fit (weak reflectors) only where the pair count lets it decide
        if len(views) >= 2 and cfg.detect_beta > 0 and score.get("pairs", 0) >= cfg.detect_min_pairs:
            cols = {g.name: loader.prior(g.name, dict(cand, beta=1.0), [cand], geom=g)
                    for g in views}
            score.update({f"fit_{k}": v for k, v in reflectance_cue(views, cols).items()})
        if (cfg.detect_explained and (score.get("surface_error") or 0) > cfg.detect_threshold
                and not (score.get("mirror_ratio") or np.inf) < cfg.mirror_ratio):
            # a failed surface warp that the mirror warp does not explain: does the scene
            # behind the plane (glass) explain it? (only here: one more ray cast per view)
            t = score_candidate([loader.transmitted(g, cand) for g in views])
            score["transmission_error"] = t["mirror_error"]
            score["transmission_ratio"] = t["mirror_ratio"]
    finally:
        loader.forget(cand["name"])
    px = max((v.camera.width * v.camera.height for v in views), default=0)  # working size
    min_fit = int(np.ceil(cfg.detect_min_fit * px))
    kept, reason = decision(score, cfg.detect_threshold, cfg.detect_min_pairs,
                            cfg.detect_beta or None, cfg.detect_corr,
                            cfg.mirror_ratio if cfg.detect_explained else None, min_fit)
    if len(views) < 2:
        reason = f"seen by {len(views)} view(s) with >= {cfg.min_mask_pixels} mask pixels, 2 needed"
    cand.update(score=score, views=len(views), kept=kept, reason=reason)
    if kept:
        if score.get("mirror_ratio") is not None and score["mirror_ratio"] < cfg.mirror_ratio:
            cand["beta"] = 1.0  # a mirror (§4.3.3 special case)
            cand["material"] = "mirror"
            cand["reason"] += "; a mirror"
        else:
            glass = (score.get("transmission_ratio") or np.inf) < cfg.mirror_ratio
            cand["material"] = "glass" if glass else "glossy"
            if (score.get("fit_beta") or 0) > 0:  # the fitted reflectance (Eq. 3)
                cand["beta"] = round(float(np.clip(score["fit_beta"], 0.01, 0.99)), 4)
        cand["source"] = "detected"
    return cand


def compute_planes(loader: Loader, score_all=None) -> dict:
    """User reflectors + planes of G detected by the multi-view cue (user ones win on overlap).
    `score_all(loader, candidates)` -> the scored candidates in order (`score_plane` of each;
    the `reflectors` stage maps it over worker processes); default: one after the other here.
    Each candidate is scored on its own, so the result does not depend on how they are mapped."""
    ws, cfg = loader.ws, loader.cfg
    user = []
    if cfg.use_user_reflectors and ws.exists(L.USER_REFLECTORS):
        for r in user_reflectors(ws, loader.scene_manifest):
            d = r.to_dict()
            d["source"] = "user"
            user.append(d)
    found, found_cands = found_reflectors(ws)
    user += found  # masked out of G like the user's: decomposed as given
    scored: list = []
    if detect_enabled(ws, cfg):
        cands = plane_candidates(loader)
        scored = (score_all(loader, cands) if score_all is not None
                  else [score_plane(loader, c) for c in cands])
    from .planes import same_plane
    merged = list(user)  # user planes win; among detections the best-supported piece wins
    for d in sorted((c for c in scored if c["kept"]), key=lambda d: -(d["score"].get("pairs") or 0)):
        same = next((u["name"] for u in merged if same_plane(d["plane"], u["plane"])), None)
        if same is None:
            merged.append(d)
        else:
            d["kept"], d["reason"] = False, f"{d['reason']}; same plane as {same}"
    keys = ("name", "plane", "score", "views", "kept", "reason")
    return {"format": "ibr_pipeline.reflectors/1", "reflectors": merged,
            "candidates": found_cands + [{k: c[k] for k in keys} for c in scored]}


# --- one view, one reflector -------------------------------------------------------------------
def decompose_reflector(loader: Loader, view: str, refl: dict, opts: DecomposeOptions | None = None) -> dict:
    """The two-layer decomposition of `view` for reflector `refl` (planes.json entry) with
    `opts` (default: the loader's cfg.decompose): neighbours, prior, one or two passes. Returns
    its report; R (the reflection component), pose, offsets and the ViewGeom unless discarded."""
    import numpy as np

    from .decompose import by_pose_distance, decompose, select_neighbours
    cfg = loader.cfg
    opts = opts or cfg.decompose
    mirror = refl.get("beta") == 1.0
    beta = float(refl.get("beta") or 1.0)
    ref = loader.geom(view, refl)

    def candidates(of, names):  # footprints built lazily, nearest first (select_neighbours)
        for o in by_pose_distance(loader.cams[of], [n for n in names if n != of], loader.cams):
            fp = loader.footprint(o, refl)
            if fp.mask.sum() >= cfg.min_mask_pixels:
                yield fp

    nbs_sel = select_neighbours(ref, candidates(view, loader.names), opts, presorted=True)
    nbs = [loader.geom(n, refl) for n, _ in nbs_sel]
    info = {"name": refl["name"], "beta": beta, "mirror": mirror, "mask_pixels": int(ref.mask.sum()),
            "neighbours": [{"view": n, "overlap": round(f, 3)} for n, f in nbs_sel]}
    if not mirror and len(nbs) < opts.min_neighbours:
        info["discarded"] = f"{len(nbs)} neighbour(s) with > {opts.min_overlap:.0%} overlap"
        return info
    prior = None
    if opts.lambda_scene > 0 and not mirror:
        prior = loader.prior(view, refl, loader.reflectors)
    res = decompose(ref, nbs, opts, beta=beta, mirror=mirror, R_prior=prior)
    history = [dict(h, **{"pass": 1}) for h in res["history"]]
    if opts.multiview and not mirror and nbs:  # §4.3.3: aggregate the neighbours' first pass
        loader.first[(view, refl["name"])] = res["R"]
        prev = {}
        for nb in nbs:
            nn = select_neighbours(nb, candidates(nb.name, loader.names), opts, presorted=True)
            nbn = [loader.geom(n, refl) for n, _ in nn]
            key = (nb.name, refl["name"])
            if key in loader.first:  # first pass already computed by this worker
                prev[nb.name] = loader.first[key]
            elif nbn:
                nbp = loader.prior(nb.name, refl, loader.reflectors) if opts.lambda_scene > 0 else None
                prev[nb.name] = loader.first[key] = decompose(nb, nbn, opts, beta=beta,
                                                              R_prior=nbp)["R"]
        res = decompose(ref, nbs, opts, beta=beta, aggregate_from=prev, R_init=res["R"],
                        R_prior=prior)
        history += [dict(h, **{"pass": 2}) for h in res["history"]]
    info.update(R=res["R"], pose=res["pose"], history=history, mask=ref.mask, geom=ref,
                m1_offset=res.get("m1_offset"), m0_offset=res.get("m0_offset"))
    for key in ("m0_offset", "m1_offset"):  # relative depth offsets of M0's / M1's vertices
        if info[key] is not None:
            o = np.abs(info[key][ref.mask])
            info[key + "s"] = {"mean_abs": round(float(o.mean()), 5) if o.size else 0.0,
                               "max_abs": round(float(o.max()), 5) if o.size else 0.0}
    return info


def simplify_m1(v, f, wc, cfg: "ReflectionConfig"):
    """M1 through view_mesh's adaptive quadric simplification (§4.2.3): the reference is M1's own
    grid mesh rendered into the view, so its cut edges (mesh borders) and depth survive."""
    import numpy as np

    from .grid_mesh import simplify_adaptive
    budget = max(200, int(round(cfg.m1_max_vertices_640x480 * wc.width * wc.height / (640 * 480))))
    res = simplify_adaptive(v.astype(np.float64), f, wc, None, budget, 200, cfg.m1_tol_score)
    return (res.vertices.astype(np.float32), res.faces.astype(np.int32),
            {"grid_faces": res.grid_faces, "faces": int(len(res.faces))})


