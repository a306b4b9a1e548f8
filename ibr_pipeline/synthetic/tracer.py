"""Whitted-style ray tracer over the world's triangle soup (open3d RaycastingScene), vectorised.

Rays are processed as a wavefront: every bounce casts all live rays at once, shades their hits
(diffuse: albedo times a clamped irradiance term from point lights with shadow rays, plus
ambient), and spawns reflection / refraction rays with their weights (see materials.py).

Every ray carries a *tag* saying which primary-level branch of the ray tree it feeds
(Lochmann et al. 2014 §3.2): D = the local (diffuse) radiance at the primary hit, R = radiance
arriving along the primary reflection, T = along the primary refraction/transmission. The
primary-level view-independent factors (kr, tint) and the view-dependent Fresnel weight are
*not* applied to R and T, so the same pass yields both
  Xu et al. Eq. 3 layers:  I0 = D + (1 - F) T,  I1 = R,  beta = kr F,  I = I0 + beta I1
  and the ray-tree nodes:  D,  kr R,  tint T,  composited with Fresnel F.
"""
from __future__ import annotations


import numpy as np

from ..geometry import raycast
from ..geometry.normals import dot3
from ..scene import Camera
from .materials import (FRESNEL_NONE, fresnel_dielectric,
                        fresnel_pane, reflect, refract)
from .scenes import World

EPS = 2e-4        # ray origin offset (m)
MIN_WEIGHT = 2e-3  # rays whose weight drops below this are not traced further
MAX_RADIANCE = 0.95  # diffuse radiance is clamped here, so every composite stays <= 1
TAG_D, TAG_R, TAG_T = 0, 1, 2


