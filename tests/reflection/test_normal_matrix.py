"""decompose.normal_matrix: the image step's H = A^T A + D^T diag(w) D + diag(d) as one product
of stacked rows, against the sum written out."""
import numpy as np
import pytest
import scipy.sparse as sp

from ibr_pipeline.geometry.decompose import normal_matrix


def _terms(seed=0, P=60, N=150, E=90):
    rng = np.random.default_rng(seed)
    A = sp.random(N, P, density=0.08, random_state=seed, format="csr")
    e = rng.integers(0, P, (E, 2))
    e = e[e[:, 0] != e[:, 1]]
    D = sp.csr_matrix((np.r_[-np.ones(len(e)), np.ones(len(e))],
                       (np.r_[np.arange(len(e)), np.arange(len(e))], np.r_[e[:, 0], e[:, 1]])),
                      shape=(len(e), P))
    w = rng.random(len(e))
    w[::7] = 0.0   # an edge without weight, a variable with no diagonal term
    d = rng.random(P)
    d[3] = 0.0
    return A, D, w, d


@pytest.mark.parametrize("seed", range(3))
def test_equals_the_sum_of_the_three_terms(seed):
    A, D, w, d = _terms(seed)
    H = normal_matrix(A, D, w, d)
    ref = (A.T @ A + D.T @ sp.diags(w) @ D + sp.diags(d)).toarray()
    assert isinstance(H, sp.csr_matrix) and H.has_sorted_indices
    np.testing.assert_allclose(H.toarray(), ref, rtol=1e-12, atol=1e-12)
    # what the solver reads: H x for a block of right-hand sides
    x = np.random.default_rng(seed).normal(size=(A.shape[1], 3))
    np.testing.assert_allclose(H @ x, ref @ x, rtol=1e-10, atol=1e-10)


def test_shapes_are_checked():
    A, D, w, d = _terms()
    with pytest.raises(ValueError):
        normal_matrix(A, D, w[:-1], d)
    with pytest.raises(ValueError):
        normal_matrix(A, D, w, d[:-1])
