"""Horizon-aware Covariance Intersection: choose omega for the bound after future filtering.

Ajgl, Šimandl, Reinhardt, Noack & Hanebeck (2014) show that the CI weight that minimises
the fused bound *now* is not the weight that minimises the bound after the filter has
processed more measurements. With the block-diagonal bound (13) of the joint covariance
fixed by omega, the best estimator of the state ``kappa`` steps later (the *batch*
approach, their Fig. 1) is the Kalman filter started from the CI bound (eqs. 16, 31-33);
omega is then chosen to minimise a criterion of that propagated bound. The *recursive*
approach (their Fig. 2) fixes omega at ``kappa = 0`` and filters on.

With ``rho=`` the same is done for partial-correlation CI (Wu, Cai & Fu 2018): the
block-diagonal bound of the joint covariance is ``blockdiag(P_i / w_i(delta))`` with eq. (24),
``w_i(delta) = delta_i / (rho_i + (1 - rho_i) delta_i)`` (Lemma 7), and ``delta`` on the simplex
is chosen for the horizon (:mod:`cifilter._partial_horizon`; the convexity proof is on the
documentation page ``docs/methods/horizon.rst``).

How the minimisation works (and why it is global)
--------------------------------------------------
Run the local filter's Riccati recursion once from ``P = 0`` (the initial state known
exactly). It gives ``P_c`` (the bound if the initial state were known), the closed-loop
transition ``Psi = prod_j (I - K_j H_j) F`` and the information ``Gamma`` that the future
measurements carry about the initial state. For every initial bound ``P_0``

    P_kappa(P_0) = P_c + Psi (P_0^-1 + Gamma)^-1 Psi^T                                (*)

(the superposition formula for Riccati solutions with different initial conditions, or
generalised least squares on the stacked initial estimates, process noises and
measurements). The CI bound has ``P_0(omega)^-1 = omega P_A^-1 + (1 - omega) P_B^-1``, so

    P_kappa(omega) = P_c + Psi S(omega)^-1 Psi^T,   S(omega) = omega S_A + (1 - omega) S_B,
    S_A = P_A^-1 + Gamma,   S_B = P_B^-1 + Gamma,

with ``S`` affine in omega. The matrix inverse is operator convex, so ``P_kappa(omega)`` is
matrix convex and ``trace(W P_kappa)`` is a convex function of omega. ``log det P_kappa``
is convex as well: if ``P_c`` is invertible, ``log det P_kappa = log det(S + Psi^T P_c^-1
Psi) - log det S + const``, whose second derivative ``tr(S^-1 D S^-1 D) - tr((S + G)^-1 D
(S + G)^-1 D)`` (``D = S_A - S_B``, ``G = Psi^T P_c^-1 Psi >= 0``) is non-negative because
``X -> tr(X D X D)`` increases with ``X`` in the positive semidefinite order (its gradient
``2 D X D`` is positive semidefinite); a singular ``P_c`` is the limit of invertible ones.
The same holds on the simplex for N estimates (``S(w) = sum_i w_i S_i``). Hence every
criterion here is convex in omega at every horizon, although the propagated bound is a
rational function of omega of growing degree, and a local minimum is the global one.

For two estimates, ``S_B = L L^T`` and ``L^-1 S_A L^-T = U diag(mu) U^T`` give ``S(omega)^-1 =
T diag(1 / (1 + omega (mu_k - 1))) T^T`` with ``T = L^-T U``, so the first and second
derivatives of the criterion are closed-form; :func:`cifilter._optimize.minimize_convex_interval`
returns ``omega = 0`` (``f'(0) >= 0``) or ``omega = 1`` (``f'(1) <= 0``) exactly and otherwise
brackets the root of ``f'`` and polishes it with safeguarded Newton steps. The sign
conditions on ``f'`` are the certificate of global optimality. ``Psi`` is carried with a
separate log-scale, so that the omega-dependent part of the bound, which decays like the
closed loop's spectral radius to the power ``2 kappa``, is never lost to rounding against
``P_c``: the optimum stays well defined at horizons where the criterion values themselves
agree to machine precision.

Overflow and conditioning (the conditioning contract)
-----------------------------------------------------
For an unstable model the bound grows like the spectral radius of ``F`` to the power
``2 kappa``. The terms are therefore carried as ``P_kappa = 2^e (P_c + exp(2 s) Psi S^-1
Psi^T)`` with an exact power-of-two exponent ``e`` (the recursion runs with ``G Q G^T`` and
``R`` scaled by ``2^-e``; nothing is rescaled below ``2^200``), the weights are optimised on
the scaled terms, and only the returned bound and criterion are multiplied out. A bound or a
criterion that float64 cannot represent raises a ``ValueError`` naming the horizon and the
quantity (and quoting the optimal weights, which stay well defined); a bound or horizon
term that is not numerically positive definite raises ``IllConditionedError`` (from
``cifilter._linalg``, a ``ValueError``). Nothing returns NaN, and no non-finite optimum is
reported as converged. Derivation and examples: ``docs/methods/horizon.rst``, "Numerical
formulation".
"""

import numbers
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np
from scipy import linalg as sla

from ._criteria import criterion_value as _criterion_value
from ._criteria import parse_criterion as _parse_criterion
from ._linalg import (
    IllConditionedError,
    cho_inverse,
    cho_solve,
    cholesky,
    condition_number,
    diagonalise_pair,
    ill_conditioned,
    symmetrize,
)
from ._optimize import minimize_convex_interval, minimize_convex_simplex
from ._partial_correlation import check_rho as _check_rho
from ._partial_correlation import effective_rho as _effective_rho
from ._partial_correlation import partial_weights as _partial_weights
from ._partial_horizon import information_bound, partial_horizon_delta
from ._riccati import (
    Terms,
    as_matrix,
    as_model,
    broadcast_terms,
    check_steps_available,
    horizon_terms,
    propagated_bound,
    riccati_scaled,
    unscale,
    update,
)
from ._validation import as_covariances, as_float_array, check_covariances, check_int
from .ci import ci_weights

__all__ = [
    "HorizonOmega",
    "HorizonStudy",
    "horizon_study",
    "horizon_weights",
    "optimal_omega",
    "propagate_bound",
    "steady_state_covariance",
]


# --------------------------------------------------------------------------- the weights
def _informations(Ps, Gamma):
    """S_i = P_i^-1 + Gamma, (..., N, n, n)."""
    est = as_covariances(Ps, name="Ps")
    informations = cho_inverse(est.L)
    return est, symmetrize(informations + Gamma[..., None, :, :])


