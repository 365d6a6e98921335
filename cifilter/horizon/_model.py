"""The local filter's model, its scaled Riccati recursion and the horizon terms.

Validation of ``F, Q, H, R, G`` (constant or one measurement model per step), the
predict/update steps of eqs. (16), (32)-(33) of Ajgl et al. (2014), the terms of the
superposition formula ``P_kappa(P_0) = P_c + Psi (P_0^-1 + Gamma)^-1 Psi^T`` on a
power-of-two scale, and the checked unscaling of bounds and criteria. Derivation and
scaling scheme: ``docs/methods/horizon.rst``.
"""

import math
import numbers
from typing import Any, NamedTuple, Optional

import numpy as np

from .._numerics.criteria import criterion_value
from .._numerics.linalg import cho_solve, cholesky, solve_lower, symmetrize
from .._numerics.validation import as_float_array, as_matrix, check_covariances, check_psd

__all__ = [
    "MAX_PLAIN_STEPS",
    "STEADY_FROM",
    "Model",
    "PeriodicBounds",
    "SteadyState",
    "Terms",
    "as_model",
    "at_horizon",
    "broadcast_terms",
    "check_steps_available",
    "checked_bound",
    "criterion_at",
    "horizon_terms",
    "model_parts",
    "overflow_error",
    "predict",
    "propagated_bound",
    "rescale",
    "riccati_scaled",
    "stack_terms",
    "unscale",
    "update",
]


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
        noise = symmetrize(G @ Qm @ G.swapaxes(-1, -2))
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


# --------------------------------------------------------------------------- scaling
# Bounds are carried as ``P = 2^e P_hat`` with an integer exponent ``e`` per batch item, so
# that an unstable model's bound, which grows like the spectral radius to the power 2 k,
# never overflows inside the recursion. Powers of two make the rescaling exact; it is done
# only when the largest entry passes 2^RESCALE_LOG2, so moderate problems are computed
# exactly as without it. The recursion is homogeneous: with P scaled by 2^-e, the noise
# G Q G^T and R are scaled alike and the gains are unchanged.
RESCALE_LOG2 = 200
# Largest binary exponent x of a float64 m 2^x (m in [0.5, 1)).
_MAX_EXPONENT = np.finfo(float).maxexp  # 1024
_LN2 = float(np.log(2.0))


def _exponent_of_max(A, axes=(-2, -1)):
    """Binary exponent x of max |A| (max |A| = m 2^x, m in [0.5, 1)); -inf for zero."""
    size = np.abs(A).max(axis=axes)
    _, exponent = np.frexp(size)
    return np.where(size > 0, exponent.astype(float), -np.inf)


def rescale(P_hat, e):
    """Exact power-of-two rescaling of ``P_hat`` where its largest entry passes 2^RESCALE_LOG2."""
    x = _exponent_of_max(P_hat)
    d = np.where(x > RESCALE_LOG2, x, 0.0).astype(np.int64)
    if not d.any():
        return P_hat, e
    return np.ldexp(P_hat, -d[..., None, None]), e + d


def unscale(P_hat, e, what, where):
    """``2^e P_hat``, or a ValueError naming ``what`` and ``where`` if it is not representable.

    ``where`` is a function of the batch index of the first failing item that says where
    (for instance ``"at horizon 5000"``).
    """
    e = np.broadcast_to(e, P_hat.shape[:-2])
    if not e.any():
        return P_hat
    top = _exponent_of_max(P_hat) + e
    if np.any(top > _MAX_EXPONENT):
        index = np.unravel_index(int(np.argmax(top.ravel())), top.shape)
        raise overflow_error(what, float(top[index]), where(index))
    return np.ldexp(P_hat, e[..., None, None])


def overflow_error(what, log2_size, where):
    """The ValueError for ``what`` of size about ``2^log2_size`` that float64 cannot hold."""
    return ValueError(
        f"{what} {where} overflows float64: its largest entry is about "
        f"1e{log2_size * np.log10(2.0):.0f}, beyond the largest float {np.finfo(float).max:.3g} "
        "(an unstable model: the bound grows like the spectral radius of F to the power "
        "2 * horizon); ask for a shorter horizon"
    )


