"""Shared test helpers: the examples of Ajgl et al. (2014) for the tests of
:mod:`cifilter.horizon` (``test_horizon_*.py``).

The models of the static and dynamical examples, the local bounds at k = 0, the CI bound for
a fixed omega written out, criterion values, random systems, a filter of the dynamical
example, and the checks shared by the horizon solvers' conditioning tests.
"""

import numpy as np

from cifilter import IllConditionedError, KalmanFilter, partial_ci
from cifilter.horizon import propagate_bound

# The dynamical example, eqs. (29)-(30).
F_DYN = 0.95 * np.eye(2)
Q_DYN = np.array([[1.0, 0.95], [0.95, 1.0]])
H_A, R_A = np.array([[1.0, 0.0]]), 1.0
H_B, R_B = np.array([[0.0, 1.0]]), 3.0
FILTERS = {"A": (H_A, R_A), "B": (H_B, R_B)}
# The static example, eqs. (22)-(23).
RA_STATIC, RB_STATIC = np.diag([1.0, 2.0]), np.diag([2.0, 1.0])
# Issue 9, item 4: an unstable model without measurements; the bound grows like 1.2^(2 k).
F_UNSTABLE = np.array([[1.2, 1.0], [0.0, 1.1]])


def local_bounds_at_zero():
    """MMSE estimates at k = 0 from P_0 = 10 I and one local measurement (eqs. 29-30)."""
    P0_inv = np.eye(2) / 10.0
    PA = np.linalg.inv(P0_inv + H_A.T @ H_A / R_A)
    PB = np.linalg.inv(P0_inv + H_B.T @ H_B / R_B)
    return PA, PB


def ci_bound(PA, PB, omega):
    return np.linalg.inv(omega * np.linalg.inv(PA) + (1 - omega) * np.linalg.inv(PB))


def criterion_value(P, criterion):
    if isinstance(criterion, np.ndarray):
        return np.einsum("ij,...ji->...", criterion, P)
    if criterion == "det":
        return np.linalg.det(P)
    if criterion == "trace":
        return np.trace(P, axis1=-2, axis2=-1)
    return np.einsum("ij,...ji->...", criterion, P)


def random_system(seed, n=3, p=2):
    g = np.random.default_rng(seed)
    A = g.standard_normal((n, n))
    F = A / max(1.0, 0.8 * np.abs(np.linalg.eigvals(A)).max()) * g.choice([0.7, 1.0, 1.2])
    B = g.standard_normal((n, n))
    Q = g.choice([0.01, 1.0]) * B @ B.T + 1e-3 * np.eye(n)
    H = g.standard_normal((p, n))
    C = g.standard_normal((p, p))
    R = g.choice([0.1, 1.0, 10.0]) * C @ C.T + 0.1 * np.eye(p)
    Ps = []
    for _ in range(2):
        D = g.standard_normal((n, n)) * g.choice([0.3, 1.0, 3.0])
        Ps.append(D @ D.T + 0.05 * np.eye(n))
    return F, Q, H, R, Ps[0], Ps[1]


def dynamic_filter(name):
    kf = KalmanFilter(dim_x=2, dim_z=1)
    kf.F, kf.Q = F_DYN.copy(), Q_DYN.copy()
    kf.H, kf.R = (H_A.copy(), np.eye(1) * R_A) if name == "A" else (H_B.copy(), np.eye(1) * R_B)
    return kf


def fused_bound_tolerance(Ps):
    """Rounding of a CI bound formed in information form: the default ``64 n N eps`` of
    :func:`worst_case.worst_violation` plus ``eps * max cond(P_i)`` (the information-form
    inverse of ``cifilter.covariance_intersection``'s fixed-omega path loses that much,
    relative to ``||P||``, for nearly equal inputs of condition number 1e11)."""
    Ps = np.asarray(Ps)
    count, n = Ps.shape[-3], Ps.shape[-1]
    return (64.0 * n * count + np.linalg.cond(Ps).max()) * np.finfo(float).eps


def assert_propagation_agrees(P, fused_P, Ps, F, Q, H, R, horizon):
    """``P`` (the horizon solver's bound) equals ``propagate_bound(fused_P, ...)``.

    The fused P's own rounding, and the propagation's: two routes to a bound whose condition
    number is cond(P) agree to about cond(P) eps relative to its norm (P = 1e12 I against
    R = 1 gives cond ~ 1e11 from well-conditioned inputs). The reference route (Joseph
    updates of F P F^T + Q) also loses eps ||prior|| absolutely: a prior of norm 3e9 (an
    estimate ignored along a measured direction) updated to a bound of norm 20 is accurate
    to only 1e-7 relative, while the solver's information form of the superposition
    formula stays exact (checked at 60 digits).
    """
    history = [fused_P]
    for _ in range(horizon):  # the reference, step by step: it has a contract of its own
        step_prior = F @ history[-1] @ F.T + Q
        try:
            history.append(propagate_bound(history[-1], F, Q, H, R, 1))
        except ValueError:  # IllConditionedError included
            # No reference: a prior beyond the conditioning contract, or one whose update
            # cancels more than float64 holds (its rounding eps ||prior|| is not small
            # against the bound the solver found; propagate_bound's covariance form)
            assert (np.linalg.cond(step_prior) > 1e12
                    or 64 * np.finfo(float).eps * np.abs(step_prior).max()
                    > 1e-3 * np.abs(P).max())
            return
    history = np.array(history)
    prior = np.abs(F @ history[:-1] @ F.T + Q).max() if horizon else 0.0
    eps = np.finfo(float).eps
    tol = max(1e-7, fused_bound_tolerance(Ps), 64 * eps * np.linalg.cond(P),
              64 * eps * prior / np.abs(P).max())
    np.testing.assert_allclose(P, history[-1], rtol=tol, atol=tol * np.abs(P).max())


def horizon_call_or_ill_conditioned(call, Ps, F, Q, H, R, horizon, rho=1.0):
    """``call()``, or None if it raises IllConditionedError naming the horizon for a problem
    whose propagated bound, at a vertex or the centre of the simplex, is beyond the
    contract's condition number 1e12 (the optimiser evaluates the criterion there)."""
    try:
        return call()
    except IllConditionedError as exc:
        assert f"horizon {horizon}" in str(exc)
        count, n = len(Ps), Ps[0].shape[-1]
        conditions = []
        for delta in np.vstack([np.eye(count), np.full(count, 1.0 / count)]):
            fused = partial_ci(np.zeros((count, n)), Ps, rho, delta=delta)
            try:
                conditions.append(np.linalg.cond(propagate_bound(fused.P, F, Q, H, R, horizon)))
            except IllConditionedError:
                conditions.append(np.inf)
        assert max(conditions) > 1e12, str(exc)
        return None