def _pair_weights(S, terms, kind, W):
    """Optimal omega for two estimates from the simultaneous diagonalisation of S_A, S_B."""
    batch = S.shape[:-3]
    n = S.shape[-1]
    size = int(np.prod(batch, dtype=int))
    pair = diagonalise_pair(cholesky(S[..., 1, :, :], "P_B^-1 + Gamma"), S[..., 0, :, :])
    mu = pair.lam
    T = np.swapaxes(pair.L1_inv, -1, -2) @ pair.U  # S(omega)^-1 = T diag(d) T^T
    V = terms.Psi @ T  # the bound is P_c + exp(2 s) V diag(d) V^T, d = 1 / (1 + omega a)
    a = (mu - 1.0).reshape(size, n)
    if kind == "det":
        # The determinant needs a Cholesky factor of Z = P_c + exp(2 s) Psi S^-1 Psi^T. S^-1
        # is factored directly at every omega: rebuilt from the simultaneous diagonalisation,
        # T diag(d) T^T loses the small eigenvalues of S^-1 when S_A and S_B are
        # ill-conditioned in different directions (Z then came out indefinite).
        P_c = terms.P_c.reshape(size, n, n)
        Psi = terms.Psi.reshape(size, n, n)
        S_A = S[..., 0, :, :].reshape(size, n, n)
        S_B = S[..., 1, :, :].reshape(size, n, n)
        D = symmetrize(S_A - S_B)
        weight = np.exp(2.0 * terms.log_scale).reshape(size)

        def parts(omega, index):
            S_w = symmetrize(S_B[index] + omega[:, None, None] * D[index])
            X = cho_inverse(cholesky(S_w, "fused information"))
            Z = P_c[index] + weight[index, None, None] * (
                Psi[index] @ X @ np.swapaxes(Psi[index], -1, -2))
            LZ = cholesky(symmetrize(Z), "propagated bound")
            C = np.swapaxes(Psi[index], -1, -2) @ cho_solve(LZ, Psi[index])
            return X, C

        def derivatives(omega, index):
            # f = log det Z; f' and f'' divided by exp(2 s) (their sign and root are kept):
            # with M = C X D X, f' = -tr(M), f'' = 2 tr(M D X) - exp(2 s) tr(M M).
            X, C = parts(omega, index)
            XDX = X @ D[index] @ X
            M = C @ XDX
            g = -np.trace(M, axis1=-2, axis2=-1)
            # traces of products as sums of elementwise products (no einsum over 3 operands)
            h = 2.0 * ((M @ D[index]) * np.swapaxes(X, -1, -2)).sum(axis=(-2, -1)) - weight[
                index] * (M * np.swapaxes(M, -1, -2)).sum(axis=(-2, -1))
            return g, h

        everything = np.arange(size)
        ends = [parts(np.full(size, w), everything) for w in (0.0, 1.0)]
        scale = sum(np.einsum("iab,iba->i", C, X) for X, C in ends)
    else:
        weight_matrix = np.eye(n) if kind == "trace" else W
        c = np.einsum("...ik,...ij,...jk->...k", V, weight_matrix, V)
        c = np.broadcast_to(c, batch + (n,)).reshape(size, n)

        def derivatives(omega, index):
            d = 1.0 / (1.0 + omega[:, None] * a[index])
            term = c[index] * a[index] * d**2
            return -term.sum(axis=-1), 2.0 * (term * a[index] * d).sum(axis=-1)

        scale = (c * (1.0 + 1.0 / (1.0 + a))).sum(axis=-1)
    omega, iterations, converged = minimize_convex_interval(derivatives, size, scale=scale)
    weights = np.stack([omega, 1.0 - omega], axis=-1).reshape(batch + (2,))
    return weights, iterations.reshape(batch), converged.reshape(batch)


def _simplex_det_weights(S, terms):
    """Optimal weights for N > 2 estimates and f = log det P_kappa(w), by active-set Newton.

    With S(w) = sum_i w_i S_i, A_i = S^-1 S_i, C = exp(2 s) Psi^T Z^-1 Psi and
    M_i = C A_i S^-1: g_i = -tr(M_i), H_ij = 2 tr(C A_i A_j S^-1) - tr(M_i M_j).
    """
    count = S.shape[-3]
    weight = np.exp(2.0 * terms.log_scale)[..., None, None]
    # log det from a Cholesky factor has rounding errors of order n eps whatever its value;
    # the constant n tells the solver's rounding test (relative to |f|) that level, which it
    # would not see where det P_kappa is near 1 (it then ran to its iteration limit).
    level = float(S.shape[-1])

    def fused(w):
        L = cholesky(symmetrize(np.einsum("...k,...kij->...ij", w, S)), "fused information")
        S_inv = cho_inverse(L)
        LZ = cholesky(propagated_bound(terms, S_inv), "propagated bound")
        return S_inv, LZ

    def objective(w):
        return level + 2.0 * np.log(np.diagonal(fused(w)[1], axis1=-2, axis2=-1)).sum(axis=-1)

    def evaluate(w):
        S_inv, LZ = fused(w)
        f = level + 2.0 * np.log(np.diagonal(LZ, axis1=-2, axis2=-1)).sum(axis=-1)
        C = weight * (np.swapaxes(terms.Psi, -1, -2) @ cho_solve(LZ, terms.Psi))
        A = S_inv[..., None, :, :] @ S
        Mi = C[..., None, :, :] @ A @ S_inv[..., None, :, :]
        g = -np.trace(Mi, axis1=-2, axis2=-1)
        CA = C[..., None, :, :] @ A
        H = 2.0 * np.einsum("...iab,...jbc,...ca->...ij", CA, A, S_inv)
        H = H - np.einsum("...iab,...jba->...ij", Mi, Mi)
        return f, g, symmetrize(H)

    return minimize_convex_simplex(evaluate, objective, count, S.shape[:-3])


def _zero_to_identity(W):
    """Normalise weight matrices to max |entry| 1; an all-zero one (flat criterion) -> I."""
    size = np.abs(W).max(axis=(-2, -1), keepdims=True)
    return np.where(size > 0, W / np.where(size > 0, size, 1.0), np.eye(W.shape[-1]))


def _optimal_weights(Ps, terms, kind, W, rho=None):
    """Criterion-optimal weights (..., N) for the bound at the horizon described by ``terms``.

    With ``rho`` (..., N) the weights are partial CI's ``delta`` (eq. 24 of Wu et al.).
    """
    if rho is not None:
        return _optimal_partial(Ps, terms, kind, W, rho)
    est, S = _informations(Ps, terms.Gamma)
    batch = np.broadcast_shapes(S.shape[:-3], terms.P_c.shape[:-2], terms.log_scale.shape,
                                () if W is None else W.shape[:-2])
    S = np.broadcast_to(S, batch + S.shape[-3:])
    terms = broadcast_terms(terms, batch)
    if est.count == 2:
        weights, iterations, converged = _pair_weights(S, terms, kind, W)
        solver = "diagonalise"
    elif kind == "det":
        weights, iterations, converged = _simplex_det_weights(S, terms)
        solver = "simplex"
    else:
        # trace(W P_kappa) = trace(W P_c) + exp(2 s) trace(Psi^T W Psi S(w)^-1), and
        # S(w)^-1 is the CI bound of the matrices S_i^-1: a weighted-trace CI problem.
        base = np.eye(est.dim) if kind == "trace" else W
        weight = _zero_to_identity(symmetrize(np.swapaxes(terms.Psi, -1, -2) @ base
                                              @ terms.Psi))
        weights, info = ci_weights(cho_inverse(cholesky(S, "P_i^-1 + Gamma")), weight,
                                   method="simplex")
        iterations, converged, solver = info["iterations"], info["converged"], "simplex"
    _check_weights(weights)
    return weights, {"iterations": iterations, "converged": converged, "solver": solver}


def _solve(Ps, terms, kind, W, rho, horizons):
    """:func:`_optimal_weights`; a matrix found singular on the way becomes an
    IllConditionedError naming the horizon (never a NaN optimum)."""
    try:
        return _optimal_weights(Ps, terms, kind, W, rho)
    except ValueError as exc:  # IllConditionedError included: it gains the horizon
        if not isinstance(exc, IllConditionedError) and "not positive definite" not in str(exc):
            raise
        if "at horizon" in str(exc):
            raise
        shown = horizons if np.ndim(horizons) == 0 else f"in {np.asarray(horizons).tolist()}"
        raise IllConditionedError(
            f"at horizon {shown} the horizon terms are numerically singular ({exc}): the "
            "propagated bound's condition number exceeds what float64 resolves (for an "
            "unstable F it grows like the ratio of the two largest |eigenvalues| to the power "
            "2 * horizon); ask for a shorter horizon") from None


