"""geometry.fusion.triangle_components (clean_mesh's components) against open3d's
cluster_connected_triangles: the same partition, triangles joined only across shared edges."""
import numpy as np
import pytest

from ibr_pipeline.geometry.fusion import clean_mesh, triangle_components


def _partition(labels) -> set:
    """The partition as a set of frozensets of face indices (label values are arbitrary)."""
    labels = np.asarray(labels)
    return {frozenset(np.nonzero(labels == k)[0].tolist()) for k in np.unique(labels)}


def _open3d_labels(v, f):
    import open3d as o3d
    m = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(v), o3d.utility.Vector3iVector(f))
    return np.asarray(m.cluster_connected_triangles()[0])


def test_shared_edge_joins_shared_vertex_does_not():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [2, 1, 0], [1, 2, 0]], float)
    # faces 0 and 1 share edge (1, 2); face 2 touches face 1 only at vertex 3 (a bow tie)
    f = np.array([[0, 1, 2], [1, 3, 2], [3, 4, 5]])
    label, counts = triangle_components(f)
    assert _partition(label) == {frozenset({0, 1}), frozenset({2})}
    assert sorted(counts.tolist()) == [1, 2] and counts[label[0]] == 2
    assert _partition(label) == _partition(_open3d_labels(v, f))


@pytest.mark.parametrize("seed", range(3))
def test_same_partition_as_open3d(seed):
    rng = np.random.default_rng(seed)
    n = 60   # few vertices, many faces: non-manifold edges, bow ties and isolated pieces
    v = rng.normal(size=(n, 3))
    f = np.stack([rng.choice(n, 3, replace=False) for _ in range(40)])
    label, counts = triangle_components(f)
    assert _partition(label) == _partition(_open3d_labels(v, f))
    assert counts.sum() == len(f) and np.array_equal(counts, np.bincount(label))


def test_clean_mesh_drops_small_components_and_bad_faces():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [5, 5, 5], [6, 5, 5], [5, 6, 5]],
                 float)
    f = np.array([[0, 1, 2], [1, 3, 2], [4, 5, 6]])
    mesh, removed = clean_mesh(v, f, None, min_component=0.4)   # the lone face is 1/3 < 0.4
    assert removed == 1 and len(mesh.faces) == 2 and len(mesh.vertices) == 4
    assert triangle_components(np.zeros((0, 3), int))[0].shape == (0,)
    with pytest.raises(ValueError, match="faces"):
        triangle_components(np.zeros((3, 2), int))
