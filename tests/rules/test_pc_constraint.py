"""The PC-EI solver and the shared ellipsoidal geometry (cifilter.rules._pc_constraint and
cifilter.rules._ellipsoidal), through their public names: derivatives against finite
differences, the positive definiteness test, and the inequality behind the closed form
with partial ties checked against the general solver.
"""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_ei import random_spd

from cifilter import ellipsoidal_intersection, pc_ellipsoidal_intersection
from cifilter.rules._ellipsoidal import decompose, pair_estimates, whiten
from cifilter.rules._pc_constraint import (
    ConstraintProblem,
    constraint_base,
    positive_definite,
    solve_batch,
)

inv = np.linalg.inv


def test_pc_gradient_and_hessian_of_psi_match_finite_differences():
    g = np.random.default_rng(3)
    n = 3
    for mutual_mean in ("as-printed", "sijs-lazar"):
        lam = np.exp(g.uniform(-1, 1, n))
        J0 = np.diag(np.minimum(1, lam))
        problem = ConstraintProblem(
            np.diag(np.maximum(0, 1 - lam))[None], np.diag(np.maximum(0, lam - 1))[None],
            J0[None], g.standard_normal((1, n)), g.standard_normal((1, n)), lam[None],
            np.zeros(1), mutual_mean)
        X = g.standard_normal((n, n))
        N = (0.2 * X @ X.T / n + 0.05 * np.eye(n))[None]
        _, grad, hess = problem.psi_derivatives(N)
        basis, h = problem.basis, 1e-6
        for p in range(basis.q):
            E = basis.matrix(np.eye(basis.q)[p])[None]
            up, down = problem.psi_derivatives(N + h * E), problem.psi_derivatives(N - h * E)
            assert (up[0] - down[0])[0] / (2 * h) == pytest.approx(grad[0, p], rel=1e-6)
            np.testing.assert_allclose((up[1] - down[1])[0] / (2 * h), hess[0, p],
                                       rtol=1e-5, atol=1e-6 * np.abs(hess).max())


def test_positive_definite_test_matches_eigenvalues():
    g = np.random.default_rng(0)
    H = g.standard_normal((200, 5, 5))
    H = H @ np.swapaxes(H, -1, -2) - g.uniform(0, 2, (200, 1, 1)) * np.eye(5)
    expected = np.linalg.eigvalsh(H)[:, 0] > 1e-10
    np.testing.assert_array_equal(positive_definite(H), expected)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_sijs_lazar_partial_ties_closed_form_matches_the_interior_point_solver(seed):
    """One tied direction (whitened e_Z != 0): C_c - C_EI has rank one and is optimal.

    The closed form rests on psi >= e_Z^T N_ZZ^-1 e_Z / 2 (tested below); here the
    general interior-point solver, run on the same problem, finds the same optimum.
    """
    g = np.random.default_rng(seed)
    Pa = random_spd(3, seed=seed)
    T = np.linalg.cholesky(Pa)
    Pb = T @ np.diag([1.0, np.exp(g.uniform(0.2, 1)), np.exp(-g.uniform(0.2, 1))]) @ T.T
    xa, xb = 0.5 * g.standard_normal(3), 0.5 * g.standard_normal(3)
    pc = pc_ellipsoidal_intersection(xa, Pa, xb, Pb)
    ei = ellipsoidal_intersection(xa, Pa, xb, Pb)
    assert pc.info["active"] and pc.info["solver"] == "closed-form"
    added = pc.info["common_P"] - ei.info["common_P"]
    assert np.linalg.matrix_rank(added, tol=1e-9 * np.abs(added).max()) == 1
    # the general solver on the whitened problem
    w = whiten(pair_estimates(xa[None], Pa, xb[None], Pb))
    tie, lam, J0, A0, B0 = constraint_base(w, 1e-8, "information")
    problem = ConstraintProblem(A0, B0, J0, w.a, w.b, lam,
                                np.log([pc.info["threshold"]]), "sijs-lazar")
    solved = solve_batch(problem, tie, 1e-10, 300)
    assert solved["converged"][0]
    general = -np.linalg.slogdet(J0[0] - solved["N"][0])[1]
    closed = np.linalg.slogdet(pc.info["common_P"])[1] - np.linalg.slogdet(Pa)[1]
    assert general == pytest.approx(closed, abs=1e-7)


@given(st.integers(2, 5).flatmap(lambda n: st.tuples(st.just(n), st.integers(1, n - 1))),
       st.integers(0, 2**32 - 1))
def test_sijs_lazar_psi_is_bounded_by_the_tied_block(sizes, seed):
    """psi(N) >= e_Z^T N_ZZ^-1 e_Z / 2 for every 0 < N < J_EI (Sijs & Lazar's mean).

    This is the inequality behind the closed form with tied directions Z (whitened
    coordinates, tied directions first).
    """
    n, z = sizes
    g = np.random.default_rng(seed)
    d = np.exp(g.uniform(-1.5, 1.5, n))
    d[:z] = 1.0
    lam = 1 / d
    J0 = np.diag(np.minimum(1, lam))
    A0, B0 = np.diag(np.maximum(0, 1 - lam)), np.diag(np.maximum(0, lam - 1))
    a, b = g.standard_normal(n), g.standard_normal(n)
    X = g.standard_normal((n, n)) * np.exp(g.uniform(-3, 1, (1, n)))
    root = np.sqrt(J0)
    N = root @ inv(np.eye(n) + inv(X @ X.T + 1e-9 * np.eye(n))) @ root
    psi = decompose(A0 + N, B0 + N, J0 - N, a, b, lam, "sijs-lazar").psi
    e = (a - b)[:z]
    assert psi >= e @ np.linalg.solve(N[:z, :z], e) / 2 * (1 - 1e-7) - 1e-12