def _check_weights(weights):
    """Never return a non-finite optimum (as converged or otherwise)."""
    if not np.isfinite(weights).all():
        raise ValueError("the horizon-optimal weights are not finite: the propagated bound "
                         "is not representable in float64 for this model and horizon")


def _optimal_partial(Ps, terms, kind, W, rho):
    """Horizon-optimal ``delta`` of partial CI (module :mod:`cifilter._partial_horizon`)."""
    est = as_covariances(Ps, name="Ps")
    informations = cho_inverse(est.L)
    batch = np.broadcast_shapes(informations.shape[:-3], terms.P_c.shape[:-2],
                                terms.log_scale.shape, rho.shape[:-1],
                                () if W is None else W.shape[:-2])
    informations = np.broadcast_to(informations, batch + informations.shape[-3:])
    rho = np.broadcast_to(rho, batch + rho.shape[-1:])
    terms = broadcast_terms(terms, batch)
    weight = None if kind == "det" else np.eye(est.dim) if kind == "trace" else W
    delta, iterations, converged, gap = partial_horizon_delta(informations, terms, rho, weight)
    _check_weights(delta)
    return delta, {"iterations": iterations, "converged": converged, "solver": "simplex",
                   "gap": gap}


def _fused_bound(Ps, terms, weights, rho=None):
    """The propagated bound for CI weights, or partial CI's ``delta`` given ``rho``, / 2^e.

    Multiply by ``2^terms.exponent`` with :func:`cifilter._riccati.unscale` (which raises if
    the product overflows).
    """
    if rho is not None:
        informations = cho_inverse(as_covariances(Ps, name="Ps").L)
        return information_bound(informations, terms, _partial_weights(weights, rho))
    _, S = _informations(Ps, terms.Gamma)
    S_w = symmetrize(np.einsum("...k,...kij->...ij", weights, S))
    return propagated_bound(terms, cho_inverse(cholesky(S_w, "fused information")))


# --------------------------------------------------------------------------- public API
def propagate_bound(P, F, Q, H, R, horizon, G=None, *, history=False):
    """Carry a covariance bound through ``horizon`` Kalman filter steps.

    Each step is the prediction (16), ``M = F P F^T + G Q G^T``, followed by the update with
    the optimal gain (32) and the Joseph form (33), ``P = (I - K H) M (I - K H)^T + K R K^T``
    with ``K = M H^T (H M H^T + R)^-1``. Applied to a CI bound, this is the bound of the
    recursive approach of Ajgl et al. (2014); for a fixed omega it is also the bound of
    their batch approach (Sec. III).

    Parameters
    ----------
    P : array_like, shape (..., n, n)
        The bound at the fusion time (symmetric positive definite).
    F : array_like, shape (..., n, n)
        State transition matrix.
    Q : array_like, shape (..., m, m), or float
        Process noise covariance (positive semidefinite; a number means ``Q * I``).
    H : array_like, shape (..., p, n), sequence, or None
        Measurement matrix used at every step; a list of ``horizon`` matrices (or None
        entries for steps without a measurement), one per step; None for a prediction-only
        horizon.
    R : array_like, shape (..., p, p), float, sequence, or None
        Measurement noise covariance (positive definite; a number means ``R * I``), a list
        matching ``H``, or None when ``H`` is None.
    horizon : int
        Number of predict/update steps, ``kappa >= 0``.
    G : array_like, shape (..., n, m), optional
        Noise gain of eq. (1); default the identity (``Q`` is then n x n).
    history : bool, optional
        Also return the bounds after 0, 1, ..., ``horizon`` steps.

    Returns
    -------
    ndarray, shape (..., n, n), or (..., horizon + 1, n, n) with ``history=True``
        The propagated bound (symmetric); leading batch axes of all inputs broadcast.

    Raises
    ------
    ValueError
        Bad shapes, non-finite values, ``P`` or ``R`` not symmetric positive definite, ``Q``
        not positive semidefinite, ``H`` given without ``R`` (or vice versa), a sequence of
        the wrong length, a negative horizon; a propagated bound that float64 cannot hold
        (an unstable ``F`` and a long horizon: the message names the horizon, with
        ``history=True`` the first that overflows, and the size of the bound).
    IllConditionedError
        A propagated bound that is finite but not numerically positive definite.
    TypeError
        Non-numeric input or a non-integer horizon.

    Notes
    -----
    The recursion runs on ``P / 2^e`` with ``G Q G^T`` and ``R`` scaled alike (``e`` an
    integer, changed only when the largest entry passes ``2^200``; the gains are scale
    invariant), so intermediate bounds never overflow; the returned bound is finite,
    symmetric and positive definite.

    References
    ----------
    .. [1] J. Ajgl, M. Šimandl, M. Reinhardt, B. Noack and U. D. Hanebeck, "Covariance
       intersection in state estimation of dynamical systems", FUSION 2014, eqs. (16),
       (31)-(33).

    Examples
    --------
    The static example (eqs. 22-28): one future measurement of filter A turns the CI bound
    (24) into (28), ``diag(2 / (3 + omega), 2 / (3 - omega))``.

    >>> import numpy as np
    >>> from cifilter import covariance_intersection
    >>> from cifilter.horizon import propagate_bound
    >>> RA, RB = np.diag([1.0, 2.0]), np.diag([2.0, 1.0])
    >>> fused = covariance_intersection([np.zeros(2)] * 2, [RA, RB], omega=0.5).P
    >>> propagate_bound(fused, np.eye(2), 0.0, np.eye(2), RA, horizon=1).round(4).tolist()
    [[0.5714, 0.0], [0.0, 0.8]]
    """
    horizon = check_int(horizon, "horizon", low=0)
    P = as_float_array(P, "P")
    if P.ndim < 2 or P.shape[-1] != P.shape[-2]:
        raise ValueError(f"P must hold square matrices (..., n, n), got shape {P.shape}")
    P, _ = check_covariances(P, "P")
    model = as_model(F, Q, H, R, G, P.shape[-1], steps=horizon if horizon else None)
    scaled = riccati_scaled(P, model, horizon)
    steps = range(horizon + 1) if history else [horizon]
    bounds = [_checked_bound(*scaled[k], _at(k if k == horizon else f"{k} of {horizon}"))
              for k in steps]
    if not history:
        return bounds[-1]
    batch = np.broadcast_shapes(*(b.shape[:-2] for b in bounds))
    return np.stack([np.broadcast_to(b, batch + b.shape[-2:]) for b in bounds], axis=-3)


@dataclass(frozen=True, repr=False)
class HorizonOmega:
    """The CI weight chosen for a horizon (result of :func:`optimal_omega`).

    The parameters are also the attributes of the result.

    Parameters
    ----------
    omega : ndarray, shape (...) or (..., N)
        The weight of the first estimate (:func:`optimal_omega`) or the weights of all N
        estimates (:func:`horizon_weights`). With ``rho`` (partial CI) these are
        ``delta`` (the simplex variable of eq. (24) of Wu, Cai & Fu 2018; ``delta = omega``
        for ``rho = 1``).
    value : ndarray, shape (...)
        The criterion of the propagated bound at the horizon with these weights (the
        determinant for ``"det"``).
    P : ndarray, shape (..., n, n)
        The propagated bound at the horizon (batch approach, eqs. 31-33).
    info : dict
        ``horizon``, ``criterion``, ``omega_recursive`` and ``value_recursive`` (the weights
        of the recursive approach, optimal at horizon 0, and the criterion they give at the
        horizon), ``iterations``, ``converged`` and ``solver``. With ``rho`` also ``rho``
        (..., N) the bounds used (``sqrt(rho_1 rho_2)`` twice for a pair), ``weights``
        (..., N) the information weights ``w_i`` of eq. (24) (they do not sum to one) and
        ``gap``, a certified bound on the relative excess of the criterion over its
        minimum.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.horizon import optimal_omega
    >>> r = optimal_omega(np.diag([1.0, 2.0]), np.diag([2.0, 1.0]), np.eye(2), 0.0,
    ...                   np.eye(2), np.diag([1.0, 2.0]), horizon=1)
    >>> round(float(r.omega), 12), float(r.info["omega_recursive"])
    (0.0, 0.5)
    """

    omega: np.ndarray
    value: np.ndarray
    P: np.ndarray
    info: Any

    def __repr__(self):
        return (f"HorizonOmega(omega={np.array2string(np.asarray(self.omega), precision=4)}, "
                f"value={np.array2string(np.asarray(self.value), precision=4)}, "
                f"horizon={self.info.get('horizon')})")