class Tracer:
    """Holds the world's acceleration structures and per-material lookup tables."""

    def __init__(self, world: World):
        self.world = world
        soup = world.soup
        self.soup = soup
        self.face_normals = soup.face_normals
        verts = soup.tris.reshape(-1, 3)
        tri_idx = np.arange(len(verts)).reshape(-1, 3)
        self.scene = raycast.build_scene(verts, tri_idx)
        opaque = np.array([m.opaque for m in soup.materials])[soup.face_material]
        occ = soup.subset(opaque)
        self.shadow_scene = raycast.build_scene(occ.tris.reshape(-1, 3),
                                                np.arange(3 * len(occ.tris)).reshape(-1, 3))
        mats = soup.materials
        self.kind = np.array([["diffuse", "glossy", "mirror", "glass_pane", "dielectric"].index(m.kind)
                              for m in mats])
        self.kr = np.array([m.kr if m.kind in ("glossy", "mirror") else
                            (1.0 if m.kind in ("glass_pane", "dielectric") else 0.0) for m in mats])
        self.ior = np.array([m.ior if m.kind in ("glass_pane", "dielectric") else 0.0 for m in mats])
        self.tint = np.array([m.tint for m in mats], dtype=np.float64)
        self.fcode = np.array([m.fresnel_code for m in mats])

    # --- shading ----------------------------------------------------------------------------
    def albedo(self, mat: np.ndarray, p: np.ndarray, nf: np.ndarray) -> np.ndarray:
        """(N, 3) albedo from each material's texture on planar-projected coordinates."""
        out = np.zeros((len(p), 3))
        a = np.abs(nf)  # the dominant axis (argmax written out: numpy's short-axis reduction is slow)
        ax = np.where((a[:, 0] >= a[:, 1]) & (a[:, 0] >= a[:, 2]), 0, np.where(a[:, 1] >= a[:, 2], 1, 2))
        uv = np.where((ax == 0)[:, None], p[:, [1, 2]], np.where((ax == 1)[:, None], p[:, [0, 2]],
                                                                  p[:, [0, 1]]))
        for m in np.unique(mat):
            tex = self.soup.materials[m].texture
            if tex is not None:
                sel = mat == m
                out[sel] = tex.albedo(uv[sel])
        return out

    def irradiance(self, p: np.ndarray, ns: np.ndarray, nf: np.ndarray) -> np.ndarray:
        """(N,) view-independent lighting term: ambient + sum of visible point lights."""
        w = self.world
        e = np.full(len(p), w.ambient)
        origin = p + EPS * 5 * nf
        for L, power in zip(w.lights, w.light_power):
            to = L[None] - p
            d2 = dot3(to, to)
            cos = dot3(ns, to) / np.sqrt(d2)
            lit = (cos > 0) & (dot3(nf, to) > 0)
            if not lit.any():
                continue
            idx = np.nonzero(lit)[0]
            vis = ~raycast.occluded(self.shadow_scene, origin[idx], np.broadcast_to(L, (len(idx), 3)))
            e[idx[vis]] += power * cos[idx[vis]] / (d2[idx[vis]] + 0.25)
        return e

    def local_radiance(self, mat, p, ns, nf) -> np.ndarray:
        """(N, 3) diffuse radiance leaving the hits (0 for mirrors and transparent materials)."""
        out = np.zeros((len(p), 3))
        k = self.kind[mat]
        sel = k <= 1  # diffuse or glossy
        if sel.any():
            a = self.albedo(mat[sel], p[sel], nf[sel])
            e = self.irradiance(p[sel], ns[sel], nf[sel])
            rad = np.minimum(a * e[:, None], MAX_RADIANCE)
            out[sel] = rad * (1.0 - self.kr[mat[sel]])[:, None]
        return out

    # --- the wavefront ------------------------------------------------------------------------
    def trace(self, camera: Camera) -> dict[str, np.ndarray]:
        """Render one camera. Returns (H, W, ...) float arrays: see module docstring.

        Keys: D, R, T (radiance per tag), I0, I1, beta, image (= I0 + beta I1), depth (z-depth),
        range, normal (smooth, facing the camera), material, kr, ior, fresnel_code,
        R_range, T_range (distance from the primary hit to the next hit along R / T; 0 if none).
        """
        H, W = camera.height, camera.width
        n = H * W
        o, d = raycast.camera_rays(camera)
        self._primary_dirs = d
        acc = np.zeros((3, n, 3))
        w = np.ones((n, 3))
        pix = np.arange(n)
        tag = np.full(n, TAG_D)
        out = {"range": np.full(n, np.inf), "normal": np.zeros((n, 3)), "material": np.full(n, -1),
               "F": np.zeros(n), "R_range": np.zeros(n), "T_range": np.zeros(n)}
        for depth in range(self.world.max_depth + 1):
            if len(o) == 0:
                break
            hit = raycast.cast(self.scene, o, d)
            ok = hit["primitive_ids"] >= 0
            if depth == 1:  # ranges of the primary children (ray-tree Z of the R and T nodes)
                for tg, key in ((TAG_R, "R_range"), (TAG_T, "T_range")):
                    s = tag == tg
                    out[key][pix[s]] = np.where(ok[s], hit["t_hit"][s], 0.0)
            o, d, w, pix, tag = o[ok], d[ok], w[ok], pix[ok], tag[ok]
            t, prim, buv = hit["t_hit"][ok], hit["primitive_ids"][ok], hit["primitive_uvs"][ok]
            p = o + t[:, None] * d
            mat = self.soup.face_material[prim]
            nf = self.face_normals[prim]
            ns = self.soup.smooth_normals(prim, buv)
            entering = dot3(d, nf) < 0
            sgn = np.where(entering, 1.0, -1.0)[:, None]
            nf, ns = nf * sgn, ns * sgn  # both now face the incoming ray
            ns = np.where((dot3(ns, d) < 0)[:, None], ns, nf)
            cos_i = -dot3(d, ns)
            k, kr, ior = self.kind[mat], self.kr[mat], self.ior[mat]
            local = self.local_radiance(mat, p, ns, nf)
            flat = tag * n + pix  # scatter-add (a pixel may have several rays in flight)
            contrib = w * local
            for c in range(3):
                acc[:, :, c] += np.bincount(flat, contrib[:, c], minlength=3 * n).reshape(3, n)
            # Fresnel weights for this bounce
            F = np.ones(len(p))
            pane = k == 3
            diel = k == 4
            F[pane] = fresnel_pane(cos_i[pane], ior[pane])
            eta = np.where(entering, 1.0 / np.maximum(ior, 1e-9), ior)
            F[diel] = fresnel_dielectric(cos_i[diel], eta[diel])
            if depth == 0:
                out["range"][pix] = t
                out["normal"][pix] = ns
                out["material"][pix] = mat
                out["F"][pix] = np.where(k >= 3, F, 1.0)
            # children: reflection (mirror, glossy, pane, dielectric) and transmission
            refl = k >= 1
            r_dir = reflect(d[refl], ns[refl])
            r_w = w[refl] * (np.ones((refl.sum(), 1)) if depth == 0 else
                             (kr[refl] * F[refl])[:, None])
            r_tag = np.where(depth == 0, TAG_R, tag[refl])
            r_o = p[refl] + EPS * nf[refl]
            tr = k >= 3
            t_dir, tir = refract(d[tr], ns[tr], np.where(k[tr] == 3, 1.0, eta[tr]))
            t_dir = np.where((k[tr] == 3)[:, None], d[tr], t_dir)
            keep = ~tir | (k[tr] == 3)
            t_fac = self.tint[mat[tr]] * (1.0 if depth == 0 else (1.0 - F[tr])[:, None])
            t_w = (w[tr] * t_fac)[keep]
            t_tag = np.where(depth == 0, TAG_T, tag[tr])[keep]
            t_o = (p[tr] - EPS * nf[tr])[keep]
            o = np.concatenate([r_o, t_o])
            d = np.concatenate([r_dir, t_dir[keep]])
            w = np.concatenate([r_w, t_w])
            pix = np.concatenate([pix[refl], pix[tr][keep]])
            tag = np.concatenate([np.broadcast_to(r_tag, (len(r_o),)), t_tag])
            # weight of a primary child in the final image (for pruning only)
            eff = np.maximum(np.maximum(w[:, 0], w[:, 1]), w[:, 2]) if depth > 0 else np.ones(len(w))
            live = eff > MIN_WEIGHT
            o, d, w, pix, tag = o[live], d[live], w[live], pix[live], tag[live]
        return self._finish(camera, acc, out)

    def _finish(self, camera: Camera, acc: np.ndarray, out: dict) -> dict[str, np.ndarray]:
        H, W = camera.height, camera.width
        mat = out["material"]
        valid = mat >= 0
        safe = np.where(valid, mat, 0)
        k = np.where(valid, self.kind[safe], 0)
        kr = np.where(valid & (k >= 1), self.kr[safe], 0.0)
        F = np.where(k >= 3, out["F"], 1.0)
        D, R, T = acc
        I0 = D + ((1.0 - F) * (k >= 3))[:, None] * T
        beta = np.where(k >= 1, kr * F, 0.0)
        d = self._primary_dirs
        rng = out["range"]
        depth = np.where(np.isfinite(rng), rng * (d @ camera.viewing_direction), 0.0)
        res = {
            "D": D, "R": R, "T": T, "I0": I0, "I1": R.copy(), "beta": beta,
            "image": I0 + beta[:, None] * R, "depth": depth, "range": np.where(valid, rng, 0.0),
            "normal": out["normal"], "material": mat, "kind": np.where(valid, k, -1), "kr": kr,
            "F": F, "ior": np.where(valid, self.ior[safe], 0.0),
            "fresnel_code": np.where(valid, self.fcode[safe], FRESNEL_NONE),
            "tint": np.where((k >= 3)[:, None], self.tint[safe], 0.0),
            "R_range": out["R_range"], "T_range": out["T_range"],
        }
        return {key: v.reshape((H, W) + v.shape[1:]) for key, v in res.items()}

    # --- the RGB-D sensor's view: path length along the dominant light path -----------------
    def sensor_range(self, camera: Camera, max_bounces: int = 3) -> dict[str, np.ndarray]:
        """Time-of-flight range per pixel: a mirror returns the length of the reflected path (the
        depth of what it reflects), glass the path through it; refractive solids give no return.

        Returns (H, W) arrays: `range` (0 = no return), `cos` (incidence cosine at the last
        surface, for grazing-angle dropouts) and `depth` (z-depth of the virtual point).
        """
        n = camera.width * camera.height
        o, d0 = raycast.camera_rays(camera)
        d = d0.copy()
        total = np.zeros(n)
        result = np.zeros(n)
        cosv = np.zeros(n)
        idx = np.arange(n)
        for _ in range(max_bounces + 1):
            hit = raycast.cast(self.scene, o, d)
            ok = hit["primitive_ids"] >= 0
            idx, o, d, t = idx[ok], o[ok], d[ok], hit["t_hit"][ok]
            prim = hit["primitive_ids"][ok]
            total[idx] += t
            mat = self.soup.face_material[prim]
            nf = self.face_normals[prim]
            k = self.kind[mat]
            cos = np.abs(dot3(d, nf))
            stop = k <= 1
            result[idx[stop]] = total[idx[stop]]
            cosv[idx[stop]] = cos[stop]
            go = (k == 2) | (k == 3)  # mirrors reflect, panes transmit (a ToF sees through glass)
            p = o + t[:, None] * d
            nfs = nf * np.where(dot3(d, nf) < 0, 1.0, -1.0)[:, None]
            newd = np.where((k == 2)[:, None], reflect(d, nfs), d)
            off = np.where((k == 2)[:, None], nfs, -nfs) * EPS
            idx, o, d = idx[go], (p + off)[go], newd[go]
            if len(idx) == 0:
                break
        depth = result * (d0 @ camera.viewing_direction)
        shape = (camera.height, camera.width)
        return {"range": result.reshape(shape), "cos": cosv.reshape(shape),
                "depth": depth.reshape(shape)}
