"""The image step's CG (geometry/block_pcg.py): the numba kernel against the numpy / scipy
reference, and both against a dense solve."""
import numpy as np
import pytest
import scipy.sparse as sp

from ibr_pipeline.geometry.block_pcg import block_pcg, block_pcg_reference


def _problem(n=120, c=3, seed=0):
    rng = np.random.default_rng(seed)
    A = sp.random(300, n, density=0.05, random_state=seed + 1) + sp.identity(300, format="csr")[:, :n]
    H = (A.T @ A + 0.1 * sp.identity(n)).tocsr()
    return H, rng.standard_normal((n, c))


@pytest.mark.parametrize("solve", [block_pcg, block_pcg_reference], ids=["numba", "reference"])
def test_solves_the_normal_equations_with_fixed_variables(solve):
    H, g = _problem()
    x = solve(H, g, np.zeros((120, 3)), np.ones((120, 3), bool), iterations=500, tol=1e-10)
    assert np.allclose(x, np.linalg.solve(H.toarray(), g), atol=1e-6)
    free = np.ones((120, 3), bool)
    free[:10] = False
    x0 = np.full((120, 3), 0.25)
    x = solve(H, g, x0, free, iterations=500, tol=1e-10)
    assert np.all(x[:10] == 0.25)
    Hd = H.toarray()
    ref = np.linalg.solve(Hd[10:, 10:], g[10:] - Hd[10:, :10] @ x0[:10])
    assert np.allclose(x[10:], ref, atol=1e-6)


@pytest.mark.parametrize("channels", [3, 1, 2])
@pytest.mark.parametrize("iterations", [1, 7, 40])
def test_the_kernel_follows_the_reference_iterate_by_iterate(channels, iterations):
    """Stopped early (before convergence), with a different fixed set per channel: the two
    implementations must give the same iterate, so the kernel is the reference's algorithm and
    not merely another solver of the same system."""
    H, g = _problem(200, channels, seed=3)
    rng = np.random.default_rng(4)
    free = rng.random((200, channels)) > 0.2
    x0 = rng.random((200, channels))
    a = block_pcg_reference(H, g, x0, free, iterations=iterations, tol=1e-12)
    b = block_pcg(H, g, x0, free, iterations=iterations, tol=1e-12)
    assert np.allclose(a, b, rtol=1e-9, atol=1e-12)
    assert np.all(b[~free] == x0[~free])
    if iterations == 1:  # one step moves the free variables: the comparison is not vacuous
        assert np.abs(b - x0)[free].max() > 1e-3


def test_a_float32_matrix_is_solved_alike_by_both_and_close_to_float64():
    """The image step stores H in float32 (decompose.matrix_precision): kernel and reference
    read the same rounded entries, so they still follow each other iterate by iterate, and the
    solution moves only by the rounding of H."""
    H, g = _problem(200, 3, seed=5)
    H32 = H.astype(np.float32)
    rng = np.random.default_rng(6)
    free = rng.random((200, 3)) > 0.2
    x0 = rng.random((200, 3))
    for its in (5, 300):
        a = block_pcg_reference(H32, g, x0, free, iterations=its, tol=1e-12)
        b = block_pcg(H32, g, x0, free, iterations=its, tol=1e-12)
        assert a.dtype == b.dtype == np.float64
        assert np.allclose(a, b, rtol=1e-9, atol=1e-12)
    x64 = block_pcg(H, g, x0, free, iterations=300, tol=1e-12)
    d = np.abs(b - x64).max() / np.abs(x64).max()
    assert 0 < d < 1e-5, d  # rounded entries: not the same matrix, nearly the same solution


def test_shapes_are_checked():
    H, g = _problem()
    with pytest.raises(ValueError, match="need H"):
        block_pcg(H, g[:10], np.zeros((10, 3)), np.ones((10, 3), bool))


def test_both_report_the_iterations_they_ran():
    H, g = _problem()
    counts = []
    for solve in (block_pcg, block_pcg_reference):
        info: dict = {}
        solve(H, g, np.zeros((120, 3)), np.ones((120, 3), bool), iterations=500, tol=1e-8, info=info)
        counts.append(info["iterations"])
        capped: dict = {}
        solve(H, g, np.zeros((120, 3)), np.ones((120, 3), bool), iterations=3, tol=1e-8, info=capped)
        assert capped["iterations"] == 3
    assert counts[0] == counts[1] and 3 < counts[0] < 500