def _check_finite(step, horizon, **arrays):
    for name, A in arrays.items():
        if not np.isfinite(A).all():
            raise ValueError(
                f"{name} overflowed at step {step} of the horizon {horizon} (it is not finite "
                "even with the bound carried on a power-of-two scale); the model is too "
                "unstable or badly scaled for this horizon"
            )


# --------------------------------------------------------------------------- steady state
# Horizons up to STEADY_FROM steps are always computed step by step (bitwise as before the
# steady-state detection existed). Beyond, the recursion of a constant model looks for its
# steady state: a state that repeats exactly (a fixed point or a cycle of the floating-point
# recursion, see :class:`SteadyState`), after which whole cycles are skipped. A horizon above
# MAX_PLAIN_STEPS whose recursion has not repeated by then is refused with a ValueError.
STEADY_FROM = 4096
MAX_PLAIN_STEPS = 50_000


class SteadyState:
    """Brent's cycle detection on the scaled recursion's state (for a constant model).

    ``observe(step, state, log_scale, gamma_changed)`` after every step, with ``state`` the
    arrays the next step is computed from (``P_c``, ``Psi``, ``Gamma``, ``e``; ``P_hat, e``
    for :func:`riccati_scaled`), the accumulated log scale of ``Psi`` (0 if there is none)
    and whether the step changed ``Gamma``. A copy of the state is kept at steps 1, 2, 4,
    8, ...; when a later state equals the kept one bitwise, ``Gamma`` has not changed since
    it was kept and the log scale has not grown, ``(period, log-scale change per period)``
    is returned, then and at every later call.

    Why this is exact: a step's result depends on the state and on the log scale ``s`` only
    through the term ``exp(2 s - e ln 2) B^T B`` added to ``Gamma``. If ``Gamma`` absorbed
    every term of one period (it did not change), the terms at the same phase of later
    periods are no larger in magnitude (``s`` did not grow, and rounding is monotone: the
    floating-point sum of ``s`` and the same increments is monotone in ``s``), so they are
    absorbed too, and the state repeats with that period for ever. Only ``s`` keeps
    changing; skipping ``c`` periods adds ``c`` times the change of one period to it
    (instead of ``c * period`` rounded additions).
    """

    def __init__(self) -> None:
        self.kept: Optional[tuple] = None
        self.kept_step = 0
        self.kept_scale: Any = None
        self.next_keep = 1
        self.gamma_step = 0
        self.found: Optional[tuple] = None

    def observe(self, step: int, state: tuple, log_scale: Any,
                gamma_changed: bool) -> Optional[tuple]:
        """Record the state after ``step`` steps.

        Parameters
        ----------
        step : int
            Steps done so far.
        state : tuple of ndarray or int
            What the next step is computed from (compared bit for bit).
        log_scale : float or ndarray
            The accumulated log scale ``s`` (0 where there is none).
        gamma_changed : bool
            Whether this step changed ``Gamma``.

        Returns
        -------
        tuple or None
            ``(period, change of s per period)`` once the state repeats, else None.
        """
        if gamma_changed:
            self.gamma_step = step
        if self.found is not None:
            return self.found
        if (self.kept is not None and self.gamma_step <= self.kept_step
                and np.all(np.asarray(log_scale) <= self.kept_scale)
                and all(np.array_equal(a, b) for a, b in zip(state, self.kept))):
            change = np.asarray(log_scale) - self.kept_scale
            self.found = (step - self.kept_step, change if change.ndim else float(change))
            return self.found
        if step == self.next_keep:
            self.kept = tuple(np.array(a, copy=True) for a in state)
            self.kept_step = step
            self.kept_scale = np.array(log_scale, dtype=float, copy=True)
            self.next_keep *= 2
        return None


def _skip(step, horizon, wanted, found):
    """``(new step, periods skipped)``: whole periods up to the next wanted horizon."""
    period = found[0]
    target = min([w for w in wanted if w > step] + [horizon])
    periods = (target - step) // period
    return step + periods * period, periods