def _at(horizons, weights=None):
    """``where(index)`` for error messages; the last batch axis runs over ``horizons`` if an
    array is given, and the weights found there (..., N) are quoted (they are well defined)."""

    def where(index):
        index = tuple(int(i) for i in index)
        if np.ndim(horizons):
            text, batch_index = f"at horizon {horizons[index[-1]]}", index[:-1]
        else:
            text, batch_index = f"at horizon {horizons}", index
        if batch_index:
            text += f" (batch index {batch_index})"
        if weights is not None:
            found = np.round(np.asarray(weights)[index], 6).tolist()
            text += f", where the optimal weights {found} are still well defined,"
        return text

    return where


def _value(P_hat, exponent, kind, W, where):
    """The criterion of ``2^e P_hat`` without forming it (ValueError if not representable).

    ``det`` is ``exp(log det)`` from a Cholesky factor of ``P_hat`` plus ``n e ln 2``.
    """
    exponent = np.broadcast_to(exponent, P_hat.shape[:-2])
    if kind == "det":
        n = P_hat.shape[-1]
        L = cholesky(P_hat, "propagated bound")
        log_det = (2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)
                   + n * np.log(2.0) * exponent)
        bad = (log_det > np.log(np.finfo(float).max)) | (log_det < np.log(np.finfo(float).tiny))
        if bad.any():
            index = np.unravel_index(int(np.argmax(bad.ravel())), bad.shape)
            raise ValueError(
                f"det of the propagated bound {where(index)} is not representable in float64: "
                f"log det = {float(log_det[index]):.6g}; ask for a shorter horizon")
        return np.exp(log_det)
    value = _criterion_value(P_hat, kind, W)
    return unscale(value[..., None, None], exponent, "the criterion of the propagated bound",
                   where)[..., 0, 0]


def _checked_bound(P_hat, exponent, where):
    """``2^e P_hat``: finite (ValueError otherwise) and positive definite
    (IllConditionedError otherwise)."""
    P = unscale(P_hat, exponent, "the propagated bound", where)
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        cond = condition_number(P)
        index = np.unravel_index(int(np.argmax(cond.ravel())), cond.shape)
        raise ill_conditioned(f"the propagated bound {where(index)}", cond[index],
                              "is not numerically positive definite") from None
    return P


def _choose(Ps, model, horizon, criterion, n, rho=None):
    """Horizon-optimal weights, value and bound, and the recursive approach's for comparison."""
    kind, W = _parse_criterion(criterion, n)
    check_steps_available(model, horizon)
    terms_list = horizon_terms(model, horizon, n, collect=sorted({0, horizon}))
    start, terms = terms_list[0], terms_list[-1]
    weights, info = _solve(Ps, terms, kind, W, rho, horizon)
    recursive, _ = _solve(Ps, start, kind, W, rho, 0)
    P_hat = _fused_bound(Ps, terms, weights, rho)
    where = _at(horizon, np.broadcast_to(weights, P_hat.shape[:-2] + weights.shape[-1:]))
    P = _checked_bound(P_hat, terms.exponent, where)
    value = _value(P_hat, terms.exponent, kind, W, where)
    P_recursive = _fused_bound(Ps, terms, recursive, rho)
    info.update(horizon=horizon, criterion=kind, omega_recursive=recursive,
                value_recursive=_value(P_recursive, terms.exponent, kind, W, _at(horizon)))
    if rho is not None:
        info.update(rho=np.broadcast_to(rho, weights.shape).copy(),
                    weights=_partial_weights(weights, rho))
    return weights, value, P, info


def _as_rho(rho, count, batch_shape):
    """Validated bounds (..., N) as partial CI uses them (eq. 24; pairs: sqrt(rho_1 rho_2))."""
    if rho is None:
        return None
    try:
        lead = np.shape(rho)[:-1]
    except ValueError:  # ragged: let the validation name it
        lead = ()
    try:
        batch_shape = np.broadcast_shapes(batch_shape, lead)
    except ValueError:
        raise ValueError(f"rho of shape {np.shape(rho)} does not broadcast against the batch "
                         f"shape {batch_shape} of the covariances") from None
    return _effective_rho(_check_rho(rho, count, batch_shape))


