"""Materials and the optics of the Whitted tracer: reflection, refraction, Fresnel.

Material kinds and how the tracer treats a hit (radiance L along the incoming ray):
  diffuse     L = albedo * E                                  (E: irradiance term, see tracer)
  glossy      L = (1 - kr) * albedo * E + kr * L_refl          (polished coat, constant kr)
  mirror      L = kr * L_refl                                  (kr = 1: full reflection)
  glass_pane  L = F_pane * L_refl + (1 - F_pane) * tint * L_trans   (thin non-absorbing sheet)
  dielectric  L = F * L_refl + (1 - F) * tint * L_refr          (solid with index `ior`)
F is the exact unpolarised Fresnel reflectance; F_pane sums the two interfaces of a thin sheet
(incoherent multiple reflections, no ray offset).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.normals import dot3
from .textures import Texture

KINDS = ("diffuse", "glossy", "mirror", "glass_pane", "dielectric")
# per-pixel Fresnel model codes of the ray tree (how a compositor weights the R and T nodes)
FRESNEL_NONE, FRESNEL_DIELECTRIC, FRESNEL_PANE = 0, 1, 2


@dataclass(frozen=True)
class Material:
    name: str
    kind: str = "diffuse"
    texture: Texture | None = None
    kr: float = 0.0          # view-independent reflectance (glossy coat, mirror); 1 for dielectrics
    ior: float = 1.0         # index of refraction (glass_pane, dielectric)
    tint: tuple[float, float, float] = (1.0, 1.0, 1.0)  # transmission filter colour

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"material {self.name}: unknown kind {self.kind!r}")
        if self.kind in ("diffuse", "glossy") and self.texture is None:
            raise ValueError(f"material {self.name}: a {self.kind} material needs a texture")

    @property
    def opaque(self) -> bool:
        """Does it cast shadows (block light)? Transparent materials do not."""
        return self.kind in ("diffuse", "glossy", "mirror")

    @property
    def fresnel_code(self) -> int:
        return {"glass_pane": FRESNEL_PANE, "dielectric": FRESNEL_DIELECTRIC}.get(self.kind, FRESNEL_NONE)


def reflecting_indices(materials: list[dict]) -> list[int]:
    """Indices of the materials that reflect, from a GT scene.json's "materials" list: a coat or
    mirror (kr > 0) and glass, which reflects by Fresnel with kr 0 (the "inside reflectors"
    masks of evaluation)."""
    return [m["index"] for m in materials
            if m.get("kr", 0) > 0 or m.get("kind") in ("glass_pane", "dielectric")]


def _check_dn(d: np.ndarray, n: np.ndarray) -> None:
    if d.shape != n.shape or d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions and normals must both be (N, 3), got {d.shape}, {n.shape}")


def reflect(d: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Mirror the directions (N, 3) about the unit normals (N, 3)."""
    _check_dn(d, n)
    return d - 2.0 * dot3(d, n)[:, None] * n


def refract(d: np.ndarray, n: np.ndarray, eta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Snell refraction of unit `d` at unit `n` facing against d, eta = n_from / n_to.

    Returns (directions (N, 3), total-internal-reflection mask (N,)); TIR rows are zero.
    """
    _check_dn(d, n)
    eta = np.broadcast_to(np.asarray(eta, dtype=np.float64), (len(d),))
    cos_i = -dot3(d, n)
    k = 1.0 - eta ** 2 * (1.0 - cos_i ** 2)
    tir = k < 0
    out = eta[:, None] * d + (eta * cos_i - np.sqrt(np.maximum(k, 0)))[:, None] * n
    out[tir] = 0
    norm = np.sqrt(dot3(out, out))[:, None]
    return np.where(norm > 0, out / np.maximum(norm, 1e-12), 0), tir


def _rs_rp(cos_i: np.ndarray, eta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Squared amplitude reflectances (s, p) and TIR mask; eta = n_from / n_to."""
    cos_i = np.clip(np.abs(cos_i), 0.0, 1.0)
    sin_t2 = eta ** 2 * (1.0 - cos_i ** 2)
    tir = sin_t2 >= 1.0
    cos_t = np.sqrt(np.maximum(1.0 - sin_t2, 0.0))
    rs = (eta * cos_i - cos_t) / np.maximum(eta * cos_i + cos_t, 1e-12)
    rp = (eta * cos_t - cos_i) / np.maximum(eta * cos_t + cos_i, 1e-12)
    return np.where(tir, 1.0, rs ** 2), np.where(tir, 1.0, rp ** 2), tir


def fresnel_dielectric(cos_i: np.ndarray, eta: np.ndarray) -> np.ndarray:
    """Unpolarised Fresnel reflectance of one interface; eta = n_from / n_to (1/ior entering)."""
    Rs, Rp, _ = _rs_rp(np.asarray(cos_i, dtype=np.float64), np.asarray(eta, dtype=np.float64))
    return 0.5 * (Rs + Rp)


def fresnel_pane(cos_i: np.ndarray, ior: np.ndarray) -> np.ndarray:
    """Reflectance of a thin non-absorbing sheet (two interfaces, incoherent): 2R/(1+R) per
    polarisation, averaged."""
    Rs, Rp, _ = _rs_rp(np.asarray(cos_i, dtype=np.float64), 1.0 / np.asarray(ior, dtype=np.float64))
    return 0.5 * (2 * Rs / (1 + Rs) + 2 * Rp / (1 + Rp))


def fresnel_weight(code: np.ndarray, cos_i: np.ndarray, ior: np.ndarray) -> np.ndarray:
    """View-dependent reflection weight per pixel for the ray-tree codes (1 where FRESNEL_NONE).

    cos_i: cosine between the viewing ray and the surface normal; ior: the material's index
    (the viewing ray arrives from air, n = 1).
    """
    code = np.asarray(code)
    ior = np.where(np.asarray(ior) > 0, ior, 1.0)
    return np.where(code == FRESNEL_DIELECTRIC, fresnel_dielectric(cos_i, 1.0 / ior),
                    np.where(code == FRESNEL_PANE, fresnel_pane(cos_i, ior), 1.0))