def _no_steady_state(horizon):
    return ValueError(
        f"horizon={horizon} is too long: the Riccati recursion of this model has not reached "
        f"a steady state (a state that repeats exactly) within {MAX_PLAIN_STEPS} steps, the "
        "most that are run one by one; ask for a horizon of at most "
        f"{MAX_PLAIN_STEPS} (typical causes: a closed loop whose slowest mode is a rotating "
        "complex pair, or an unstable mode the measurements do not stabilise)")


# --------------------------------------------------------------------------- Riccati steps
def predict(P, model, e=None):
    """Eq. (16): F P F^T + G Q G^T (with P = 2^e P_hat: for P_hat, noise scaled by 2^-e)."""
    noise = model.noise if e is None or not e.any() else np.ldexp(model.noise,
                                                                   -e[..., None, None])
    return symmetrize(model.F @ P @ model.F.swapaxes(-1, -2) + noise)


def _scaled(measurement, e):
    H, R = measurement
    return (H, R) if not e.any() else (H, np.ldexp(R, -e[..., None, None]))


def update(M, measurement):
    """Eqs. (32)-(33): optimal gain and Joseph-form update of the prior bound ``M``.

    Returns the posterior, the closed-loop factor ``I - K H`` and the whitened
    measurement matrix ``L_S^-1 H`` (``S = H M H^T + R = L_S L_S^T``).
    """
    H, R = measurement
    HM = H @ M
    S = symmetrize(HM @ H.swapaxes(-1, -2) + R)
    L = cholesky(S, "innovation covariance H M H^T + R")
    K = np.swapaxes(cho_solve(L, HM), -1, -2)
    A = np.eye(M.shape[-1]) - K @ H
    P = A @ M @ A.swapaxes(-1, -2) + K @ R @ K.swapaxes(-1, -2)
    return symmetrize(P), A, L, H


class PeriodicBounds:
    """Bounds after 0, 1, ..., ``horizon`` steps: the computed ones, then their last
    ``period`` repeated (an exact cycle of the recursion, :class:`SteadyState`)."""

    def __init__(self, bounds, period, horizon):
        self.bounds, self.period, self.horizon = bounds, period, horizon

    def __len__(self):
        return self.horizon + 1

    def __getitem__(self, k):
        computed = len(self.bounds)
        if k < 0:
            k += self.horizon + 1
        if not 0 <= k <= self.horizon:
            raise IndexError(k)
        if k < computed:
            return self.bounds[k]
        start = computed - self.period
        return self.bounds[start + (k - start) % self.period]


def riccati_scaled(P, model, horizon):
    """Bounds after 0, 1, ..., horizon steps as a sequence of ``(P_hat, e)``, ``P = 2^e P_hat``.

    A list, or for a constant model beyond :data:`STEADY_FROM` steps whose recursion repeats
    exactly, a :class:`PeriodicBounds`. Raises ValueError if a bound is not finite even on
    this scale (naming the step), or :func:`_no_steady_state`'s error.
    """
    e = np.zeros(P.shape[:-2], dtype=np.int64)
    bounds = [(P, e)]
    finder = SteadyState() if model.steps is None and horizon > STEADY_FROM else None
    step = 0
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        while step < horizon:
            P_hat, e = bounds[-1]
            e = np.broadcast_to(e, np.broadcast_shapes(e.shape, model.F.shape[:-2],
                                                       model.noise.shape[:-2]))
            M = predict(P_hat, model, e)
            measurement = model.measurement(step)
            if measurement is not None:
                e = np.broadcast_to(e, np.broadcast_shapes(e.shape, *(m.shape[:-2]
                                                                   for m in measurement)))
                M = update(M, _scaled(measurement, e))[0]
            _check_finite(step + 1, horizon, bound=M)
            bounds.append(rescale(M, e))
            step += 1
            if finder is None:
                continue
            if finder.observe(step, bounds[-1], 0.0, False) is not None:
                # The map P -> P' is autonomous: the bounds repeat exactly with the period.
                return PeriodicBounds(bounds, finder.found[0], horizon)
            if step == MAX_PLAIN_STEPS and horizon > MAX_PLAIN_STEPS:
                raise _no_steady_state(horizon)
    return bounds


