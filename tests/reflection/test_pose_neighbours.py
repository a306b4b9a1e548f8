"""decompose_terms.nearest_by_pose against sorting by pose_distance one pair at a time."""
import numpy as np

from ibr_pipeline.geometry.decompose_terms import nearest_by_pose, pose_distance
from ibr_pipeline.scene import Camera


def _cameras(n, seed):
    rng = np.random.default_rng(seed)
    K = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    return [Camera.look_at(rng.uniform(-1, 1, 3), np.array([0.0, 0.0, 4.0]) + rng.normal(0, 0.5, 3),
                           np.array([0.0, -1.0, 0.0]), K, 64, 48) for _ in range(n)]


def test_equals_the_pairwise_sort():
    for seed, n, k in ((0, 9, 2), (1, 15, 4), (2, 3, 5)):
        cams = _cameras(n, seed)
        got = nearest_by_pose(cams, k)
        for a, cam in enumerate(cams):
            ref = sorted((b for b in range(n) if b != a), key=lambda b: pose_distance(cam, cams[b]))
            assert got[a] == ref[:k]
        assert all(len(g) == min(k, n - 1) for g in got)


def test_ties_keep_list_order_and_edge_cases():
    cams = _cameras(4, 7)
    twins = [cams[0], cams[1], cams[1], cams[2]]  # the same camera twice: a tie
    got = nearest_by_pose(twins, 3)
    assert got[1][0] == 2 and got[2][0] == 1  # each twin's nearest is the other
    assert nearest_by_pose([], 2) == [] and nearest_by_pose(cams[:1], 2) == [[]]
