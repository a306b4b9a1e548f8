"""Triangle meshes as PLY: the one reader/writer every stage uses.

Our own files are binary little-endian PLY with float32 `x y z`, optional float32 `nx ny nz`,
optional uchar `red green blue`, optional float32 vertex `quality`, and faces as
`list uchar int vertex_indices` with an optional int `material` per face (the synthetic GT mesh).
Reading is a numpy structured-array parse (fast, no open3d import); files in other PLY flavours
(ASCII, other property types) are read through open3d. Writes are atomic (temporary name + rename).
Positions are in world space, metres (scene.py conventions).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..workspace import atomic_path

_TYPES = {"float": "<f4", "float32": "<f4", "double": "<f8", "float64": "<f8", "uchar": "u1",
          "uint8": "u1", "char": "i1", "int8": "i1", "int": "<i4", "int32": "<i4", "uint": "<u4",
          "uint32": "<u4", "short": "<i2", "int16": "<i2", "ushort": "<u2", "uint16": "<u2"}


@dataclass
class Mesh:
    """vertices (V,3) float32; faces (F,3) int32; optional per-vertex normals (V,3) float32,
    colors (V,3) uint8, quality (V,) float32; optional per-face material (F,) int32."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    quality: np.ndarray | None = None
    material: np.ndarray | None = None
    extra: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.vertices = np.ascontiguousarray(self.vertices, dtype=np.float32).reshape(-1, 3)
        self.faces = np.ascontiguousarray(self.faces, dtype=np.int32).reshape(-1, 3)
        n = len(self.vertices)
        for name, width, dt in (("normals", 3, np.float32), ("colors", 3, np.uint8),
                                ("quality", 1, np.float32)):
            a = getattr(self, name)
            if a is not None:
                a = np.ascontiguousarray(a, dtype=dt)
                if a.shape[0] != n or (width > 1 and a.shape[1:] != (width,)):
                    raise ValueError(f"Mesh.{name}: shape {a.shape} for {n} vertices")
                setattr(self, name, a)
        if self.material is not None:
            self.material = np.ascontiguousarray(self.material, dtype=np.int32).reshape(-1)
            if len(self.material) != len(self.faces):
                raise ValueError("Mesh.material: one entry per face")
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= n):
            raise ValueError("Mesh.faces: vertex index out of range")

    @property
    def triangles(self) -> np.ndarray:
        """(F, 3, 3) corner positions."""
        return self.vertices[self.faces]