class Terms(NamedTuple):
    """The horizon terms of (*), on a power-of-two scale:

    P_kappa(P_0) = 2^e (P_c + exp(2 s) Psi (P_0^-1 + Gamma)^-1 Psi^T).
    """

    P_c: np.ndarray  # (..., n, n), the bound for a known initial state, divided by 2^e
    Psi: np.ndarray  # (..., n, n), normalised to max |entry| = 1 (or 0)
    log_scale: np.ndarray  # (...), s: exp(2 s) is at most 2^(2 RESCALE_LOG2)
    Gamma: np.ndarray  # (..., n, n), not scaled
    exponent: np.ndarray  # (...), e (integers)


def _record(P_c, Psi, s, Gamma, e):
    """Terms with the relative scale s - e ln2 / 2; a large one moves into the exponent."""
    relative = s - 0.5 * _LN2 * e
    shift = np.where(relative > RESCALE_LOG2 * _LN2 / 2.0,
                     np.ceil(2.0 * relative / _LN2), 0.0).astype(np.int64)
    if shift.any():
        P_c = np.ldexp(P_c, -shift[..., None, None])
        e = e + shift
        relative = s - 0.5 * _LN2 * e
    return Terms(P_c, Psi, relative, Gamma, e)


def _single_problem(model):
    """Whether the model has no batch axes (one local filter): then the recursion runs on
    2-D arrays with scalar scales (:func:`_single_horizon_terms`)."""
    if model.F.ndim != 2 or model.noise.ndim != 2:
        return False
    entries = (model.constant,) if model.steps is None else model.steps
    return all(m is None or (m[0].ndim == 2 and m[1].ndim == 2) for m in entries)


def _single_horizon_terms(model, horizon, n, wanted):
    """:func:`horizon_terms` for one problem: the same recursion, scales and checks, with the
    exponents and log-scales as Python numbers (a single fusion pays for every call)."""
    F, FT = model.F, model.F.T
    eye = np.eye(n)
    P_c, Psi, Gamma = np.zeros((n, n)), eye.copy(), np.zeros((n, n))
    log_scale, e = 0.0, 0
    found = []
    finder = SteadyState() if model.steps is None and horizon > STEADY_FROM else None
    step = 0
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        while True:
            if step in wanted:
                found.append(_record(P_c, Psi, np.array(log_scale), Gamma,
                                     np.array(e, dtype=np.int64)))
            if step == horizon:
                break
            Gamma_before = Gamma
            noise = model.noise if e == 0 else np.ldexp(model.noise, -e)
            M = F @ P_c @ FT + noise
            M = 0.5 * (M + M.T)
            Psi = F @ Psi
            measurement = model.measurement(step)
            if measurement is not None:
                H, R = measurement
                if e:
                    R = np.ldexp(R, -e)
                HM = H @ M
                S = HM @ H.T + R
                L = cholesky(0.5 * (S + S.T), "innovation covariance H M H^T + R")
                K = cho_solve(L, HM).T
                A = eye - K @ H
                P_c = A @ M @ A.T + K @ R @ K.T
                P_c = 0.5 * (P_c + P_c.T)
                B = solve_lower(L, H @ Psi)
                BtB = B.T @ B
                weight = math.exp(2.0 * log_scale - _LN2 * e)
                term = weight * BtB if math.isfinite(weight) else np.where(
                    BtB == 0.0, 0.0, weight * BtB)
                Gamma = Gamma + term
                Gamma = 0.5 * (Gamma + Gamma.T)
                Psi = A @ Psi
            else:
                P_c = M
            size = float(np.abs(Psi).max())
            if size > 0:
                Psi = Psi / size
                log_scale += math.log(size)
            top = float(np.abs(P_c).max())
            if top > 0:
                exponent = math.frexp(top)[1]
                if exponent > RESCALE_LOG2:
                    P_c = np.ldexp(P_c, -exponent)
                    e += exponent
            if not math.isfinite(float(P_c.sum()) + float(Gamma.sum()) + float(Psi.sum())):
                _check_finite(step + 1, horizon, **{"the bound P_c": P_c,
                                                    "the information Gamma": Gamma,
                                                    "the transition Psi": Psi})
            step += 1
            if finder is not None:
                step, log_scale = _watch(finder, step, (P_c, Psi, Gamma, e), log_scale,
                                         not np.array_equal(Gamma, Gamma_before), horizon,
                                         wanted)
    return found