def optimal_omega(PA, PB, F, Q, H, R, horizon, criterion="trace", G=None, *, rho=None):
    """The CI weight that minimises the bound ``horizon`` filter steps after the fusion.

    The batch approach of Ajgl et al. (2014): the CI bound
    ``P_0(omega) = (omega P_A^-1 + (1 - omega) P_B^-1)^-1`` is carried through ``horizon``
    predict/update steps of the local filter (eqs. 16, 31-33) and ``omega`` minimises the
    criterion of the result. ``horizon = 0`` is ordinary criterion-optimal CI.

    Parameters
    ----------
    PA, PB : array_like, shape (..., n, n)
        Covariances (bounds) of the two estimates; ``omega`` weighs ``PA``.
    F, Q, H, R, G : array_like
        The model of the filter that fuses and then filters on; see :func:`propagate_bound`
        (``H`` and ``R`` may be None or per-step sequences).
    horizon : int
        The horizon ``kappa >= 0`` whose bound is minimised.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        ``trace(P)``, ``det(P)`` or ``trace(W P)`` of the propagated bound.
    rho : float or array_like, shape (..., 2) or (..., 1), optional
        Correlation coefficient bound(s) of partial CI (Wu, Cai & Fu 2018), as for
        :func:`cifilter.partial_ci` (per-estimate bounds of a pair act through
        ``sqrt(rho_1 rho_2)``). Then the bound at the fusion time is eq. (33),
        ``(w_A P_A^-1 + w_B P_B^-1)^-1`` with the weights (24) of ``delta = (omega,
        1 - omega)``, and ``omega`` is the horizon-optimal ``delta_1``; apply it with
        ``partial_ci(..., rho, delta=...)``. None (default): Covariance Intersection.

    Returns
    -------
    HorizonOmega
        ``omega`` (...), the criterion ``value``, the propagated bound ``P`` and ``info``
        (including the recursive approach's omega and value for comparison).

    Raises
    ------
    ValueError
        Bad covariances, model or criterion (see :func:`propagate_bound`); a propagated bound
        or criterion value that float64 cannot hold at this horizon (the message names the
        horizon, the quantity and the optimal weights, which remain well defined).
    IllConditionedError
        The propagated bound, or a horizon term the ``"det"`` criterion needs, is not
        numerically positive definite (its condition number exceeds what float64 resolves).
    TypeError
        Non-numeric input or a non-integer horizon.

    Notes
    -----
    The criterion is a convex function of omega at every horizon (proof in the module
    docstring of :mod:`cifilter.horizon`): with ``P_c``, ``Psi``, ``Gamma`` from one Riccati
    run started at ``P = 0``, ``P_kappa(omega) = P_c + Psi S(omega)^-1 Psi^T`` with ``S``
    affine in omega, and the inverse is operator convex (trace criteria) and ``log det`` of
    this form has a non-negative second derivative. So the global minimum on [0, 1] is found
    without a grid: a simultaneous diagonalisation of ``S_A`` and ``S_B`` gives the
    derivatives in closed form; the optimum is ``omega = 0`` exactly if ``f'(0) >= 0``,
    ``omega = 1`` if ``f'(1) <= 0`` (boundary optima, as in the static example), and
    otherwise the bracketed root of ``f'`` (safeguarded Newton, tolerance 1e-13). These sign
    conditions certify global optimality. The test suite compares the result with dense
    grids on random systems. Batched over leading axes of all inputs.

    With ``rho`` the bound is ``P_c + Psi S(delta)^-1 Psi^T`` with
    ``S(delta) = sum_i w_i(delta) P_i^-1 + Gamma``; it is convex in ``delta`` as well
    (``w_i`` is concave, ``S`` matrix concave and the criteria convex and non-increasing in
    ``S``), and it is minimised by the active-set Newton method on the simplex with exact
    gradients and Hessians (see :func:`horizon_weights`).

    References
    ----------
    .. [1] J. Ajgl, M. Šimandl, M. Reinhardt, B. Noack and U. D. Hanebeck, "Covariance
       intersection in state estimation of dynamical systems", FUSION 2014, Sec. III,
       eqs. (13)-(16), (31)-(34), Figs. 3 and 6.
    .. [2] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, Lemma 7, eqs. (24), (33) (with ``rho``).

    Examples
    --------
    The dynamical example (eqs. 29-30, 34): at the fusion time the determinant picks
    ``omega = 0.6``; filter A, expecting its own measurements, almost ignores its estimate.

    >>> import numpy as np
    >>> from cifilter.horizon import optimal_omega
    >>> F, Q = 0.95 * np.eye(2), np.array([[1.0, 0.95], [0.95, 1.0]])
    >>> PA, PB = np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13])
    >>> HA = np.array([[1.0, 0.0]])
    >>> round(float(optimal_omega(PA, PB, F, Q, HA, 1.0, 0, "det").omega), 6)
    0.6
    >>> round(float(optimal_omega(PA, PB, F, Q, HA, 1.0, 50, "det").omega), 4)
    0.0418

    With a correlation coefficient bound of 0.5 (partial CI), ``delta_1`` moves less:

    >>> [round(float(optimal_omega(PA, PB, F, Q, HA, 1.0, k, "det", rho=0.5).omega), 4)
    ...  for k in (0, 50)]
    [0.5511, 0.2666]
    """
    horizon = check_int(horizon, "horizon", low=0)
    Ps = _pair(PA, PB)
    rho = _as_rho(rho, 2, Ps.shape[:-3])
    model = as_model(F, Q, H, R, G, Ps.shape[-1])
    weights, value, P, info = _choose(Ps, model, horizon, criterion, Ps.shape[-1], rho)
    info["omega_recursive"] = info["omega_recursive"][..., 0]
    return HorizonOmega(weights[..., 0], value, P, info)


def _pair(PA, PB):
    PA, PB = as_float_array(PA, "PA"), as_float_array(PB, "PB")
    for name, M in (("PA", PA), ("PB", PB)):
        if M.ndim < 2 or M.shape[-1] != M.shape[-2]:
            raise ValueError(f"{name} must hold square matrices (..., n, n), got shape {M.shape}")
    if PA.shape[-1] != PB.shape[-1]:
        raise ValueError(f"PA is {PA.shape[-1]}x{PA.shape[-1]} but PB is "
                         f"{PB.shape[-1]}x{PB.shape[-1]}")
    batch = np.broadcast_shapes(PA.shape[:-2], PB.shape[:-2])
    n = PA.shape[-1]
    return np.stack([np.broadcast_to(PA, batch + (n, n)), np.broadcast_to(PB, batch + (n, n))],
                    axis=-3)


def horizon_weights(Ps, F, Q, H, R, horizon, criterion="trace", G=None, *, rho=None):
    """Horizon-optimal CI weights of N estimates (the generalisation of :func:`optimal_omega`).

    The CI bound ``(sum_i w_i P_i^-1)^-1`` is carried through ``horizon`` filter steps and
    the weights ``w`` on the simplex minimise the criterion of the result.

    Parameters
    ----------
    Ps : sequence of array_like or array_like, shape (..., N, n, n)
        Covariances of the N >= 2 estimates.
    F, Q, H, R, G : array_like
        The model of the filter that fuses; see :func:`propagate_bound`.
    horizon : int
        The horizon ``kappa >= 0``.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What to minimise.
    rho : float or array_like, shape (..., N) or (..., 1), optional
        Correlation coefficient bound(s) of partial CI (Wu, Cai & Fu 2018), as for
        :func:`cifilter.partial_ci`: the fused bound is eq. (33) with the weights (24) of
        ``delta`` and ``omega`` is the horizon-optimal ``delta``; apply it with
        ``partial_ci(..., rho, delta=omega)``. None (default): Covariance Intersection.

    Returns
    -------
    HorizonOmega
        ``omega`` of shape (..., N), ``value``, ``P`` and ``info`` (``omega_recursive`` is
        then (..., N) as well; with ``rho`` also ``rho``, ``weights`` and ``gap``).

    Raises
    ------
    ValueError
        Fewer than two estimates, bad covariances, model or criterion; a propagated bound or
        criterion value that float64 cannot hold (as :func:`optimal_omega`).
    IllConditionedError
        As :func:`optimal_omega`.
    TypeError
        Non-numeric input or a non-integer horizon.

    Notes
    -----
    With ``S_i = P_i^-1 + Gamma`` the bound is ``P_c + Psi (sum_i w_i S_i)^-1 Psi^T``, convex in
    ``w`` (module docstring). For the trace criteria, ``trace(W P_kappa) = trace(W P_c) +
    trace(Psi^T W Psi (sum_i w_i S_i)^-1)`` is a weighted-trace CI problem of the matrices
    ``S_i^-1`` and is solved by :func:`cifilter.ci_weights`; for ``"det"`` an active-set Newton
    method on the simplex uses the closed-form gradient and Hessian of ``log det P_kappa``.
    N = 2 goes to the interval solver of :func:`optimal_omega`.

    With ``rho``, ``S(delta) = sum_i w_i(delta) P_i^-1 + Gamma`` (the weights (24) do not sum
    to one, so this information form replaces ``sum_i w_i S_i``). The criterion is convex in
    ``delta`` for every ``rho`` in [0, 1] (proof on the documentation page) and the
    active-set Newton method on the simplex minimises it, for every N, with the gradient and
    Hessian in ``w`` chained through ``w_i' = rho_i / b_i^2`` and
    ``w_i'' = -2 rho_i (1 - rho_i) / b_i^3`` (``b_i = rho_i + (1 - rho_i) delta_i``); optima on
    faces (``delta_i = 0``) are exact. ``info["gap"]`` certifies the result from convexity.
    Positive bounds below 1e-8 are raised to 1e-8 for the iterations only (the curvature
    grows like ``rho_i^-2`` near ``delta_i = 0``); the bound is always that of the true
    ``rho``, and ``gap`` states how far from its optimum the ``delta`` can be. ``rho_i = 0``
    means ``w_i = 1`` whatever ``delta_i``: such an input gets ``delta_i = 0`` when others
    are correlated, and with ``rho = 0`` throughout every ``delta`` is optimal and the start
    ``1/N`` is kept. ``rho = 1`` is the CI problem.

    References
    ----------
    .. [1] J. Ajgl, M. Šimandl, M. Reinhardt, B. Noack and U. D. Hanebeck, "Covariance
       intersection in state estimation of dynamical systems", FUSION 2014 (two estimates;
       the N-estimate form is this package's generalisation).
    .. [2] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, Lemma 7, eqs. (24), (33), (34) (with ``rho``;
       the horizon-aware choice of ``delta`` is this package's generalisation).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.horizon import horizon_weights
    >>> Ps = [np.diag([1.0, 2.0]), np.diag([2.0, 1.0]), np.diag([1.5, 1.5])]
    >>> r = horizon_weights(Ps, np.eye(2), 0.0, np.eye(2), np.diag([1.0, 2.0]), horizon=1)
    >>> r.omega.round(4).tolist()
    [0.0, 1.0, 0.0]

    Partial CI with bounds 0.3, 0.3 and 0 (the third estimate is uncorrelated, so its
    weight is 1 and it needs no ``delta``):

    >>> r = horizon_weights(Ps, np.eye(2), 0.0, np.eye(2), np.diag([1.0, 2.0]), horizon=1,
    ...                     rho=[0.3, 0.3, 0.0])
    >>> r.omega.round(4).tolist(), r.info["weights"].round(4).tolist()
    ([0.4713, 0.5287, 0.0], [0.7482, 0.789, 1.0])
    """
    horizon = check_int(horizon, "horizon", low=0)
    est = as_covariances(Ps, name="Ps")
    rho = _as_rho(rho, est.count, est.batch_shape)
    model = as_model(F, Q, H, R, G, est.dim)
    weights, value, P, info = _choose(est.P, model, horizon, criterion, est.dim, rho)
    return HorizonOmega(weights, value, P, info)


