"""Batched minimisers for the convex weight problems of Covariance Intersection.

Both solvers run one Newton iteration for the whole batch at a time (vectorised over
the batch; the Python loop is over iterations only) and report, per problem, the
number of iterations and whether the tolerance was met. Optima on the boundary are
returned exactly (weights of exactly 0 or 1), not approached asymptotically.
"""

import math

import numpy as np

__all__ = [
    "INTERIOR_MIN_COUNT",
    "frank_wolfe_gap",
    "interval_gap",
    "minimize_convex_interval",
    "minimize_convex_scalar",
    "minimize_convex_segment",
    "minimize_convex_simplex",
]

# Relative cut-off of the pseudo-inverse of the normalised KKT system: directions whose
# curvature is at the rounding level of the Hessian (exact ties) get no step, curvature
# above it (nearly tied inputs, ill-conditioned ones) is resolved.
_RCOND = 1e-13


def frank_wolfe_gap(w, gradient):
    """``sum_i w_i g_i - min_i g_i`` (..., ): a certified bound on ``f(w) - min f``.

    For ``f`` convex on the probability simplex with gradient ``g`` at ``w`` (..., N),
    ``f(v) >= f(w) + g . (v - w)`` and the right side is smallest at the vertex of the
    smallest ``g_i``. Never negative (rounding is cut at zero).
    """
    along = np.einsum("...i,...i->...", w, gradient)
    return np.maximum(along - gradient.min(axis=-1), 0.0)


def interval_gap(t, slope):
    """:func:`frank_wolfe_gap` on the segment ``(t, 1 - t)`` from ``f'(t)``.

    ``t max(f', 0) + (1 - t) max(-f', 0)``, written with ``abs`` so that it serves numpy
    arrays and Python floats alike.
    """
    return 0.5 * (abs(slope) + (2.0 * t - 1.0) * slope)


def minimize_convex_interval(derivatives, size, *, scale, xtol=1e-13, max_iter=100):
    """Minimise ``size`` convex functions of one variable on [0, 1].

    Parameters
    ----------
    derivatives : callable
        ``derivatives(w, index) -> (f', f'')`` for the problems ``index`` (an integer
        array) at the points ``w`` (same length); ``f'`` must be non-decreasing in ``w``.
        Only unfinished problems are evaluated, so the cost falls as problems converge.
    size : int
        Number of problems.
    scale : ndarray, shape (size,)
        Typical magnitude of ``f`` per problem; ``|f'| <= 1e-13 * scale`` at both ends
        means ``f`` is constant and ``w = 1/2`` is returned.
    xtol : float
        Stop when the Newton step or the bracket is below ``xtol``.
    max_iter : int
        Iteration limit.

    Returns
    -------
    w, iterations, converged : ndarray, shape (size,)
        Minimisers in [0, 1], iterations used and convergence flags.

    Notes
    -----
    If ``f'(0) >= 0`` the minimum is at 0 exactly, if ``f'(1) <= 0`` at 1 exactly;
    otherwise the root of ``f'`` is bracketed in (0, 1) and found by Newton's method,
    falling back to bisection whenever a Newton step leaves the bracket.
    """
    everything = np.arange(size)
    g0, _ = derivatives(np.zeros(size), everything)
    g1, _ = derivatives(np.ones(size), everything)
    tiny = 1e-13 * scale
    flat = (np.abs(g0) <= tiny) & (np.abs(g1) <= tiny)
    at_zero = ~flat & (g0 >= 0)
    at_one = ~flat & ~at_zero & (g1 <= 0)
    w = np.where(at_zero, 0.0, np.where(at_one, 1.0, 0.5))
    done = flat | at_zero | at_one
    iterations = np.zeros(size, dtype=int)
    lo, hi = np.zeros(size), np.ones(size)
    for _ in range(max_iter):
        index = np.flatnonzero(~done)
        if index.size == 0:
            break
        wi, lo_i, hi_i = w[index], lo[index], hi[index]
        g, h = derivatives(wi, index)
        lo_i = np.where(g < 0, wi, lo_i)
        hi_i = np.where(g > 0, wi, hi_i)
        with np.errstate(divide="ignore", invalid="ignore"):
            step = -g / h
        newton = wi + step
        # A Newton step below xtol means w is the root to working precision; testing this
        # before the bracket avoids bisecting away from a root that sits on a bracket end.
        settled = (np.abs(step) < xtol) | (g == 0)
        inside = (newton > lo_i) & (newton < hi_i) & np.isfinite(newton)
        w_new = np.where(inside, newton, np.where(settled, wi, 0.5 * (lo_i + hi_i)))
        w[index], lo[index], hi[index] = w_new, lo_i, hi_i
        iterations[index] += 1
        done[index] = settled | (hi_i - lo_i < xtol)
    return w, iterations, done