def horizon_terms(model, horizon, n, collect=None):
    """Run the Riccati recursion from P = 0 and return the terms of (*) at ``horizon``.

    ``collect``: sorted horizons at which to record the terms (returns a list); default only
    the last. The information about the initial state is ``Gamma = sum_j B_j^T B_j`` with
    ``B_j = L_S^-1 H F Psi_{j-1}`` (the innovations of the filter started at P = 0 depend on
    the initial state through ``H F Psi_{j-1}`` and have covariance ``S_j``).

    ``P_c`` is carried as ``2^e P_c_hat`` (noise and ``R`` scaled by ``2^-e`` in the
    recursion, exact and gain-preserving) and ``Psi`` as ``exp(s) Psi_hat``, so neither
    overflows for unstable models; ValueError names the step if ``Gamma`` (which is not
    scaled) or a scaled term still overflows.
    """
    wanted = [horizon] if collect is None else list(collect)
    if _single_problem(model):
        found = _single_horizon_terms(model, horizon, n, wanted)
        return found if collect is not None else found[0]
    batch = np.broadcast_shapes(model.F.shape[:-2], model.noise.shape[:-2])
    P_c = np.zeros(batch + (n, n))
    Psi = np.broadcast_to(np.eye(n), batch + (n, n)).copy()
    log_scale = np.zeros(batch)  # s of Psi = exp(s) Psi_hat (absolute)
    e = np.zeros(batch, dtype=np.int64)  # P_c = 2^e P_c_hat
    Gamma = np.zeros(batch + (n, n))
    found = []
    finder = SteadyState() if model.steps is None and horizon > STEADY_FROM else None
    step = 0
    with np.errstate(over="ignore", invalid="ignore", under="ignore"):
        while True:
            if step in wanted:
                found.append(_record(P_c, Psi, log_scale, Gamma, e))
            if step == horizon:
                break
            Gamma_before = Gamma
            M = predict(P_c, model, e)
            Psi = model.F @ Psi
            measurement = model.measurement(step)
            if measurement is not None:
                widened = np.broadcast_shapes(e.shape, *(m.shape[:-2] for m in measurement))
                e = np.broadcast_to(e, widened)
                P_c, A, L, H = update(M, _scaled(measurement, e))
                B = solve_lower(L, H @ Psi)
                BtB = B.swapaxes(-1, -2) @ B
                # Gamma is not scaled: the whitening by L = 2^(-e/2) L_true costs 2^-e.
                weight = np.exp(2.0 * log_scale - _LN2 * e)[..., None, None]
                Gamma = symmetrize(Gamma + np.where(BtB == 0.0, 0.0, weight * BtB))
                Psi = A @ Psi
            else:
                P_c = M
            # Keep Psi of order one; its size lives in log_scale (no underflow at long
            # horizons), and P_c below 2^RESCALE_LOG2 (its size lives in e).
            size = np.abs(Psi).max(axis=(-2, -1))
            size = np.where(size > 0, size, 1.0)
            Psi = Psi / size[..., None, None]
            log_scale = log_scale + np.log(size)
            P_c, e = rescale(P_c, e)
            _check_finite(step + 1, horizon, **{"the bound P_c": P_c,
                                                "the information Gamma": Gamma,
                                                "the transition Psi": Psi})
            shapes = (P_c.shape[:-2], Gamma.shape[:-2], Psi.shape[:-2], log_scale.shape,
                      e.shape)
            if any(shape != batch for shape in shapes):  # a batched H or R widened the batch
                batch = np.broadcast_shapes(batch, *shapes)
                P_c, Gamma, Psi = (np.broadcast_to(M, batch + (n, n))
                                   for M in (P_c, Gamma, Psi))
                log_scale = np.broadcast_to(log_scale, batch)
                e = np.broadcast_to(e, batch)
            step += 1
            if finder is not None:
                step, log_scale = _watch(finder, step, (P_c, Psi, Gamma, e), log_scale,
                                         not np.array_equal(Gamma, Gamma_before), horizon,
                                         wanted)
    return found if collect is not None else found[0]