def steady_state_covariance(F, Q, H, R, G=None):
    """Steady-state posterior covariance of the local Kalman filter.

    The prior ``M`` solves the discrete algebraic Riccati equation
    ``M = F M F^T - F M H^T (H M H^T + R)^-1 H M F^T + G Q G^T``
    (:func:`scipy.linalg.solve_discrete_are`); the posterior is
    ``M - M H^T (H M H^T + R)^-1 H M``, the limit of eq. (33). Without measurements
    (``H = R = None``) it is the solution of the Lyapunov equation ``M = F M F^T + G Q G^T``.

    Parameters
    ----------
    F : array_like, shape (..., n, n)
        State transition matrix.
    Q : array_like, shape (..., m, m), or float
        Process noise covariance.
    H : array_like, shape (..., p, n), or None
        Measurement matrix.
    R : array_like, shape (..., p, p), float, or None
        Measurement noise covariance.
    G : array_like, shape (..., n, m), optional
        Noise gain (default identity).

    Returns
    -------
    ndarray, shape (..., n, n)
        The steady posterior covariance (symmetric, finite, positive semidefinite; singular
        only along noise-free modes).

    Raises
    ------
    ValueError
        Bad shapes or values; no stabilising solution (for example an undetectable pair
        ``(F, H)``, or ``F`` not stable without measurements).
    IllConditionedError
        A solution that is not finite or not positive semidefinite beyond rounding (the
        solvers' result is checked, never returned as NaN).
    TypeError
        Non-numeric input.

    Notes
    -----
    SciPy's solvers are not vectorised, so batched models are solved one at a time.

    References
    ----------
    .. [1] J. Ajgl, M. Šimandl, M. Reinhardt, B. Noack and U. D. Hanebeck, "Covariance
       intersection in state estimation of dynamical systems", FUSION 2014, eq. (35).

    Examples
    --------
    Eq. (35), filter A of the dynamical example:

    >>> import numpy as np
    >>> from cifilter.horizon import steady_state_covariance
    >>> F, Q = 0.95 * np.eye(2), np.array([[1.0, 0.95], [0.95, 1.0]])
    >>> steady_state_covariance(F, Q, np.array([[1.0, 0.0]]), 1.0).round(4).tolist()
    [[0.6076, 0.5772], [0.5772, 1.5483]]
    """
    F0 = as_matrix(F, "F")
    n = F0.shape[-1]
    model = as_model(F0, Q, H, R, G, n)
    if model.steps is not None:
        raise ValueError("steady_state_covariance needs one H and R, not a sequence per step")
    parts = [model.F, model.noise] + ([] if model.constant is None else list(model.constant))
    batch = np.broadcast_shapes(*(p.shape[:-2] for p in parts))
    parts = [np.broadcast_to(p, batch + p.shape[-2:]) for p in parts]
    out = np.empty(batch + (n, n))
    for index in np.ndindex(*batch):  # SciPy's Riccati and Lyapunov solvers take one model
        F_i, noise_i = parts[0][index], parts[1][index]
        if model.constant is None:
            if np.max(np.abs(np.linalg.eigvals(F_i))) >= 1.0:
                raise ValueError("without measurements the steady state exists only for a "
                                 "stable F (spectral radius < 1)")
            out[index] = sla.solve_discrete_lyapunov(F_i, noise_i)
            continue
        H_i, R_i = parts[2][index], parts[3][index]
        try:
            M = sla.solve_discrete_are(F_i.T, H_i.T, noise_i, R_i)
        except (np.linalg.LinAlgError, ValueError) as exc:
            raise ValueError(f"the Riccati equation has no stabilising solution ({exc}); "
                             "is (F, H) detectable?") from None
        out[index] = update(symmetrize(M), (H_i, R_i))[0]
    out = symmetrize(out)
    finite = np.isfinite(out).all(axis=(-2, -1))
    if not finite.all():
        raise ill_conditioned("the steady-state covariance", np.inf, "is not finite")
    # A steady state may be singular (noise-free stable modes); negative beyond rounding it
    # may not.
    eigenvalues = np.linalg.eigvalsh(out)
    tolerance = 64.0 * n * np.finfo(float).eps * np.abs(eigenvalues).max(axis=-1)
    if np.any(eigenvalues[..., 0] < -tolerance):
        raise ill_conditioned("the steady-state covariance", condition_number(out),
                              "is not numerically positive semidefinite")
    return out