def minimize_convex_scalar(derivative, *, scale, xtol=1e-13, max_iter=100):
    """:func:`minimize_convex_interval` for one problem, in Python floats.

    The same iteration (the same end tests, bracket, Newton and bisection steps and stopping
    rules), without the batch bookkeeping that dominates the cost of a single problem.

    Parameters
    ----------
    derivative : callable
        ``derivative(w) -> (f', f'')`` at a float ``w`` in [0, 1]; ``f'`` non-decreasing.
    scale : float
        Typical magnitude of ``f`` (the flatness test, as in :func:`minimize_convex_interval`).
    xtol : float
        Stop when the Newton step or the bracket is below ``xtol``.
    max_iter : int
        Iteration limit.

    Returns
    -------
    w : float
        The minimiser in [0, 1] (exactly 0 or 1 at an end).
    iterations : int
    converged : bool
    """
    g0, _ = derivative(0.0)
    g1, _ = derivative(1.0)
    tiny = 1e-13 * scale
    if abs(g0) <= tiny and abs(g1) <= tiny:
        return 0.5, 0, True
    if g0 >= 0:
        return 0.0, 0, True
    if g1 <= 0:
        return 1.0, 0, True
    w, lo, hi = 0.5, 0.0, 1.0
    for iteration in range(1, max_iter + 1):
        g, h = derivative(w)
        if g < 0:
            lo = w
        elif g > 0:
            hi = w
        if h != 0:
            step = -g / h
        else:  # as numpy's -g / 0: an infinite step (bisection) or, for g = 0, none
            step = math.copysign(math.inf, -g) if g != 0 else math.nan
        newton = w + step
        settled = abs(step) < xtol or g == 0
        if lo < newton < hi and math.isfinite(newton):
            w = newton
        elif not settled:
            w = 0.5 * (lo + hi)
        if settled or hi - lo < xtol:
            return w, iteration, True
    return w, max_iter, False


def minimize_convex_segment(evaluate, size, *, scale, max_iter=100):
    """Minimise ``size`` convex functions of two weights on the segment ``w = (t, 1 - t)``.

    The simplex of two estimates is a segment: ``f'(t) = g_1 - g_2`` and
    ``f''(t) = H_11 - 2 H_12 + H_22`` from the gradient and Hessian in ``w``, minimised by
    :func:`minimize_convex_interval` (one problem: :func:`minimize_convex_scalar`, the same
    iteration without the batch bookkeeping).

    Parameters
    ----------
    evaluate : callable
        ``evaluate(w, index) -> (f, g, H)`` for the problems ``index`` at ``w``
        (len(index), 2): gradient (len(index), 2) and Hessian (len(index), 2, 2).
    size : int
        Number of problems.
    scale : ndarray, shape (size,)
        Typical magnitude of ``f`` (the flatness test of :func:`minimize_convex_interval`).
    max_iter : int
        Iteration limit.

    Returns
    -------
    w : ndarray, shape (size, 2)
        Minimisers, exactly ``(1, 0)`` or ``(0, 1)`` at an end.
    iterations, converged : ndarray, shape (size,)
    """
    def derivatives(t, index):
        _, g, H = evaluate(np.stack([t, 1.0 - t], axis=-1), index)
        return g[:, 0] - g[:, 1], H[:, 0, 0] - 2.0 * H[:, 0, 1] + H[:, 1, 1]

    if size == 1:
        only = np.zeros(1, dtype=int)

        def derivative(t):
            slope, curvature = derivatives(np.array([t]), only)
            return float(slope[0]), float(curvature[0])

        t, iterations, converged = minimize_convex_scalar(
            derivative, scale=float(scale[0]), max_iter=max_iter)
        t, iterations, converged = np.array([t]), np.array([iterations]), np.array([converged])
    else:
        t, iterations, converged = minimize_convex_interval(derivatives, size, scale=scale,
                                                            max_iter=max_iter)
    return np.stack([t, 1.0 - t], axis=-1), iterations, converged


def _towards_best_vertices(where, w, g, g_scale, d, slope, free):
    """A Frank-Wolfe direction for the problems ``where`` (the rest keep ``d``).

    Every vertex within rounding of the smallest gradient gets the same share, so that
    equal inputs keep equal weights; ``g.d = min g - w.g < 0``, a feasible descent
    direction. Returns the new ``d``, its slope and the free set with those vertices.
    """
    best = g <= g.min(axis=-1, keepdims=True) + 1e-12 * g_scale[..., None]
    target = best / best.sum(axis=-1, keepdims=True)
    d = np.where(where[..., None], target - w, d)
    slope = np.where(where, np.einsum("...i,...i->...", g, d), slope)
    return d, slope, free | (where[..., None] & best)


# The interior-point phase runs for this many weights and more. Below it the active-set
# method alone takes about as many iterations as the two phases (its count grows with the
# changes of face, about N from the uniform start: measured on CI and partial CI of random
# 3x3 estimates, medians 9 against 10 at N = 8, 17 against 11 at N = 16; see
# docs/methods/simplex_solver.rst), and it keeps tied weights exactly equal.
INTERIOR_MIN_COUNT = 12
# The interior-point phase hands over to the active-set phase once the Frank-Wolfe gap of
# its iterate is at most this, relative to the rounding scale of f: by then every weight is
# either well inside (w_i ~ 1/support) or far below the others (w_i ~ gap / (N (g_i - mu))),
# and the face can be read off the iterate.
_CROSSOVER = 1e-8
# Fraction of the step to the boundary of the positive orthant taken at most (w and z).
_TO_BOUNDARY = 0.995
# Iterations of the interior-point phase at most (measured: both phases together take 10 to
# 17 on CI and partial CI of 30 to 1000 random estimates); past it the active-set phase
# goes on from its iterate.
_INTERIOR_MAX_ITER = 80


