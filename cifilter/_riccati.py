"""The local filter's linear model and its Riccati recursion, for :mod:`cifilter.horizon`.

Validation of ``F, Q, H, R, G`` (constant or one measurement model per step), the
predict/update steps of eqs. (16), (32)-(33) of Ajgl et al. (2014), and the terms of the
superposition formula ``P_kappa(P_0) = P_c + Psi (P_0^-1 + Gamma)^-1 Psi^T``.
"""

import numbers
from typing import NamedTuple, Optional

import numpy as np

from ._linalg import cho_solve, cholesky, solve_lower, symmetrize
from ._validation import as_float_array, as_matrix, check_covariances, check_psd

__all__ = ["Model", "Terms", "as_matrix", "as_model", "broadcast_terms", "check_steps_available",
           "horizon_terms", "predict", "propagated_bound", "riccati", "update"]


# --------------------------------------------------------------------------- the model
class Model(NamedTuple):
    """A validated linear model: x+ = F x + G w, z = H x + v."""

    F: np.ndarray  # (..., n, n)
    noise: np.ndarray  # G Q G^T, (..., n, n)
    steps: Optional[tuple]  # per-step (H, R) or None entries; None: ``constant`` every step
    constant: Optional[tuple]  # (H, R) used at every step, or None (prediction only)

    def measurement(self, step):
        """(H, R) of step ``step`` (0-based) or None for a prediction-only step."""
        return self.constant if self.steps is None else self.steps[step]


def is_step_sequence(value):
    """A list/tuple of matrices (or None): one entry per step, not one nested-list matrix."""
    return isinstance(value, (list, tuple)) and len(value) > 0 and all(
        item is None or np.ndim(item) >= 2 for item in value
    )


def measurement_model(H, R, n, names):
    """Validate one measurement model; None and None mean no measurement at this step."""
    h_name, r_name = names
    if H is None and R is None:
        return None
    if H is None or R is None:
        missing, given = (h_name, r_name) if H is None else (r_name, h_name)
        raise ValueError(f"{missing} is None but {given} is not: give both or neither")
    H = as_matrix(H, h_name, (None, n))
    p = H.shape[-2]
    if isinstance(R, numbers.Real) and not isinstance(R, bool):
        R = float(R) * np.eye(p)  # filterpy's convention for a scalar R
    R = as_float_array(R, r_name)
    if R.ndim < 2 or R.shape[-2:] != (p, p):
        raise ValueError(f"{r_name} must have shape (..., {p}, {p}) to match {h_name}, "
                         f"got shape {R.shape}")
    R, _ = check_covariances(R, r_name)
    return H, R


def as_model(F, Q, H, R, G, n, steps=None):
    """Validate the local filter's model for state dimension ``n``.

    ``steps`` is the number of per-step entries H and R must have when they are sequences.
    """
    F = as_matrix(F, "F", (n, n))
    if G is None:
        noise = check_psd(Q, n, "Q")
    else:
        G = as_matrix(G, "G")
        if G.shape[-2] != n:
            raise ValueError(f"G must have shape (..., {n}, m), got shape {G.shape}")
        Qm = check_psd(Q, G.shape[-1], "Q")
        noise = symmetrize(G @ Qm @ np.swapaxes(G, -1, -2))
    if is_step_sequence(H) or (H is None and is_step_sequence(R)):
        if not (isinstance(R, (list, tuple)) and isinstance(H, (list, tuple))
                and len(R) == len(H)):
            raise ValueError("when H is a sequence with one matrix per step, R must be a "
                             "sequence of the same length (and vice versa)")
        if steps is not None and len(H) != steps:
            raise ValueError(f"H and R have {len(H)} entries but the horizon needs one per "
                             f"step, {steps}")
        entries = tuple(
            measurement_model(h, r, n, (f"H[{j}]", f"R[{j}]")) for j, (h, r) in enumerate(zip(H, R))
        )
        return Model(F, noise, entries, None)
    return Model(F, noise, None, measurement_model(H, R, n, ("H", "R")))


def check_steps_available(model, horizon):
    if model.steps is not None and len(model.steps) < horizon:
        raise ValueError(f"H and R have {len(model.steps)} entries, fewer than the horizon "
                         f"{horizon}")


# --------------------------------------------------------------------------- Riccati steps
def predict(P, model):
    """Eq. (16): F P F^T + G Q G^T."""
    return symmetrize(model.F @ P @ np.swapaxes(model.F, -1, -2) + model.noise)