@dataclass(frozen=True, repr=False)
class HorizonStudy:
    """Batch versus recursive CI over a range of horizons (result of :func:`horizon_study`).

    The parameters are also the attributes of the result. Trailing axes run over the
    horizons; leading axes are the batch of fusion problems.

    Parameters
    ----------
    horizons : ndarray, shape (K,)
        The horizons ``kappa``.
    omega : ndarray, shape (..., K)
        The batch-optimal omega for each horizon.
    batch : ndarray, shape (..., K)
        The criterion of the propagated bound with the horizon-optimal omega.
    recursive : ndarray, shape (..., K)
        The criterion with omega fixed at its horizon-0 optimum (the recursive approach).
    omega_recursive : ndarray, shape (...)
        The omega of the recursive approach (criterion-optimal CI at the fusion time).
    criterion : str
        ``"trace"``, ``"det"`` or ``"weighted-trace"``.
    P_batch, P_recursive : ndarray, shape (..., K, n, n)
        The propagated bounds of the two approaches.
    steady_P : ndarray, shape (..., n, n), or None
        The local filter's steady posterior covariance (discrete algebraic Riccati
        equation), the limit of both bounds; None for per-step measurement models.
    steady_value : ndarray, shape (...), or None
        Its criterion (the limit of ``batch`` and ``recursive``).
    omega_limit : ndarray, shape (...)
        The limit of the batch-optimal omega as the horizon grows (NaN if it has none, for
        instance when the closed loop's dominant mode rotates, or for per-step models).
    rho : ndarray, shape (..., 2), or None
        The correlation coefficient bounds of partial CI as used (``sqrt(rho_A rho_B)``
        twice), or None for CI; with ``rho`` the omega fields hold ``delta_1``.

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.horizon import horizon_study
    >>> F, Q = 0.95 * np.eye(2), np.array([[1.0, 0.95], [0.95, 1.0]])
    >>> s = horizon_study(np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13]), F, Q,
    ...                   np.array([[1.0, 0.0]]), 1.0, horizons=10, criterion="det")
    >>> bool(np.all(s.batch <= s.recursive)), round(float(s.omega_limit), 3)
    (True, 0.042)
    """

    horizons: np.ndarray
    omega: np.ndarray
    batch: np.ndarray
    recursive: np.ndarray
    omega_recursive: np.ndarray
    criterion: str
    P_batch: np.ndarray
    P_recursive: np.ndarray
    steady_P: Optional[np.ndarray]
    steady_value: Optional[np.ndarray]
    omega_limit: np.ndarray
    rho: Optional[np.ndarray] = None

    def __repr__(self):
        return (f"HorizonStudy(criterion={self.criterion!r}, horizons {self.horizons[0]}.."
                f"{self.horizons[-1]}, batch shape={np.shape(self.omega_recursive)})")

    def plot(self, axes=None, label=None):
        """Draw omega and the two criteria against the horizon (as Figs. 3 and 4).

        Parameters
        ----------
        axes : sequence of two matplotlib.axes.Axes, optional
            Where to draw omega and the criterion; new axes in a new figure by default.
        label : str, optional
            Prefix of the legend labels (for instance the filter's name).

        Returns
        -------
        matplotlib.figure.Figure
            The figure of the axes.

        Raises
        ------
        ValueError
            If the study is batched (draw one problem: index the inputs first) or ``axes``
            does not hold two axes.

        Examples
        --------
        >>> import matplotlib
        >>> matplotlib.use("Agg")
        >>> import matplotlib.pyplot as plt
        >>> import numpy as np
        >>> from cifilter.horizon import horizon_study
        >>> s = horizon_study(np.eye(2), 2 * np.eye(2), 0.9 * np.eye(2), np.eye(2),
        ...                   np.array([[1.0, 0.0]]), 1.0, horizons=5)
        >>> fig = s.plot(label="A")
        >>> plt.close(fig)
        """
        if np.ndim(self.omega_recursive) != 0:
            raise ValueError("plot draws one fusion problem; this study is batched with shape "
                             f"{np.shape(self.omega_recursive)}")
        import matplotlib.pyplot as plt

        if axes is None:
            _, axes = plt.subplots(1, 2, figsize=(9, 3.5), layout="constrained")
        if len(axes) != 2:
            raise ValueError(f"axes must hold two matplotlib axes, got {len(axes)}")
        prefix = f"{label}: " if label else ""
        ax_omega, ax_value = axes
        ax_omega.plot(self.horizons, self.omega, "o-", ms=3, label=f"{prefix}batch (optimal)")
        ax_omega.axhline(float(self.omega_recursive), ls="--", color="gray",
                         label=f"{prefix}recursive (fixed at 0)")
        if np.isfinite(self.omega_limit):
            ax_omega.axhline(float(self.omega_limit), ls=":", color="k",
                             label=f"{prefix}limit")
        weight = "$\\omega$" if self.rho is None else "$\\delta_1$ (partial CI)"
        ax_omega.set(xlabel="horizon $\\kappa$", ylabel=weight, ylim=(-0.02, 1.02))
        ax_value.plot(self.horizons, self.batch, "-", label=f"{prefix}batch")
        ax_value.plot(self.horizons, self.recursive, "--", label=f"{prefix}recursive")
        if self.steady_value is not None:
            ax_value.axhline(float(self.steady_value), ls=":", color="k",
                             label=f"{prefix}steady state")
        ax_value.set(xlabel="horizon $\\kappa$", ylabel=f"{self.criterion} of the bound")
        for ax in axes:
            ax.legend(fontsize="small")
        return ax_omega.figure


def _as_horizons(horizons):
    if isinstance(horizons, numbers.Integral) and not isinstance(horizons, bool):
        return np.arange(check_int(horizons, "horizons", low=0) + 1)
    values = np.asarray(horizons)
    if values.ndim != 1 or values.size == 0 or not np.issubdtype(values.dtype, np.integer):
        raise ValueError("horizons must be a non-negative integer K (meaning 0..K) or a "
                         f"non-empty 1-D sequence of integers, got {horizons!r}")
    if np.any(values < 0):
        raise ValueError(f"horizons must be >= 0, got {values.min()}")
    return values.astype(int)


def _stack_terms(terms_list):
    batch = np.broadcast_shapes(*(t.log_scale.shape for t in terms_list),
                                *(t.P_c.shape[:-2] for t in terms_list))
    terms_list = [broadcast_terms(t, batch) for t in terms_list]
    return Terms(*(np.stack(parts, axis=len(batch)) for parts in zip(*terms_list)))


# Horizons at which the limit of omega is looked for; converged when the last two agree.
_LIMIT_HORIZONS = (200, 400)