class _Rows:
    """The caller's ``evaluate`` and ``objective`` on a flat batch ``(size, count)``.

    With ``subset`` the callables take the rows ``index`` and only the problems asked for
    are evaluated (the others get placeholders: f = 0, g = 0, H = I); without it they take
    the whole batch in its own ``shape``.
    """

    def __init__(self, evaluate, objective, count, shape, subset):
        self._evaluate, self._objective = evaluate, objective
        self.count, self.shape, self.subset = count, tuple(shape), subset
        self.size = int(np.prod(self.shape, dtype=int))

    def evaluate(self, w, rows):
        count, size = self.count, self.size
        if not self.subset:
            f, g, H = self._evaluate(w.reshape(self.shape + (count,)))
            return (np.reshape(f, (size,)), np.reshape(g, (size, count)),
                    np.reshape(H, (size, count, count)))
        f, g = np.zeros(size), np.zeros((size, count))
        H = np.broadcast_to(np.eye(count), (size, count, count)).copy()
        index = np.flatnonzero(rows)
        if index.size:
            f[index], g[index], H[index] = self._evaluate(w[index], index)
        return f, g, H

    def objective(self, w, rows):
        if not self.subset:
            return np.reshape(self._objective(w.reshape(self.shape + (self.count,))),
                              (self.size,))
        f = np.zeros(self.size)
        index = np.flatnonzero(rows)
        if index.size:
            f[index] = self._objective(w[index], index)
        return f


def minimize_convex_simplex(evaluate, objective, count, shape, *, xtol=1e-12, max_iter=200,
                            gtol=0.0, absolute_gap=False, subset=False):
    """Minimise smooth convex functions over the probability simplex, batched.

    Parameters
    ----------
    evaluate : callable
        ``evaluate(w) -> (f, g, H)`` with ``w`` of shape ``shape + (count,)``, ``f`` of
        ``shape``, gradient ``g`` of ``shape + (count,)`` and Hessian ``H`` of
        ``shape + (count, count)``.
    objective : callable
        ``objective(w) -> f`` (cheaper than ``evaluate``; used by the line searches).
    count : int
        Number of weights N.
    shape : tuple
        Batch shape.
    xtol : float
        Stop when the Newton step on the current face is below ``xtol`` and no weight
        fixed at zero should be released.
    max_iter : int
        Iteration limit (both phases together; see Notes).
    gtol : float, optional
        Also stop a problem as soon as its Frank-Wolfe gap ``sum_i w_i g_i - min_i g_i``,
        a certified bound on ``f(w) - min f``, is at most ``gtol * |f|`` (or ``gtol`` with
        ``absolute_gap``). This ends problems whose optimum is not unique (tied inputs:
        the Hessian is singular along the ties and the steps need not shrink) as soon as
        the objective is optimal. 0 (default) disables the test.
    absolute_gap : bool, optional
        Compare the gap with ``gtol`` itself rather than ``gtol * |f|`` (for objectives
        such as a log-determinant whose value may be near zero).
    subset : bool, optional
        ``shape`` is one axis and ``evaluate(w, index)``, ``objective(w, index)`` take the
        rows ``index`` (an integer array) of the problems: only unfinished problems are
        evaluated, so a batch costs what its problems cost, and one slow problem does
        not make every other one pay for its iterations.

    Returns
    -------
    w, iterations, converged : ndarray
        Minimisers (exact zeros where the optimum lies on a face), iterations used and
        convergence flags. A problem whose line search finds no decrease above the
        rounding level of ``f`` stops there, unconverged unless a test above holds: the
        caller should certify such a point (for instance by its gap).

    Notes
    -----
    Two phases; derivation and measurements in ``docs/methods/simplex_solver.rst``.

    *Interior point* (only for ``count >= INTERIOR_MIN_COUNT``): a primal-dual
    interior-point method on ``min f(w)``, ``sum_i w_i = 1``, ``w >= 0`` from the uniform
    weights, with duals ``z = g - mu`` and a barrier parameter chosen by Mehrotra's rule;
    each iteration solves one N x N system and backtracks on the barrier function. Its
    iteration count depends on the accuracy asked for, not on N (it moves every weight at
    once). It stops when the Frank-Wolfe gap of its iterate is ``_CROSSOVER`` relative to
    ``f`` (or earlier where a line search cannot decrease the barrier function above the
    rounding level), and the face is read off the iterate: a weight is kept where
    ``w_i max_j |g_j| >= g_i - min_j g_j``, the others are set to exactly zero.

    *Active set*, from the uniform weights (fewer estimates) or from that face: weights
    fixed at zero are excluded; on the face of the free ones, the equality-constrained
    Newton step solves the KKT system ``[H_FF 1; 1^T 0] [d; nu] = [-g_F; 0]``. A step that
    would make a weight negative is cut at the boundary and that weight is fixed at exactly
    zero. When the step on the face vanishes, ``-nu`` is the common gradient level ``mu``
    of the free weights; a fixed weight whose gradient is below ``mu`` would decrease ``f``
    and is released. The KKT system is solved by a pseudo-inverse (on the free weights
    only), so that directions in which ``f`` is flat (equal inputs) get no step and the
    weights keep their start there (uniform: tied inputs keep exactly equal weights when
    the active-set phase runs alone; after the interior-point phase, equal to rounding).
    At the result the KKT conditions of the simplex hold: ``g_i = mu`` for ``w_i > 0`` and
    ``g_i >= mu`` for ``w_i = 0``. Each problem's iterations of both phases count against
    ``max_iter``; convergence is decided by the active-set phase alone (the certified gap
    where ``gtol > 0``).
    """
    rows = _Rows(evaluate, objective, count, shape, subset)
    w = np.full((rows.size, count), 1.0 / count)
    free = np.ones((rows.size, count), dtype=bool)
    iterations = np.zeros(rows.size, dtype=int)
    interior = count >= INTERIOR_MIN_COUNT
    if interior and max_iter > 0:
        w, free, iterations = _interior_point(rows, max_iter, gtol, absolute_gap)
    w, iterations, done = _active_set(rows, w, free, iterations, xtol=xtol,
                                      max_iter=max_iter, gtol=gtol,
                                      absolute_gap=absolute_gap, compress=interior)
    shape = tuple(shape)
    return w.reshape(shape + (count,)), iterations.reshape(shape), done.reshape(shape)


