"""Textured meshes as binary glTF (GLB) through trimesh: projective texturing by a capture view.

A per-view mesh (or a reflection layer's M0 / M1) is textured with the image its camera took: each
vertex's UV is its projection into that camera, so the photo lands on the geometry exactly where it
was seen (Debevec-style projective texturing; no atlas, one texture per mesh).

UV convention. trimesh's `TextureVisuals` follows OpenGL: the origin of (u, v) is the *bottom-left*
corner of the image, v up; its GLB exporter writes `1 - v` because glTF puts the origin at the
*top-left*, v down (and its importer flips back). `projective_uvs` therefore returns trimesh's
convention. With scene.py's pixel convention (the centre of the top-left pixel at (0, 0)), pixel
(x, y) has u = (x + 0.5) / W and v = 1 - (y + 0.5) / H, so a vertex that projects onto a pixel
centre samples exactly that texel.

Materials are PBR with the image as baseColorTexture, metallic 0, roughness 1 and the
`KHR_materials_unlit` extension (added to the glTF tree after trimesh builds it; trimesh 5.2 does
not write it itself), double-sided because mirror-world meshes (M1) have reversed winding. The
texture holds the 8-bit values of the PNG as they are: the pipeline's images are linear
(scene.py), glTF declares baseColor textures sRGB; an unlit viewer shows the stored values
unchanged, as an image viewer shows the PNG. Positions stay in the scene frame (no change of axes),
so a GLB lines up with the COLMAP / transforms.json exports of the same workspace.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..scene import Camera
from ..workspace import atomic_path

UNLIT = "KHR_materials_unlit"


def projective_uvs(vertices: np.ndarray, camera: Camera) -> np.ndarray:
    """(N, 2) float64 texture coordinates of world points `vertices` (N, 3) in `camera`'s image,
    in trimesh's convention (origin at the bottom-left of the image, v up: module docstring),
    clipped to [0, 1]. Points behind the camera (z <= 0) or projecting outside the image get the
    clipped value of their projection (their colour is meaningless either way; a view's own mesh
    has none)."""
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"projective_uvs: vertices must be (N, 3), got {v.shape}")
    px, z = camera.project(v)
    px = np.where((z > 0)[:, None], px, 0.0)   # behind the camera: no meaningful projection
    px = np.nan_to_num(px, nan=0.0, posinf=0.0, neginf=0.0)
    u = (px[:, 0] + 0.5) / camera.width
    vv = 1.0 - (px[:, 1] + 0.5) / camera.height
    return np.clip(np.stack([u, vv], axis=1), 0.0, 1.0)


def _uint8_rgb(image: np.ndarray) -> np.ndarray:
    a = np.asarray(image)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"textured_mesh: image must be (H, W, 3), got {a.shape}")
    if a.dtype == np.uint8:
        return np.ascontiguousarray(a)
    if not np.issubdtype(a.dtype, np.floating):
        raise ValueError(f"textured_mesh: image must be uint8 or float in [0, 1], got {a.dtype}")
    return np.clip(np.rint(np.nan_to_num(a) * 255.0), 0, 255).astype(np.uint8)


def textured_mesh(vertices: np.ndarray, faces: np.ndarray, image: np.ndarray, camera: Camera,
                  name: str):
    """A `trimesh.Trimesh` of `vertices` (N, 3) and `faces` (F, 3) with vertex normals, UVs from
    `projective_uvs` and `image` (H, W, 3; float in [0, 1] or uint8) as its PBR baseColor texture
    (metallic 0, roughness 1; `write_glb` marks it unlit). The image must have the camera's size:
    a UV is a fraction of the camera's image, so another size would shift nothing but mean a
    different camera. Vertex order is kept (no merging), so vertex i has UV i."""
    import trimesh
    from PIL import Image

    img = _uint8_rgb(image)
    if (img.shape[1], img.shape[0]) != camera.size:
        raise ValueError(f"textured_mesh: image is {img.shape[1]}x{img.shape[0]}, camera "
                         f"{camera.width}x{camera.height}")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and not np.issubdtype(f.dtype, np.integer)):
        raise ValueError(f"textured_mesh: faces must be (F, 3) integers, got {f.shape} {f.dtype}")
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise ValueError(f"textured_mesh: face index out of range for {len(v)} vertices")
    uv = projective_uvs(v, camera)
    material = trimesh.visual.material.PBRMaterial(
        name=name, baseColorTexture=Image.fromarray(img, "RGB"), baseColorFactor=[255, 255, 255, 255],
        metallicFactor=0.0, roughnessFactor=1.0, doubleSided=True)
    mesh = trimesh.Trimesh(vertices=v, faces=f.astype(np.int64),
                           visual=trimesh.visual.TextureVisuals(uv=uv, material=material),
                           process=False)   # processing would merge vertices and reorder UVs
    _ = mesh.vertex_normals                 # computed now (area-weighted), exported with the mesh
    return mesh


def _mark_unlit(tree: dict) -> None:
    """tree_postprocessor for trimesh's exporter: every material unlit (the metallic 0 / roughness
    1 PBR values stay as the fallback the extension's spec asks for)."""
    materials = tree.get("materials", [])
    for m in materials:
        m.setdefault("extensions", {})[UNLIT] = {}
    if materials:
        used = set(tree.get("extensionsUsed", []))
        tree["extensionsUsed"] = sorted(used | {UNLIT})


def glb_bytes(meshes: list) -> bytes:
    """The GLB of one scene holding each (name, Trimesh) of `meshes` as a node named `name`
    (its mesh and material named alike), at the identity transform."""
    import trimesh
    from trimesh.exchange.gltf import export_glb

    names = [n for n, _ in meshes]
    if len(set(names)) != len(names):
        raise ValueError(f"write_glb: node names must be unique, got {names}")
    scene = trimesh.Scene()
    for name, mesh in meshes:
        if not isinstance(name, str) or not name:
            raise ValueError(f"write_glb: node name must be a non-empty string, got {name!r}")
        scene.add_geometry(mesh, node_name=name, geom_name=name)
    return export_glb(scene, include_normals=True, tree_postprocessor=_mark_unlit)


def write_glb(path: Path | str, meshes: list) -> None:
    """Write `meshes` [(name, trimesh.Trimesh), ...] as one GLB scene with named nodes, atomically
    (temporary name + rename: a killed export never leaves a half-written file). Meshes without
    faces are written as nodes without geometry (glTF has no empty primitive)."""
    data = glb_bytes(meshes)
    with atomic_path(Path(path)) as tmp:
        tmp.write_bytes(data)