# --- canonical order -------------------------------------------------------------------------------
def canonical_order(vertices: np.ndarray, faces: np.ndarray, attributes: np.ndarray | None = None,
                    face_attributes: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A vertex and face order that depends only on what the mesh is, not on how it was built.

    Meshes from parallel algorithms (open3d's TSDF VoxelBlockGrid and its marching cubes, which
    emit vertices in hash-map order that depends on thread timing) describe the same surface with
    a different vertex and face order on every run; written as is, identical inputs give
    different bytes. This order is a pure function of the geometry:

    * vertices sorted lexicographically by position (x, then y, then z, compared as numbers), then
      by the optional per-vertex `attributes` columns (e.g. colours), then by the raw bits of both
      (so -0.0 and 0.0, equal as numbers, still sort the same way every time);
      vertices identical in all of these are indistinguishable, and are merged into one (no order
      between them could be canonical); faces that merging collapses to fewer than 3 distinct
      vertices are dropped;
    * every face rotated cyclically so that its smallest vertex index comes first (the winding,
      hence the orientation, is kept);
    * faces sorted lexicographically by their three indices, then by the optional per-face
      `face_attributes` columns (e.g. materials); faces equal in all of these are identical rows
      of the file, so their order does not matter.

    Positions are compared exactly, not quantised: the values the parallel code computes are
    deterministic, only their order is not, and rounding would only move the sort's ties to the
    rounding boundaries. Idempotent: a mesh in canonical order maps to itself.

    vertices (V, 3) finite floats (compared as float32, the precision the PLY files store);
    faces (F, 3) integer indices into them; attributes (V,) or (V, k) and face_attributes (F,) or
    (F, k) finite numbers, or None.
    Returns (vertex_order (V',) int64: new vertex i is old vertex vertex_order[i]; faces (F', 3)
    int32 in the new indices; face_order (F',) int64: new face j is old face face_order[j]).
    Raises ValueError on bad shapes, non-finite positions or out-of-range indices."""
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"canonical_order: vertices must be (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"canonical_order: faces must be (F, 3), got {f.shape}")
    if f.size and not np.issubdtype(f.dtype, np.integer):
        raise ValueError(f"canonical_order: faces must be integer indices, got {f.dtype}")
    v32 = np.ascontiguousarray(v, dtype=np.float32)
    if not np.all(np.isfinite(v32)):
        raise ValueError("canonical_order: vertices must be finite")
    n = len(v32)
    f = f.astype(np.int64, copy=False)
    if f.size and (f.min() < 0 or f.max() >= n):
        raise ValueError(f"canonical_order: face index out of range for {n} vertices")
    a = _columns(attributes, n, "attributes", "vertices")
    fa = _columns(face_attributes, len(f), "face_attributes", "faces")
    # the raw bits of position and attributes: a total order, and what "identical" means
    ident = np.concatenate([v32.view(np.uint32).astype(np.uint64), a.view(np.uint64)], axis=1)
    # np.lexsort sorts by its last key first: x, y, z, then (only needed where two positions are
    # equal as numbers, which marching cubes hardly ever gives) the attributes and the raw bits
    order = np.lexsort([v32[:, i] for i in (2, 1, 0)]) if n else np.zeros(0, np.int64)
    if n > 1:
        tie = np.all(v32[order[1:]] == v32[order[:-1]], axis=1)
        if tie.any():
            order = _break_ties(order, tie, a, ident)
    ident = ident[order]   # identical vertices are adjacent after the sort: merge them
    new_group = np.ones(n, bool)
    if n > 1:
        new_group[1:] = np.any(ident[1:] != ident[:-1], axis=1)
    group = np.cumsum(new_group) - 1                   # new index of each sorted vertex
    remap = np.empty(n, np.int64)
    remap[order] = group
    vertex_order = order[new_group].astype(np.int64)
    nf = remap[f] if f.size else np.zeros((0, 3), np.int64)
    keep = (nf[:, 0] != nf[:, 1]) & (nf[:, 1] != nf[:, 2]) & (nf[:, 0] != nf[:, 2])
    face_idx = np.nonzero(keep)[0]
    nf, fa = nf[keep], fa[keep]
    r = np.argmin(nf, axis=1)                           # rotate: smallest index first, same winding
    rows = np.arange(len(nf))
    nf = np.stack([nf[rows, (r + k) % 3] for k in range(3)], axis=1) if len(nf) else nf
    if fa.shape[1] == 0 and len(vertex_order) < 2**21:   # one int64 key: a single (faster) sort
        forder = np.argsort((nf[:, 0] << 42) | (nf[:, 1] << 21) | nf[:, 2], kind="stable")
    else:
        fkeys = [fa[:, j] for j in range(fa.shape[1] - 1, -1, -1)] + [nf[:, 2], nf[:, 1], nf[:, 0]]
        forder = np.lexsort(fkeys) if len(nf) else np.zeros(0, np.int64)
    return vertex_order, nf[forder].astype(np.int32), face_idx[forder].astype(np.int64)


def _break_ties(order: np.ndarray, tie: np.ndarray, a: np.ndarray, ident: np.ndarray) -> np.ndarray:
    """`order` (a stable sort by position) with each run of equal positions (`tie[i]`: sorted
    vertices i and i+1 are equal as numbers) sorted by the attributes `a`, then the raw bits
    `ident`: the order one lexsort by all of these keys gives, at the cost of the runs alone (a
    fused mesh has a handful of them among millions of vertices)."""
    n = len(order)
    in_run = np.zeros(n, bool)
    in_run[1:] |= tie
    in_run[:-1] |= tie
    pos = np.nonzero(in_run)[0]
    run = np.concatenate([[0], np.cumsum(~tie)])[pos]   # runs stay in position order
    idx = order[pos]
    keys = ([ident[idx, j] for j in range(ident.shape[1] - 1, -1, -1)]
            + [a[idx, j] for j in range(a.shape[1] - 1, -1, -1)] + [run])
    out = order.copy()
    out[pos] = idx[np.lexsort(keys)]   # stable: full ties keep the position sort's (input) order
    return out


def _columns(values, n: int, name: str, what: str) -> np.ndarray:
    """(n, k) float64 view of optional per-vertex / per-face tie-break values."""
    if values is None:
        return np.zeros((n, 0))
    a = np.asarray(values)
    a = a.reshape(-1, 1) if a.ndim == 1 else a
    if a.ndim != 2 or a.shape[0] != n:
        raise ValueError(f"canonical_order: {name} must be ({what[0].upper()},) or "
                         f"({what[0].upper()}, k) for {n} {what}, got {np.shape(values)}")
    if not (np.issubdtype(a.dtype, np.number) or a.dtype == bool):
        raise ValueError(f"canonical_order: {name} must be numbers, got {a.dtype}")
    a = a.astype(np.float64)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"canonical_order: {name} must be finite")
    return a


def canonical_mesh(mesh: Mesh) -> Mesh:
    """`mesh` in `canonical_order`: colours, quality and normals break ties between vertices at
    the same position, materials between faces with the same corners; normals, colours, quality and
    materials follow their vertex or face."""
    cols = [c for c in (mesh.colors, None if mesh.quality is None else mesh.quality[:, None],
                        mesh.normals) if c is not None]
    attrs = np.concatenate([np.asarray(c, np.float64) for c in cols], axis=1) if cols else None
    vo, faces, fo = canonical_order(mesh.vertices, mesh.faces, attrs, mesh.material)
    pick = lambda a, idx: None if a is None else a[idx]  # noqa: E731
    return Mesh(mesh.vertices[vo], faces, normals=pick(mesh.normals, vo),
                colors=pick(mesh.colors, vo), quality=pick(mesh.quality, vo),
                material=pick(mesh.material, fo), extra=dict(mesh.extra))


def write_ply(path: Path | str, mesh: Mesh, comment: str = "ibr_pipeline") -> None:
    """Write `mesh` as binary little-endian PLY, atomically."""
    vfields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if mesh.normals is not None:
        vfields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if mesh.colors is not None:
        vfields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    if mesh.quality is not None:
        vfields += [("quality", "<f4")]
    v = np.empty(len(mesh.vertices), dtype=np.dtype(vfields))
    for i, k in enumerate("xyz"):
        v[k] = mesh.vertices[:, i]
        if mesh.normals is not None:
            v["n" + k] = mesh.normals[:, i]
    if mesh.colors is not None:
        for i, k in enumerate(("red", "green", "blue")):
            v[k] = mesh.colors[:, i]
    if mesh.quality is not None:
        v["quality"] = mesh.quality
    ffields = [("n", "u1"), ("v", "<i4", (3,))]
    if mesh.material is not None:
        ffields.append(("material", "<i4"))
    f = np.empty(len(mesh.faces), dtype=np.dtype(ffields))
    f["n"] = 3
    f["v"] = mesh.faces
    if mesh.material is not None:
        f["material"] = mesh.material
    rev = {"<f4": "float", "u1": "uchar", "<i4": "int"}
    header = ["ply", "format binary_little_endian 1.0", f"comment {comment}",
              f"element vertex {len(v)}"]
    header += [f"property {rev[t]} {n}" for n, t in vfields]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices"]
    if mesh.material is not None:
        header.append("property int material")
    header.append("end_header\n")
    with atomic_path(Path(path)) as tmp, open(tmp, "wb") as fh:
        fh.write("\n".join(header).encode("ascii"))
        fh.write(v.tobytes())
        fh.write(f.tobytes())


def _parse_header(data: bytes, path: Path):
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply") or end < 0:
        raise InputError(f"{path}: not a PLY file")
    lines = data[:end].decode("ascii", "replace").splitlines()
    fmt, elements = None, []
    for line in lines[1:]:
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        if tok[0] == "format":
            fmt = tok[1]
        elif tok[0] == "element":
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property" and elements:
            elements[-1][2].append(tok[1:])
    return fmt, elements, end + len(b"end_header\n")


def read_ply(path: Path | str) -> Mesh:
    """Read a triangle mesh; raises InputError naming the file when it is not a readable mesh."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise InputError(f"{path}: cannot read mesh ({e.strerror})") from e
    fmt, elements, offset = _parse_header(data, path)
    names = [e[0] for e in elements]
    simple = (fmt == "binary_little_endian" and names == ["vertex", "face"]
              and all(p[0] != "list" for p in elements[0][2])
              and elements[1][2][0][:3] == ["list", "uchar", "int"]
              and all(p[0] != "list" for p in elements[1][2][1:]))
    if not simple:
        return _read_with_open3d(path)
    try:
        vdt = np.dtype([(p[1], _TYPES[p[0]]) for p in elements[0][2]])
        fdt = np.dtype([("n", "u1"), ("v", "<i4", (3,))]
                       + [(p[1], _TYPES[p[0]]) for p in elements[1][2][1:]])
        nv, nf = elements[0][1], elements[1][1]
        v = np.frombuffer(data, dtype=vdt, count=nv, offset=offset)
        f = np.frombuffer(data, dtype=fdt, count=nf, offset=offset + nv * vdt.itemsize)
    except (KeyError, ValueError) as e:
        raise InputError(f"{path}: truncated or unsupported PLY ({e})") from e
    if nf and not np.all(f["n"] == 3):
        return _read_with_open3d(path)
    fields = v.dtype.names
    verts = np.stack([v["x"], v["y"], v["z"]], 1)
    if not np.all(np.isfinite(verts)):
        raise InputError(f"{path}: mesh has non-finite vertex positions")
    get = (lambda keys, dt: np.stack([v[k] for k in keys], 1).astype(dt)
           if all(k in fields for k in keys) else None)
    return Mesh(verts, f["v"], normals=get(("nx", "ny", "nz"), np.float32),
                colors=get(("red", "green", "blue"), np.uint8),
                quality=v["quality"].astype(np.float32) if "quality" in fields else None,
                material=f["material"] if "material" in (f.dtype.names or ()) else None)


def _read_with_open3d(path: Path) -> Mesh:
    import open3d as o3d
    m = o3d.io.read_triangle_mesh(str(path))
    if len(m.vertices) == 0:
        raise InputError(f"{path}: no vertices could be read from this mesh")
    return Mesh(np.asarray(m.vertices), np.asarray(m.triangles),
                normals=np.asarray(m.vertex_normals) if m.has_vertex_normals() else None,
                colors=(np.asarray(m.vertex_colors) * 255).round().astype(np.uint8)
                if m.has_vertex_colors() else None)