def _to_boundary(x, dx):
    """The largest ``t`` with ``x + t dx >= 0`` (per row; inf where ``dx >= 0``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(dx < 0.0, x / -dx, np.inf)
    return ratio.min(axis=-1)


def _interior_point(rows, max_iter, gtol, absolute_gap):
    """Phase 1 of :func:`minimize_convex_simplex`: a primal-dual interior-point method.

    Minimises ``f(w)`` subject to ``1^T w = 1``, ``w >= 0`` through the perturbed KKT
    conditions ``g - nu 1 - z = 0``, ``w_i z_i = tau``, ``w, z > 0``. The Newton step for
    them, after eliminating ``dz``, is

        (H + Z W^-1) dw - 1 dnu = -(g - nu 1) + tau W^-1 e,   1^T dw = 0,

    solved (Jacobi-scaled) for the three right-hand sides ``-(g - nu)``, ``1/w`` and ``1``
    at once, so that the step is affine in ``tau``: the affine (``tau = 0``) step gives
    Mehrotra's ``sigma = (mu_aff / mu)^3`` and ``tau = sigma mu``, ``mu = w^T z / N``. With
    ``H`` positive semidefinite the step is a descent direction of the barrier function
    ``phi(w) = f(w) - tau sum_i log w_i`` (``(g - tau/w)^T dw = -dw^T (H + Z W^-1) dw``):
    backtracking on ``phi`` from 0.995 of the step to the boundary. Returns the crossover
    point (weights with exact zeros off the face read from the iterate), the free set and
    the iterations per problem.
    """
    count, size = rows.count, rows.size
    tiny = np.finfo(float).tiny
    w = np.full((size, count), 1.0 / count)
    z = np.ones((size, count))
    nu = np.zeros(size)
    free = np.ones((size, count), dtype=bool)
    iterations = np.zeros(size, dtype=int)
    running = np.ones(size, dtype=bool)
    started = False
    eye = np.eye(count, dtype=bool)
    for _ in range(min(max_iter, _INTERIOR_MAX_ITER) + 1):
        if not running.any():
            break
        f_all, g_all, H_all = rows.evaluate(w, running)
        index = np.flatnonzero(running)
        f, g, H = f_all[index], g_all[index], H_all[index]
        wi = w[index]
        g_scale = np.abs(g).max(axis=-1) + tiny
        f_scale = np.maximum(np.abs(f), 1.0) if absolute_gap else np.abs(f)
        g_min = g.min(axis=-1)
        gap = frank_wolfe_gap(wi, g)
        if not started:
            started = True
            # The uniform start satisfies the KKT conditions (every gradient equal) or is
            # certified: nothing for the interior phase to do (the active set confirms it).
            spread = g.max(axis=-1) - g_min
            settled = spread <= 1e-12 * g_scale
            if gtol > 0.0:
                settled |= gap <= gtol * (1.0 if absolute_gap else np.abs(f))
            settled |= ~np.isfinite(g).all(axis=-1)
            running[index[settled]] = False
            # duals z = g - nu > 0 within a factor 2 of each other: a well-centred start
            nu[index] = g_min - np.maximum(spread, 1e-3 * g_scale)
            z[index] = g - nu[index, None]
            keep = ~settled
            index, f, g, H, wi = index[keep], f[keep], g[keep], H[keep], wi[keep]
            g_scale, f_scale, g_min, gap = g_scale[keep], f_scale[keep], g_min[keep], gap[keep]
            if index.size == 0:
                break
        zi, nui = z[index], nu[index]
        # The face is read off the iterate once the gap is small, or where the last
        # iteration was the budget: the active-set phase finishes (and certifies) from it.
        out_of_budget = iterations[index] >= min(max_iter, _INTERIOR_MAX_ITER)
        crossing = (gap <= _CROSSOVER * f_scale) | out_of_budget
        crossing |= ~(np.isfinite(f) & np.isfinite(g).all(axis=-1) & np.isfinite(H).all(
            axis=(-2, -1)))
        mu = np.einsum("ki,ki->k", wi, zi) / count
        diagonal = np.einsum("kii->ki", H) + zi / wi
        ok = (diagonal > 0.0).all(axis=-1) & np.isfinite(diagonal).all(axis=-1) & ~crossing
        scale = np.where(ok[:, None], 1.0 / np.sqrt(np.where(ok[:, None], diagonal, 1.0)), 1.0)
        D = np.where(eye, np.where(ok[:, None], diagonal, 1.0)[:, :, None], H)
        D = np.where(ok[:, None, None], D, np.eye(count))
        D = scale[:, :, None] * D * scale[:, None, :]
        rhs = np.stack([-(g - nui[:, None]), 1.0 / wi, np.ones_like(wi)], axis=-1)
        with np.errstate(all="ignore"):
            try:
                solution = np.linalg.solve(D, scale[:, :, None] * rhs)
            except np.linalg.LinAlgError:  # a singular system somewhere: one by one
                solution = np.stack([_solve_or_nan(Dk, rk) for Dk, rk in
                                     zip(D, scale[:, :, None] * rhs)])
            solution = scale[:, :, None] * solution
            a0, a1, b = solution[..., 0], solution[..., 1], solution[..., 2]
            dw, dnu, dz = _interior_step(a0, a1, b, wi, zi, np.zeros(index.size))
            t_w = np.minimum(1.0, _to_boundary(wi, dw))
            t_z = np.minimum(1.0, _to_boundary(zi, dz))
            mu_affine = np.einsum("ki,ki->k", wi + t_w[:, None] * dw,
                                  zi + t_z[:, None] * dz) / count
            sigma = np.clip((mu_affine / mu) ** 3, 1e-6, 0.5)
            sigma = np.where(np.isfinite(sigma), sigma, 0.5)
            tau = sigma * mu
            dw, dnu, dz = _interior_step(a0, a1, b, wi, zi, tau)
            slope = np.einsum("ki,ki->k", g - tau[:, None] / wi, dw)
        # not a descent direction of the barrier function (H not numerically positive
        # semidefinite, a singular system): the face is read off here
        crossing |= ~(ok & (slope < 0.0) & np.isfinite(slope) & np.isfinite(dw).all(axis=-1)
                      & np.isfinite(dz).all(axis=-1) & np.isfinite(dnu))
        t = np.minimum(1.0, _TO_BOUNDARY * _to_boundary(wi, dw))
        phi = f - tau * np.log(wi).sum(axis=-1)
        trying = ~crossing
        for _ in range(50):  # Armijo backtracking on the barrier function, batched
            if not trying.any():
                break
            trial = np.where(trying[:, None], wi + t[:, None] * dw, wi)
            trial_all = w.copy()
            trial_all[index] = trial
            search = np.zeros(size, dtype=bool)
            search[index[trying]] = True
            with np.errstate(all="ignore"):
                f_trial = rows.objective(trial_all, search)[index]
                phi_trial = f_trial - tau * np.log(trial).sum(axis=-1)
            accepted = phi_trial <= phi + 1e-4 * t * slope
            trying = trying & ~accepted
            t = np.where(trying, 0.5 * t, t)
        # no decrease of the barrier function above rounding: as far as this phase goes
        crossing |= trying
        # (the evaluation that ends the phase at its budget is not an iteration: it only
        # reads the face off the last iterate)
        iterations[index] += ~out_of_budget
        moving = ~crossing
        new_w = np.where(moving[:, None], wi + t[:, None] * dw, wi)
        new_w = new_w / new_w.sum(axis=-1, keepdims=True)
        t_dual = np.minimum(1.0, _TO_BOUNDARY * _to_boundary(zi, dz))
        new_z = zi + t_dual[:, None] * dz
        # keep W^-1 Z within 1e10 of its central value tau / w^2 (as IPOPT does)
        new_z = np.clip(new_z, tau[:, None] / (1e10 * new_w), 1e10 * tau[:, None] / new_w)
        w[index] = new_w
        z[index] = np.where(moving[:, None], new_z, zi)
        nu[index] = np.where(moving, nui + t_dual * dnu, nui)
        if crossing.any():
            crossed = index[crossing]
            w[crossed], free[crossed] = _cross_over(
                rows, w, crossed, f[crossing], g[crossing], gap[crossing], f_scale[crossing])
            running[crossed] = False
    return w, free, iterations


# Crossover thresholds tried in turn: a weight is kept where w_i max_j |g_j| is at least
# this times g_i - min_j g_j (a smaller factor keeps more weights).
_KEEP_FACTORS = (1.0, 1e-4, 1e-8)


def _cross_over(rows, weights, index, f, g, gap, f_scale):
    """The face read off the interior iterates ``weights[index]`` of the problems ``index``
    (``weights`` is the whole batch: without ``subset`` every row is evaluated).

    Near the central path ``w_i (g_i - mu) = tau``, so each weight is either large against
    the excess of its gradient over the smallest or small against it; the small ones are
    set to exactly zero. The face is accepted only where the objective there is at most
    ``f(w) + gap`` (plus rounding): by convexity no point is below ``f(w) - gap``, so a
    face that loses more than that dropped weights the optimum needs (objectives that
    change steeply next to the boundary, such as partial CI with a small ``rho``). Then a
    smaller threshold keeps more weights, and if none is accepted every weight stays free
    (the active-set phase starts from the interior iterate). Returns weights and free sets.
    """
    w = weights[index]
    g_scale = np.abs(g).max(axis=-1) + np.finfo(float).tiny
    excess = g - g.min(axis=-1, keepdims=True)
    result, free = w.copy(), np.ones(w.shape, dtype=bool)
    pending = np.ones(len(index), dtype=bool)
    allowed = f + gap + 64.0 * np.finfo(float).eps * f_scale
    for factor in _KEEP_FACTORS:
        keep = w * g_scale[:, None] >= factor * excess
        kept = np.where(keep, w, 0.0)
        kept = kept / kept.sum(axis=-1, keepdims=True)
        trial = weights.copy()
        trial[index] = kept
        asked = np.zeros(rows.size, dtype=bool)
        asked[index[pending]] = True
        with np.errstate(all="ignore"):
            f_face = rows.objective(trial, asked)[index]
        accepted = pending & (f_face <= allowed)
        result[accepted], free[accepted] = kept[accepted], keep[accepted]
        pending &= ~accepted
        if not pending.any():
            break
    return result, free


def _interior_step(a0, a1, b, w, z, tau):
    """The interior-point step ``(dw, dnu, dz)`` for the barrier parameters ``tau`` from the
    solutions ``a0, a1, b`` of the scaled system for ``-(g - nu)``, ``1/w`` and ``1``."""
    a = a0 + tau[:, None] * a1
    dnu = -a.sum(axis=-1) / b.sum(axis=-1)  # makes 1^T dw = 0
    dw = a + dnu[:, None] * b
    dw = dw - dw.sum(axis=-1, keepdims=True) / w.shape[-1]  # (to rounding)
    dz = tau[:, None] / w - z - z / w * dw
    return dw, dnu, dz


def _solve_or_nan(D, rhs):
    try:
        return np.linalg.solve(D, rhs)
    except np.linalg.LinAlgError:
        return np.full(rhs.shape, np.nan)


def _face_newton(H, g, free, compress):
    """The Newton step on the face of the free weights and the level ``mu`` (see
    :func:`minimize_convex_simplex`), from the pseudo-inverse of the normalised KKT system.

    With ``compress`` the system is formed on the free weights only (padded to the largest
    free set of the batch with identity rows, which the fixed weights get in the full
    system too): the same step at a cost that does not grow with the fixed weights.
    """
    count = g.shape[-1]
    # Normalise the curvature so that the constraint rows and the Hessian have the same
    # scale; the pseudo-inverse then drops flat directions (sum_i d_i I_i = 0, along
    # which f is constant) instead of amplifying rounding noise along them, so the
    # weights stay where they started in those directions (uniform: permutation-fair).
    diagonal = np.where(free, np.diagonal(H, axis1=-2, axis2=-1), 0.0)
    curvature = np.maximum(diagonal.max(axis=-1), np.finfo(float).tiny)[..., None, None]
    order = None
    if compress:
        k = max(int(free.sum(axis=-1).max(initial=0)), 1)
        if k < count:
            order = np.argsort(~free, axis=-1, kind="stable")[..., :k]  # free ones first
            H = np.take_along_axis(np.take_along_axis(H, order[..., :, None], axis=-2),
                                   order[..., None, :], axis=-1)
            g = np.take_along_axis(g, order, axis=-1)
            free = np.take_along_axis(free, order, axis=-1)
    size = g.shape[-1]
    both_free = free[..., :, None] & free[..., None, :]
    Hm = np.where(both_free, H / curvature, 0.0) + np.eye(size) * (~free)[..., None, :]
    kkt = np.zeros(g.shape[:-1] + (size + 1, size + 1))
    kkt[..., :size, :size] = Hm
    kkt[..., :size, size] = free
    kkt[..., size, :size] = free
    rhs = np.concatenate(
        [np.where(free, -g, 0.0) / curvature[..., 0], np.zeros(g.shape[:-1] + (1,))], axis=-1
    )
    solution = (np.linalg.pinv(kkt, rcond=_RCOND) @ rhs[..., None])[..., 0]
    d = np.where(free, solution[..., :size], 0.0)
    mu = -solution[..., size] * curvature[..., 0, 0]
    if order is not None:
        full = np.zeros(d.shape[:-1] + (count,))
        np.put_along_axis(full, order, d, axis=-1)
        d = full
    return d, mu


def _active_set(rows, w, free, iterations, *, xtol, max_iter, gtol, absolute_gap, compress):
    """Phase 2 of :func:`minimize_convex_simplex`: the active-set Newton method from ``w``
    (weights outside ``free`` exactly zero), each problem within ``max_iter`` iterations in
    all (``iterations`` already used). Returns ``w``, ``iterations``, ``converged``."""
    shape, count = (rows.size,), rows.count

    def evaluate_rows(w, which):
        return rows.evaluate(w, which)

    def objective_rows(w, which):
        return rows.objective(w, which)

    w, free, iterations = w.copy(), free.copy(), iterations.copy()
    done = np.zeros(shape, dtype=bool)
    finished = np.zeros(shape, dtype=bool)  # stalled at the rounding level, unconverged
    previous_d = np.zeros(shape + (count,))  # the last step's direction, length and slope
    previous_t = np.zeros(shape)
    previous_slope = np.zeros(shape)
    previous_last = np.zeros(shape, dtype=bool)  # the last step was an unchecked Newton step
    gap = np.full(shape, np.inf)
    while True:
        # a problem at its iteration limit is not evaluated again (its last step is unchecked)
        finished |= iterations >= max_iter
        if (done | finished).all():
            break
        f, g, H = evaluate_rows(w, ~done & ~finished)
        active = ~done & ~finished
        d, mu = _face_newton(H, g, free, compress)

        if gtol > 0.0:
            previous_gap = gap
            gap = frank_wolfe_gap(w, g)
            certified = active & (gap <= gtol * (1.0 if absolute_gap else np.abs(f)))
            done |= certified
            active = active & ~certified

        small_step = np.abs(d).max(axis=-1) < xtol
        slope = np.einsum("...i,...i->...", g, d)
        # the rounding level of f: relative to |f|, or to 1 for objectives near zero
        f_scale = np.maximum(np.abs(f), 1.0) if absolute_gap else np.abs(f)
        extend = np.zeros(shape, dtype=bool)
        if gtol > 0.0:
            # A step after which the derivative along its direction kept more than half of
            # its slope went nowhere near the minimum along that line: f is nearly linear
            # there and the Hessian overstates its curvature (ill-conditioned, nearly tied
            # inputs). Continue along the same line instead, by the secant of the
            # derivative, up to the boundary; Newton resumes once the line is done.
            now = np.einsum("...i,...i->...", g, previous_d)
            # (only after a step whose slope was well above the rounding level of f, and
            # checked by the line search like any step: at the rounding level the
            # derivatives are noise and the extension could run to the boundary)
            extend = (active & (previous_t > 0.0)
                      & (-previous_slope > 64.0 * np.finfo(float).eps * f_scale)
                      & (now < 0.5 * previous_slope))
            d = np.where(extend[..., None], previous_d, d)
            slope = np.where(extend, now, slope)
            small_step = small_step & ~extend
        # -g.d = d^T H d, the squared Newton decrement. Below the rounding level of f the face
        # is solved to working precision even if d exceeds xtol (flat, badly scaled problems):
        # the line search cannot tell a decrease from rounding noise there and would stall
        # until max_iter, so the problem stops after taking this last step unchecked.
        # With a gap test (gtol > 0) the line search is trusted only above a margin over
        # the rounding level of f: ill-conditioned problems evaluate f to about cond * eps,
        # and there the gradient (and so the gap) is the better judge.
        level = max(4.0 * np.finfo(float).eps, 1e-3 * gtol)
        rounding = (-slope <= level * f_scale) & ~extend
        small = small_step | rounding
        g_scale = np.abs(g).max(axis=-1) + np.finfo(float).tiny
        deficit = np.where(free, 0.0, g - mu[..., None])  # < 0: releasing helps
        release_any = (deficit < -1e-12 * g_scale[..., None]).any(axis=-1)
        if gtol > 0.0:
            # Convergence is certified by the gap alone. A Newton step that vanishes
            # without a certified gap means curvature the pseudo-inverse could not resolve
            # (nearly tied inputs: f is almost linear along the ties): a Frank-Wolfe step
            # towards the vertices of smallest gradient takes over there. A decrement
            # below the rounding level of f is a step the line search cannot judge: it is
            # taken as it is, and the gap at the next iterate decides.
            # A Newton direction that is not a descent direction (curvature at the rounding
            # level of the Hessian, of either sign) is replaced likewise.
            converged_now = np.zeros(shape, dtype=bool)
            # At the rounding level the sign of the slope is noise: Newton is then replaced
            # only where its last unchecked step did not halve the gap.
            # A step below xtol is still taken (unchecked): only the gap ends a problem.
            stalled_newton = previous_last & ~(gap <= 0.5 * previous_gap)
            zero_step = np.abs(d).max(axis=-1) <= 4.0 * np.finfo(float).eps
            stuck = active & ~release_any & (
                zero_step | ((slope >= 0.0) & ~rounding) | (rounding & stalled_newton))
            last = active & (rounding | small_step) & ~stuck & ~release_any
        else:
            converged_now = active & small & ~release_any
            stuck = np.zeros(shape, dtype=bool)
            last = converged_now & rounding & ~small_step
        done |= converged_now
        iterations += active & ~converged_now

        # Where the face is solved, release the fixed weight whose gradient is furthest
        # below the level of the free ones, with every weight tied with it (so that equal
        # inputs stay equal). One at a time, as in the primal active-set method: from the
        # optimum of a face, the Newton step after releasing the most negative multiplier
        # increases that weight; releasing several at once can give a step that makes one
        # of them negative at once (it then blocks at length zero).
        releasing = active & small & release_any
        most = deficit.min(axis=-1, keepdims=True)
        chosen = (deficit < -1e-12 * g_scale[..., None]) & (deficit <= most * (1.0 - 1e-9))
        free = free | (releasing[..., None] & chosen)

        if stuck.any():
            d, slope, free = _towards_best_vertices(stuck, w, g, g_scale, d, slope, free)

        stepping = (active & ~small) | last | stuck
        if not stepping.any():
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(free & (d < 0), w / -d, np.inf)
        t_max = ratio.min(axis=-1)
        # A weight just released at zero whose Newton step on the enlarged face points below
        # zero blocks that step at length zero (the affine optimum of the face lies outside
        # the simplex), although releasing it decreases f. Step towards the vertices of
        # smallest gradient instead.
        blocked_at_zero = stepping & (t_max <= 0.0)
        if blocked_at_zero.any():
            d, slope, free = _towards_best_vertices(blocked_at_zero, w, g, g_scale, d, slope,
                                                    free)
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(free & (d < 0), w / -d, np.inf)
            t_max = np.where(blocked_at_zero, ratio.min(axis=-1), t_max)
        t = np.minimum(1.0, t_max)
        if extend.any():
            with np.errstate(divide="ignore", invalid="ignore"):
                further = np.where(slope > previous_slope,
                                   previous_t * slope / (previous_slope - slope), t_max)
            t = np.where(extend, np.clip(np.nan_to_num(further, nan=0.0), 0.0, t_max), t)
        by_slope = stuck & ~extend if gtol > 0.0 else np.zeros(shape, dtype=bool)
        if by_slope.any():
            # Where f is flat to its rounding level along d, its values cannot place the
            # step but its directional derivative can (the gradient stays accurate): a
            # secant step on phi'(t) = g(w + t d).d from phi'(0) and phi'(t_1),
            # t_1 = min(1, t_max), extrapolated up to the boundary where phi' has not
            # grown (f nearly linear along d).
            t_1 = np.minimum(1.0, t_max)
            trial = np.where(by_slope[..., None], np.clip(w + t_1[..., None] * d, 0.0, None), w)
            _, g_1, _ = evaluate_rows(trial, by_slope)
            s_1 = np.einsum("...i,...i->...", g_1, d)
            with np.errstate(divide="ignore", invalid="ignore"):
                secant = np.where(s_1 > slope, t_1 * -slope / (s_1 - slope), t_max)
            secant = np.clip(np.where(np.isnan(secant), 0.0, secant), 0.0, t_max)
            t = np.where(by_slope, secant, t)
        failed = np.zeros(shape, dtype=bool)
        for _ in range(60):  # Armijo backtracking, batched
            trial = np.where(stepping[..., None], w + t[..., None] * d, w)
            trial = np.clip(trial, 0.0, None)
            f_trial = objective_rows(trial, stepping & ~last & ~by_slope)
            failed = stepping & ~last & ~by_slope & ~(
                f_trial <= f + 1e-4 * t * slope + 1e-15 * np.abs(f))
            if not failed.any():
                break
            t = np.where(failed, 0.5 * t, t)
        # No decrease at any step length: f is flat to its rounding level along d, so this
        # problem is where floating point can take it. It stops (unconverged unless a
        # test above said otherwise) instead of repeating the same failing search.
        stalled = failed & (t * np.abs(d).max(axis=-1) < xtol)
        stepping = stepping & ~stalled
        finished |= stalled
        blocked = stepping & (t == t_max)
        # (only a checked Newton step may be extended, not a Frank-Wolfe or unchecked one)
        previous_d = d
        previous_t = np.where(stepping & ~blocked & ~stuck & ~last, t, 0.0)
        previous_slope = slope
        previous_last = last & stepping
        new_w = np.where(stepping[..., None], w + t[..., None] * d, w)
        hit = blocked[..., None] & (ratio == t_max[..., None])
        new_w = np.where(hit, 0.0, np.clip(new_w, 0.0, None))
        free = free & ~hit
        w = new_w / new_w.sum(axis=-1, keepdims=True)
    return w, iterations, done
