"""Triangle-soup builders for the synthetic rooms (world frame: right-handed, +z up, metres).

Geometry is kept as a soup: every triangle owns its three corners and three corner normals, so
flat faces (boxes, walls) stay flat while spheres get smooth normals interpolated with the
barycentric coordinates of the hit (`smooth_normals`).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .materials import Material


@dataclass
class MeshBuilder:
    """Accumulates triangles with per-corner normals and a material index per face."""

    materials: list[Material] = field(default_factory=list)
    _tris: list[np.ndarray] = field(default_factory=list)
    _norms: list[np.ndarray] = field(default_factory=list)
    _mats: list[np.ndarray] = field(default_factory=list)
    _mat_index: dict[str, int] = field(default_factory=dict)

    def material(self, mat: Material) -> int:
        if mat.name not in self._mat_index:
            self._mat_index[mat.name] = len(self.materials)
            self.materials.append(mat)
        return self._mat_index[mat.name]

    def add(self, tris: np.ndarray, normals: np.ndarray, mat: Material) -> None:
        tris = np.asarray(tris, dtype=np.float64).reshape(-1, 3, 3)
        normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3, 3)
        if tris.shape != normals.shape:
            raise ValueError(f"triangles {tris.shape} and corner normals {normals.shape} differ")
        self._tris.append(tris)
        self._norms.append(normals)
        self._mats.append(np.full(len(tris), self.material(mat), dtype=np.int32))

    def quad(self, p0, p1, p2, p3, normal, mat: Material) -> None:
        """A planar quad p0-p1-p2-p3 (in order around the edge) facing `normal`."""
        p = np.asarray([p0, p1, p2, p3], dtype=np.float64)
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        tris = np.stack([p[[0, 1, 2]], p[[0, 2, 3]]])
        self.add(tris, np.broadcast_to(n, tris.shape), mat)

    def box(self, lo, hi, mat: Material, top: Material | None = None, inward: bool = False) -> None:
        """Axis-aligned box [lo, hi]; `top` overrides the +z face; `inward` flips normals (rooms)."""
        (x0, y0, z0), (x1, y1, z1) = lo, hi
        s = -1.0 if inward else 1.0
        faces = [  # corners, outward normal
            ([(x0, y0, z0), (x0, y1, z0), (x0, y1, z1), (x0, y0, z1)], (-1, 0, 0)),
            ([(x1, y0, z0), (x1, y0, z1), (x1, y1, z1), (x1, y1, z0)], (1, 0, 0)),
            ([(x0, y0, z0), (x0, y0, z1), (x1, y0, z1), (x1, y0, z0)], (0, -1, 0)),
            ([(x0, y1, z0), (x1, y1, z0), (x1, y1, z1), (x0, y1, z1)], (0, 1, 0)),
            ([(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0)], (0, 0, -1)),
            ([(x0, y0, z1), (x0, y1, z1), (x1, y1, z1), (x1, y0, z1)], (0, 0, 1)),
        ]
        for corners, n in faces:
            m = top if (top is not None and n == (0, 0, 1)) else mat
            self.quad(*corners, normal=tuple(s * c for c in n), mat=m)

    def sphere(self, center, radius: float, mat: Material, rings: int = 48, segments: int = 96) -> None:
        """UV sphere with exact per-corner normals (smooth shading by barycentric interpolation)."""
        c = np.asarray(center, dtype=np.float64)
        th = np.linspace(0, np.pi, rings + 1)
        ph = np.linspace(0, 2 * np.pi, segments + 1)
        T, P = np.meshgrid(th, ph, indexing="ij")
        dirs = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1)
        a, b = dirs[:-1, :-1], dirs[1:, :-1]
        cc, d = dirs[1:, 1:], dirs[:-1, 1:]
        t1 = np.stack([a, b, cc], axis=2).reshape(-1, 3, 3)
        t2 = np.stack([a, cc, d], axis=2).reshape(-1, 3, 3)
        n = np.concatenate([t1, t2])
        area = np.linalg.norm(np.cross(n[:, 1] - n[:, 0], n[:, 2] - n[:, 0]), axis=1)
        n = n[area > 1e-12]  # drop degenerate triangles at the poles
        self.add(c + radius * n, n, mat)

    def build(self) -> "TriangleSoup":
        return TriangleSoup(np.concatenate(self._tris), np.concatenate(self._norms),
                            np.concatenate(self._mats), tuple(self.materials))


@dataclass(frozen=True, eq=False)
class TriangleSoup:
    tris: np.ndarray            # (F, 3, 3) corner positions
    corner_normals: np.ndarray  # (F, 3, 3) unit normals at the corners
    face_material: np.ndarray   # (F,) index into materials
    materials: tuple[Material, ...]

    @property
    def face_normals(self) -> np.ndarray:
        """(F, 3) geometric unit normals, oriented like the corner normals."""
        n = np.cross(self.tris[:, 1] - self.tris[:, 0], self.tris[:, 2] - self.tris[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        flip = np.sum(n * self.corner_normals.mean(axis=1), axis=1) < 0
        n[flip] *= -1
        return n

    def smooth_normals(self, prim: np.ndarray, bary_uv: np.ndarray) -> np.ndarray:
        """Normals at hits interpolated from corner normals: (1-u-v) n0 + u n1 + v n2."""
        n = self.corner_normals[prim, 0].copy()  # flat faces: all corners equal
        curved = self.curved_faces[prim]
        if curved.any():
            u = bary_uv[curved, 0:1].astype(np.float64)
            v = bary_uv[curved, 1:2].astype(np.float64)
            cn = self.corner_normals[prim[curved]]
            m = (1 - u - v) * cn[:, 0] + u * cn[:, 1] + v * cn[:, 2]
            n[curved] = m / np.maximum(np.linalg.norm(m, axis=1, keepdims=True), 1e-12)
        return n

    @property
    def curved_faces(self) -> np.ndarray:
        """(F,) bool: faces whose corner normals differ (smooth shading needed)."""
        cached = self.__dict__.get("_curved")
        if cached is None:
            cn = self.corner_normals
            cached = np.abs(cn - cn[:, :1]).max(axis=(1, 2)) > 1e-9
            object.__setattr__(self, "_curved", cached)
        return cached

    def subset(self, keep: np.ndarray) -> "TriangleSoup":
        return TriangleSoup(self.tris[keep], self.corner_normals[keep], self.face_material[keep],
                            self.materials)
