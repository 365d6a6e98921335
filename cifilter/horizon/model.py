"""Propagating a covariance bound through the local filter, and its steady state.

:func:`propagate_bound` carries a bound through predict/update steps (eqs. 16, 31-33 of
Ajgl et al. 2014); :func:`steady_state_covariance` is their limit (eq. 35). See
``docs/methods/horizon.rst``.
"""

from typing import Optional

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import linalg as sla

from .._numerics.linalg import condition_number, ill_conditioned, symmetrize
from .._numerics.validation import as_float_array, as_matrix, check_covariances, check_int
from ._core import PerStep
from ._model import as_model, at_horizon, checked_bound, riccati_scaled, update

__all__ = ["propagate_bound", "steady_state_covariance"]

def propagate_bound(P: ArrayLike, F: ArrayLike, Q: ArrayLike, H: PerStep, R: PerStep,
                    horizon: int, G: Optional[ArrayLike] = None, *,
                    history: bool = False) -> NDArray[np.float64]:
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
    The recursion runs on a power-of-two scale, so intermediate bounds never overflow (the
    scaling scheme is described in ``docs/methods/horizon.rst``, "Numerical formulation").

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
    P0 = as_float_array(P, "P")
    if P0.ndim < 2 or P0.shape[-1] != P0.shape[-2]:
        raise ValueError(f"P must hold square matrices (..., n, n), got shape {P0.shape}")
    P0, _ = check_covariances(P0, "P")
    model = as_model(F, Q, H, R, G, P0.shape[-1], steps=horizon if horizon else None)
    scaled = riccati_scaled(P0, model, horizon)
    steps = range(horizon + 1) if history else [horizon]
    bounds = [checked_bound(scaled[k][0], scaled[k][1],
                            at_horizon(k if k == horizon else f"{k} of {horizon}"))
              for k in steps]
    if not history:
        return bounds[-1]
    batch = np.broadcast_shapes(*(b.shape[:-2] for b in bounds))
    return np.stack([np.broadcast_to(b, batch + b.shape[-2:]) for b in bounds], axis=-3)


def steady_state_covariance(F: ArrayLike, Q: ArrayLike, H: Optional[ArrayLike],
                            R: Optional[ArrayLike],
                            G: Optional[ArrayLike] = None) -> NDArray[np.float64]:
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
