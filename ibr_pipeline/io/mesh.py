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