def horizon_study(PA, PB, F, Q, H, R, horizons, criterion="trace", G=None, *, limit=True,
                  rho=None):
    """Batch versus recursive Covariance Intersection for a range of horizons.

    For each horizon ``kappa``, the batch approach of Ajgl et al. (2014) chooses omega for the
    bound after ``kappa`` filter steps (:func:`optimal_omega`); the recursive approach fixes
    omega at its ``kappa = 0`` optimum and filters on (eqs. 31-33). The study also gives the
    steady-state limit of both bounds (the local filter's discrete algebraic Riccati
    equation) and the limit of the batch-optimal omega.

    Parameters
    ----------
    PA, PB : array_like, shape (..., n, n)
        Covariances (bounds) of the two estimates; omega weighs ``PA``.
    F, Q, H, R, G : array_like
        The model of the fusing filter (see :func:`propagate_bound`); per-step sequences of
        ``H`` and ``R`` need one entry per step up to the largest horizon.
    horizons : int or sequence of int
        ``K`` for the horizons 0, 1, ..., K, or the horizons themselves.
    criterion : {"trace", "det"} or array_like, shape (n, n), optional
        What to minimise.
    limit : bool, optional
        Compute ``omega_limit`` (default True; it costs a 400-step recursion).
    rho : float or array_like, shape (..., 2) or (..., 1), optional
        Correlation coefficient bound(s) of partial CI (see :func:`optimal_omega`); the
        omega fields then hold ``delta_1``. None (default): Covariance Intersection.

    Returns
    -------
    HorizonStudy
        Arrays ``horizons``, ``omega``, ``batch``, ``recursive`` (and the bounds, the steady
        state and the limit of omega) and a ``plot()`` method.

    Raises
    ------
    ValueError
        Bad covariances, model, criterion or horizons; a bound or criterion value that float64
        cannot hold at one of the horizons (named in the message).
    IllConditionedError
        As :func:`optimal_omega`.
    TypeError
        Non-numeric input.

    Notes
    -----
    One Riccati run from ``P = 0`` gives the terms of ``P_kappa(omega) = P_c + Psi S(omega)^-1
    Psi^T`` at every horizon (module docstring), and the convex problems of all horizons and
    batch items are solved together. For a fixed omega the batch and the recursive bounds
    coincide (Sec. III of the paper), so ``batch <= recursive`` at every horizon, with
    equality at ``kappa = 0``. ``omega_limit`` is the optimum at horizons 200 and 400 (with
    the transition carried on a log scale, so nothing underflows) when the two agree to
    1e-8. ``steady_P`` is None when the Riccati equation has no stabilising solution.

    References
    ----------
    .. [1] J. Ajgl, M. Šimandl, M. Reinhardt, B. Noack and U. D. Hanebeck, "Covariance
       intersection in state estimation of dynamical systems", FUSION 2014, Sec. IV.B,
       eqs. (29)-(35), Figs. 3, 4, 6 and 7.
    .. [2] J. Wu, Q. Cai and M. Fu, "Covariance intersection for partially correlated
       random vectors", IEEE TAC 63(3), 2018, eqs. (24), (33) (with ``rho``).

    Examples
    --------
    Fig. 3, filter B with the trace criterion:

    >>> import numpy as np
    >>> from cifilter.horizon import horizon_study
    >>> F, Q = 0.95 * np.eye(2), np.array([[1.0, 0.95], [0.95, 1.0]])
    >>> s = horizon_study(np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13]), F, Q,
    ...                   np.array([[0.0, 1.0]]), 3.0, horizons=[0, 1, 50])
    >>> s.omega.round(3).tolist(), round(float(s.omega_limit), 3)
    ([0.412, 0.779, 0.853], 0.853)

    The same with partial CI for ``rho = 0.5``:

    >>> s = horizon_study(np.diag([10 / 11, 10.0]), np.diag([10.0, 30 / 13]), F, Q,
    ...                   np.array([[0.0, 1.0]]), 3.0, horizons=[0, 1, 50], rho=0.5)
    >>> s.omega.round(3).tolist(), round(float(s.omega_limit), 3)
    ([0.433, 0.639, 0.657], 0.657)
    """
    horizons = _as_horizons(horizons)
    Ps = _pair(PA, PB)
    rho = _as_rho(rho, 2, Ps.shape[:-3])
    rho_k = None if rho is None else rho[..., None, :]
    n = Ps.shape[-1]
    kind, W = _parse_criterion(criterion, n)
    model = as_model(F, Q, H, R, G, n)
    check_steps_available(model, int(horizons.max()))
    distinct = sorted(set(horizons.tolist()) | {0})
    limit = bool(limit) and model.steps is None
    limit_at = [h for h in _LIMIT_HORIZONS if h not in distinct] if limit else []
    everything = sorted(set(distinct) | set(limit_at))
    collected = dict(zip(everything, horizon_terms(model, everything[-1], n,
                                                     collect=everything)))
    terms = _stack_terms([collected[h] for h in horizons])
    Ps_k = Ps[..., None, :, :, :]
    weights, _ = _solve(Ps_k, terms, kind, W, rho_k, horizons)
    recursive_w, _ = _solve(Ps, collected[0], kind, W, rho, 0)
    P_hat = _fused_bound(Ps_k, terms, weights, rho_k)
    where = _at(horizons, np.broadcast_to(weights, P_hat.shape[:-2] + weights.shape[-1:]))
    P_batch = _checked_bound(P_hat, terms.exponent, where)
    batch_value = _value(P_hat, terms.exponent, kind, W, where)
    P_hat = _fused_bound(Ps_k, terms, recursive_w[..., None, :], rho_k)
    P_recursive = _checked_bound(P_hat, terms.exponent, _at(horizons))
    recursive_value = _value(P_hat, terms.exponent, kind, W, _at(horizons))
    batch_shape = P_batch.shape[:-3]
    omega_limit = np.full(batch_shape, np.nan)
    if limit:
        tail = _stack_terms([collected[h] for h in _LIMIT_HORIZONS])
        w_tail, _ = _solve(Ps_k, tail, kind, W, rho_k, _LIMIT_HORIZONS)
        first, last = w_tail[..., 0, 0], w_tail[..., 1, 0]
        omega_limit = np.where(np.abs(first - last) < 1e-8, last, np.nan)
    steady_P = steady_value = None
    if model.steps is None:
        try:
            steady_P = steady_state_covariance(model.F, model.noise,
                                               *(model.constant or (None, None)))
        except ValueError:  # no stabilising solution: the bounds have no finite limit
            steady_P = None
        else:
            steady_value = _criterion_value(steady_P, kind, W)
    omega_recursive = recursive_w[..., 0]
    return HorizonStudy(
        horizons=horizons,
        omega=weights[..., 0],
        batch=batch_value,
        recursive=recursive_value,
        omega_recursive=np.broadcast_to(omega_recursive, batch_shape).copy(),
        criterion=kind,
        P_batch=P_batch,
        P_recursive=P_recursive,
        steady_P=steady_P,
        steady_value=steady_value,
        omega_limit=omega_limit,
        rho=None if rho is None else np.broadcast_to(rho, batch_shape + (2,)).copy(),
    )


# --------------------------------------------------------------------------- front-door hooks
def _model_parts(model):
    """F, Q, H, R, G of ``model``: a mapping or an object with those attributes."""
    fields = ("F", "Q", "H", "R", "G")
    if isinstance(model, dict):
        unknown = sorted(set(model) - set(fields))
        if unknown:
            raise ValueError(f"model has unknown entries {unknown}; it takes "
                             f"{', '.join(fields)}")
        get = model.get
    else:
        def get(name):
            return getattr(model, name, None)
    if get("F") is None or get("Q") is None:
        raise ValueError("model must give at least F and Q (and H, R for measurements)")
    return tuple(get(name) for name in fields)


def _horizon_options(estimates, model, steps, options, fixed, accepted, rho):
    if fixed in options:
        raise ValueError(f"{fixed}= fixes the weights and horizon= chooses them; give one")
    unknown = sorted(set(options) - accepted)
    if unknown:
        raise TypeError(f"horizon= accepts the option(s) "
                        f"{', '.join(map(repr, sorted(accepted)))}, got "
                        f"{', '.join(map(repr, unknown))}")
    F, Q, H, R, G = _model_parts(model)
    criterion = options.get("criterion", "trace")
    choice = horizon_weights(estimates.P, F, Q, H, R, steps, criterion, G, rho=rho)
    diagnostics = {
        "steps": choice.info["horizon"],
        "criterion": choice.info["criterion"],
        "value": choice.value,
        "value_recursive": choice.info["value_recursive"],
        "weights_recursive": choice.info["omega_recursive"],
        "iterations": choice.info["iterations"],
        "converged": choice.info["converged"],
        "solver": choice.info["solver"],
    }
    if "gap" in choice.info:
        diagnostics["gap"] = choice.info["gap"]
    return choice.omega, criterion, diagnostics


def ci_horizon_options(estimates, model, steps, options):
    """The ``"ci"`` rule's support of ``fuse(..., horizon=steps, model=model)``.

    Returns the options ``{"criterion": ..., "omega": w}`` with the weights that minimise
    the criterion of the bound ``steps`` filter steps after the fusion, and the diagnostics
    of that choice (stored as ``info["horizon"]``).
    """
    omega, criterion, diagnostics = _horizon_options(
        estimates, model, steps, options, "omega", {"criterion"}, None)
    return {"criterion": criterion, "omega": omega}, diagnostics


def pci_horizon_options(estimates, model, steps, options):
    """The ``"pci"`` rule's support of ``fuse(..., horizon=steps, model=model)``: the
    horizon-optimal ``delta`` for the given ``rho`` (see :func:`ci_horizon_options`)."""
    rho = options.get("rho")
    if rho is None:
        raise ValueError("the 'pci' rule needs a correlation coefficient bound: "
                         "fuse(..., method='pci', rho=..., horizon=...)")
    delta, _, diagnostics = _horizon_options(
        estimates, model, steps, options, "delta", {"criterion", "rho"}, rho)
    return {"rho": rho, "delta": delta}, diagnostics