def _watch(finder, step, state, log_scale, gamma_changed, horizon, wanted):
    """The steady-cycle watch after a step of the recursion: ``(step, log_scale)``, moved on
    by whole periods once the state repeats; a horizon beyond ``MAX_PLAIN_STEPS`` whose
    recursion has not repeated by then is refused."""
    if finder.observe(step, state, log_scale, gamma_changed) is not None:
        step, periods = _skip(step, horizon, wanted, finder.found)
        return step, log_scale + periods * finder.found[1]
    if step == MAX_PLAIN_STEPS and horizon > MAX_PLAIN_STEPS:
        raise _no_steady_state(horizon)
    return step, log_scale


def propagated_bound(terms, S_inverse):
    """(*) for an initial information ``S - Gamma``, divided by ``2^e``:
    ``P_c + exp(2 s) Psi S^-1 Psi^T`` (multiply by ``2^terms.exponent`` with :func:`unscale`).
    """
    weight = np.exp(2.0 * terms.log_scale)[..., None, None]
    return symmetrize(terms.P_c + weight * (terms.Psi @ S_inverse
                                            @ terms.Psi.swapaxes(-1, -2)))


def broadcast_terms(terms, batch):
    n = terms.P_c.shape[-1]
    return Terms(*(np.broadcast_to(t, batch + (n, n)) for t in terms[:2]),
                  np.broadcast_to(terms.log_scale, batch),
                  np.broadcast_to(terms.Gamma, batch + (n, n)),
                  np.broadcast_to(terms.exponent, batch))


def stack_terms(terms_list):
    """The terms of several horizons stacked along a new last batch axis."""
    batch = np.broadcast_shapes(*(t.log_scale.shape for t in terms_list),
                                *(t.P_c.shape[:-2] for t in terms_list))
    terms_list = [broadcast_terms(t, batch) for t in terms_list]
    return Terms(*(np.stack(parts, axis=len(batch)) for parts in zip(*terms_list)))


def model_parts(model):
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


# --------------------------------------------------------------------------- results
def at_horizon(horizons, weights=None):
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


def criterion_at(P_hat, exponent, kind, W, where):
    """The criterion of ``2^e P_hat`` without forming it (ValueError if not representable).

    ``det`` is ``exp(log det)`` from a Cholesky factor of ``P_hat`` plus ``n e ln 2``.
    """
    exponent = np.broadcast_to(exponent, P_hat.shape[:-2])
    if kind == "det":
        n = P_hat.shape[-1]
        L = cholesky(P_hat, "propagated bound")
        log_det = (2.0 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)
                   + n * _LN2 * exponent)
        bad = (log_det > np.log(np.finfo(float).max)) | (log_det < np.log(np.finfo(float).tiny))
        if bad.any():
            index = np.unravel_index(int(np.argmax(bad.ravel())), bad.shape)
            raise ValueError(
                f"det of the propagated bound {where(index)} is not representable in float64: "
                f"log det = {float(log_det[index]):.6g}; ask for a shorter horizon")
        return np.exp(log_det)
    value = criterion_value(P_hat, kind, W)
    return unscale(value[..., None, None], exponent, "the criterion of the propagated bound",
                   where)[..., 0, 0]


def checked_bound(P_hat, exponent, where):
    """``2^e P_hat``: finite (ValueError otherwise) and positive definite (else the error of
    :func:`cifilter._numerics.linalg.cholesky` for the first failing item, naming the horizon).

    The condition number is not limited: an unstable model's bound legitimately exceeds
    the conditioning contract of the inputs while it is still positive definite.
    """
    P = unscale(P_hat, exponent, "the propagated bound", where)
    try:
        np.linalg.cholesky(P)
    except np.linalg.LinAlgError:
        for index in np.ndindex(P.shape[:-2]):  # failure path: the first failing item
            cholesky(P[index], f"the propagated bound {where(index)}")
    return P