def update(M, measurement):
    """Eqs. (32)-(33): optimal gain and Joseph-form update of the prior bound ``M``.

    Returns the posterior, the closed-loop factor ``I - K H`` and the whitened
    measurement matrix ``L_S^-1 H`` (``S = H M H^T + R = L_S L_S^T``).
    """
    H, R = measurement
    HM = H @ M
    S = symmetrize(HM @ np.swapaxes(H, -1, -2) + R)
    L = cholesky(S, "innovation covariance H M H^T + R")
    K = np.swapaxes(cho_solve(L, HM), -1, -2)
    A = np.eye(M.shape[-1]) - K @ H
    P = A @ M @ np.swapaxes(A, -1, -2) + K @ R @ np.swapaxes(K, -1, -2)
    return symmetrize(P), A, L, H


def riccati(P, model, horizon):
    """Bounds after 0, 1, ..., horizon steps (list)."""
    bounds = [P]
    for step in range(horizon):
        M = predict(bounds[-1], model)
        measurement = model.measurement(step)
        bounds.append(M if measurement is None else update(M, measurement)[0])
    return bounds


class Terms(NamedTuple):
    """The horizon terms of (*): P_kappa(P_0) = P_c + exp(2 s) Psi (P_0^-1 + Gamma)^-1 Psi^T."""

    P_c: np.ndarray  # (..., n, n)
    Psi: np.ndarray  # (..., n, n), normalised to max |entry| = 1 (or 0)
    log_scale: np.ndarray  # (...), s
    Gamma: np.ndarray  # (..., n, n)


def horizon_terms(model, horizon, n, collect=None):
    """Run the Riccati recursion from P = 0 and return the terms of (*) at ``horizon``.

    ``collect``: sorted horizons at which to record the terms (returns a list); default only
    the last. The information about the initial state is ``Gamma = sum_j B_j^T B_j`` with
    ``B_j = L_S^-1 H F Psi_{j-1}`` (the innovations of the filter started at P = 0 depend on
    the initial state through ``H F Psi_{j-1}`` and have covariance ``S_j``).
    """
    batch = np.broadcast_shapes(model.F.shape[:-2], model.noise.shape[:-2])
    P_c = np.zeros(batch + (n, n))
    Psi = np.broadcast_to(np.eye(n), batch + (n, n)).copy()
    log_scale = np.zeros(batch)
    Gamma = np.zeros(batch + (n, n))
    wanted = [horizon] if collect is None else list(collect)
    found = []
    for step in range(horizon + 1):
        if step in wanted:
            found.append(Terms(P_c, Psi, log_scale, Gamma))
        if step == horizon:
            break
        M = predict(P_c, model)
        Psi = model.F @ Psi
        measurement = model.measurement(step)
        if measurement is not None:
            P_c, A, L, H = update(M, measurement)
            B = solve_lower(L, H @ Psi)
            Gamma = symmetrize(Gamma + np.exp(2.0 * log_scale)[..., None, None]
                               * (np.swapaxes(B, -1, -2) @ B))
            Psi = A @ Psi
        else:
            P_c = M
        # Keep Psi of order one; its size lives in log_scale (no underflow at long horizons).
        size = np.abs(Psi).max(axis=(-2, -1))
        size = np.where(size > 0, size, 1.0)
        Psi = Psi / size[..., None, None]
        log_scale = log_scale + np.log(size)
        shapes = (P_c.shape[:-2], Gamma.shape[:-2], Psi.shape[:-2], log_scale.shape)
        if any(shape != batch for shape in shapes):  # a batched H or R widened the batch
            batch = np.broadcast_shapes(batch, *shapes)
            P_c, Gamma, Psi = (np.broadcast_to(M, batch + (n, n)) for M in (P_c, Gamma, Psi))
            log_scale = np.broadcast_to(log_scale, batch)
    return found if collect is not None else found[0]


def propagated_bound(terms, S_inverse):
    """(*) for an initial information ``S - Gamma``: P_c + exp(2 s) Psi S^-1 Psi^T."""
    weight = np.exp(2.0 * terms.log_scale)[..., None, None]
    return symmetrize(terms.P_c + weight * (terms.Psi @ S_inverse
                                            @ np.swapaxes(terms.Psi, -1, -2)))


def broadcast_terms(terms, batch):
    n = terms.P_c.shape[-1]
    return Terms(*(np.broadcast_to(t, batch + (n, n)) for t in terms[:2]),
                  np.broadcast_to(terms.log_scale, batch),
                  np.broadcast_to(terms.Gamma, batch + (n, n)))
