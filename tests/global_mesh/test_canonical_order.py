"""io.mesh.canonical_order / canonical_mesh: the vertex and face order that makes global/mesh.ply's
bytes a function of the surface alone (open3d's TSDF marching cubes emits its mesh in a
thread-dependent hash-map order), and tsdf_fuse returning its mesh in that order."""
import numpy as np
import pytest

from ibr_pipeline.io.mesh import Mesh, canonical_mesh, canonical_order, read_ply, write_ply


def _grid_mesh(n=6, seed=0):
    """A bumpy (n x n)-vertex grid with colours and per-face materials, in a scrambled order."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:n, 0:n].astype(np.float32)
    v = np.stack([x, y, rng.normal(size=x.shape).astype(np.float32)], -1).reshape(-1, 3)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel()
    f = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    cols = rng.integers(0, 256, (len(v), 3)).astype(np.uint8)
    return Mesh(v, f, colors=cols, material=rng.integers(0, 3, len(f)))


def _scramble(m: Mesh, seed: int) -> Mesh:
    """The same mesh with its vertices permuted, faces shuffled and each face rotated cyclically."""
    rng = np.random.default_rng(seed)
    perm = rng.permutation(len(m.vertices))
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    f = inv[m.faces]
    rot = rng.integers(0, 3, len(f))
    f = np.stack([f[np.arange(len(f)), (rot + k) % 3] for k in range(3)], 1)
    fo = rng.permutation(len(f))
    return Mesh(m.vertices[perm], f[fo], colors=m.colors[perm], material=m.material[fo])


def _face_normals(m: Mesh) -> np.ndarray:
    t = m.vertices[m.faces].astype(np.float64)
    return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])


def _same(a: Mesh, b: Mesh) -> bool:
    return (np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
            and np.array_equal(a.colors, b.colors) and np.array_equal(a.material, b.material))


def test_any_order_of_the_same_mesh_gives_the_same_bytes(tmp_path):
    m = _grid_mesh()
    outs = [canonical_mesh(_scramble(m, s)) for s in range(4)]
    assert all(_same(outs[0], o) for o in outs[1:])
    for i, o in enumerate(outs[:2]):
        write_ply(tmp_path / f"{i}.ply", o)
    assert (tmp_path / "0.ply").read_bytes() == (tmp_path / "1.ply").read_bytes()
    c = outs[0]
    # vertices sorted lexicographically by (x, y, z); faces start at their smallest index, sorted
    assert np.all(np.diff(np.lexsort(c.vertices.T[::-1])) == 1)
    assert np.all(c.faces[:, 0] < c.faces[:, 1]) and np.all(c.faces[:, 0] < c.faces[:, 2])
    assert np.all(np.diff(np.lexsort(c.faces.T[::-1])) == 1)
    # idempotent, and the round trip through the file keeps the order
    assert _same(canonical_mesh(c), c)
    assert _same(read_ply(tmp_path / "0.ply"), c)


def test_surface_and_orientation_are_kept():
    m = _grid_mesh()
    c = canonical_mesh(_scramble(m, 7))
    assert len(c.vertices) == len(m.vertices) and len(c.faces) == len(m.faces)

    def tris(x):  # each face as its corner positions from the smallest corner on, plus material
        t = x.vertices[x.faces]
        out = []
        for tri, mat in zip(t, x.material):
            k = min(range(3), key=lambda i: tuple(tri[i]))
            out.append((tuple(map(tuple, np.roll(tri, -k, axis=0))), int(mat)))
        return sorted(out)
    assert tris(c) == tris(m)   # same triangles with the same winding (a rotation, never a flip)
    up = lambda x: np.mean(_face_normals(x)[:, 2] > 0)  # noqa: E731
    assert up(c) == up(m)


def test_attributes_break_position_ties_and_identical_vertices_merge():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 0], [1, 0, 0]], np.float32)
    f = np.array([[0, 1, 2], [3, 4, 2]])
    # vertices 0 and 3 are the same point with different colours: kept apart, ordered by colour
    cols = np.array([[9, 9, 9], [1, 1, 1], [2, 2, 2], [5, 5, 5], [1, 1, 1]])
    vo, nf, fo = canonical_order(v, f, cols)
    assert list(vo[:2]) == [3, 0]      # (0,0,0) colour 5 before (0,0,0) colour 9
    # vertices 1 and 4 are identical in position and colour: merged into one
    assert len(vo) == 4 and sorted(fo) == [0, 1]
    vo2, nf2, fo2 = canonical_order(v[[3, 4, 2, 0, 1]], np.array([[3, 4, 2], [0, 1, 2]]), cols[[3, 4, 2, 0, 1]])
    assert np.array_equal(v[vo], v[[3, 4, 2, 0, 1]][vo2]) and np.array_equal(nf, nf2)
    # a face that merging collapses is dropped; without attributes the two (0,0,0) also merge
    vo3, nf3, fo3 = canonical_order(v, np.array([[0, 3, 1], [0, 1, 2]]))
    assert len(vo3) == 3 and list(fo3) == [1]
    # -0.0 == 0.0 as numbers but not as bytes: a fixed order, never merged
    vz = np.array([[0.0, 0, 0], [-0.0, 0, 0], [1, 0, 0]], np.float32)
    a = canonical_order(vz, np.array([[0, 1, 2]]))
    b = canonical_order(vz[[1, 0, 2]], np.array([[1, 0, 2]]))
    assert np.array_equal(vz[a[0]].view(np.uint32), vz[[1, 0, 2]][b[0]].view(np.uint32))
    assert len(a[0]) == 3


def _reference_vertex_order(v, a):
    """The order by one lexsort over every key: position as numbers, attributes, raw bits."""
    v32 = np.ascontiguousarray(v, np.float32)
    a = np.zeros((len(v32), 0)) if a is None else np.asarray(a, np.float64).reshape(len(v32), -1)
    ident = np.concatenate([v32.view(np.uint32).astype(np.uint64), a.view(np.uint64)], axis=1)
    keys = ([ident[:, j] for j in range(ident.shape[1] - 1, -1, -1)]
            + [a[:, j] for j in range(a.shape[1] - 1, -1, -1)] + [v32[:, i] for i in (2, 1, 0)])
    order = np.lexsort(keys)
    x = ident[order]
    new = np.r_[True, np.any(x[1:] != x[:-1], axis=1)]
    return order[new]


@pytest.mark.parametrize("seed", range(4))
def test_position_ties_sorted_as_one_lexsort_over_all_keys(seed):
    # many vertices on few positions (-0.0 and 0.0 among them), attributes with ties of their own
    rng = np.random.default_rng(seed)
    pts = np.array([[0.0, 0, 0], [-0.0, 0, 0], [0, 1, 0], [1, 0, 0], [1, 1, 2]], np.float32)
    v = np.concatenate([pts[rng.integers(0, len(pts), 300)], rng.normal(size=(300, 3))])
    v = v[rng.permutation(len(v))].astype(np.float32)
    a = rng.integers(0, 3, (len(v), 2)).astype(np.float64)
    f = np.stack([rng.permutation(len(v))[:3] for _ in range(200)])
    for attrs in (a, None):
        vo, _, _ = canonical_order(v, f, attrs)
        assert np.array_equal(vo, _reference_vertex_order(v, attrs))


def test_empty_and_bad_arguments():
    vo, nf, fo = canonical_order(np.zeros((0, 3)), np.zeros((0, 3), int))
    assert vo.shape == (0,) and nf.shape == (0, 3) and fo.shape == (0,)
    vo, nf, fo = canonical_order(np.eye(3), np.zeros((0, 3), int))   # vertices only: sorted
    assert list(vo) == [2, 1, 0] and nf.shape == (0, 3)
    v, f = np.eye(3), np.array([[0, 1, 2]])
    with pytest.raises(ValueError, match="vertices"):
        canonical_order(np.zeros((3, 2)), f)
    with pytest.raises(ValueError, match="faces"):
        canonical_order(v, np.array([0, 1, 2]))
    with pytest.raises(ValueError, match="integer"):
        canonical_order(v, f.astype(float))
    with pytest.raises(ValueError, match="out of range"):
        canonical_order(v, np.array([[0, 1, 3]]))
    with pytest.raises(ValueError, match="finite"):
        canonical_order(np.array([[np.nan, 0, 0], [1, 0, 0], [0, 1, 0]]), f)
    with pytest.raises(ValueError, match="attributes"):
        canonical_order(v, f, np.zeros((2, 3)))
    with pytest.raises(ValueError, match="face_attributes"):
        canonical_order(v, f, None, np.zeros(2))


def test_tsdf_fuse_returns_its_mesh_in_canonical_order(tiny_scene):
    """Fusion of the tiny scene's depth frames: the mesh comes out canonical (so global/mesh.ply's
    bytes do not depend on open3d's thread timing), twice the same."""
    from ibr_pipeline.geometry.fusion import FusionOptions, tsdf_fuse
    from ibr_pipeline.io.images import read_depth_png, read_image
    from ibr_pipeline.scene import cameras_from_json

    root = tiny_scene[0]
    cams = cameras_from_json(root / "cameras.json")

    def frames():
        for n, c in cams.items():
            yield read_depth_png(root / "depth" / n), c, read_image(root / "images" / n)

    opts = FusionOptions(voxel_size=0.02, depth_max=10.0)
    a, stats = tsdf_fuse(frames(), opts)
    b, _ = tsdf_fuse(frames(), opts)
    assert len(a.faces) > 1000 and stats["faces"] == len(a.faces)
    for x in (a, b):
        c = canonical_mesh(x)
        assert np.array_equal(c.vertices, x.vertices) and np.array_equal(c.faces, x.faces)
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.faces, b.faces)
    assert np.array_equal(a.normals, b.normals) and np.array_equal(a.colors, b.colors)


def test_a_frame_with_a_few_isolated_depths_is_skipped(tiny_scene):
    """open3d samples depth on a stride when it looks for voxel blocks, so a frame whose only
    valid depths sit between the samples touches none and open3d aborts the whole fusion (met on
    a real capture: an MVS view with almost no support). Such a frame is skipped and counted."""
    from ibr_pipeline.geometry.fusion import FusionOptions, tsdf_fuse
    from ibr_pipeline.io.images import read_depth_png
    from ibr_pipeline.scene import cameras_from_json

    root = tiny_scene[0]
    cams = cameras_from_json(root / "cameras.json")
    names = sorted(cams)

    def frames():
        for i, n in enumerate(names):
            d = read_depth_png(root / "depth" / n)
            if i == 1:
                d = np.zeros_like(d)
                d[1, 1] = 2.0  # one depth, off the sampling grid
            yield d, cams[n], None

    mesh, stats = tsdf_fuse(frames(), FusionOptions(voxel_size=0.02, depth_max=10.0))
    assert stats["skipped_empty_frames"] == 1 and stats["frames"] == len(names) - 1
    assert len(mesh.faces) > 1000
