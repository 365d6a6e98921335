"""Batched minimisers for the convex weight problems of Covariance Intersection.

Both solvers run one Newton iteration for the whole batch at a time (vectorised over
the batch; the Python loop is over iterations only) and report, per problem, the
number of iterations and whether the tolerance was met. Optima on the boundary are
returned exactly (weights of exactly 0 or 1), not approached asymptotically.
"""

import math

import numpy as np

__all__ = [
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
        ``objective(w) -> f`` (cheaper than ``evaluate``; used by the line search).
    count : int
        Number of weights N.
    shape : tuple
        Batch shape.
    xtol : float
        Stop when the Newton step on the current face is below ``xtol`` and no weight
        fixed at zero should be released.
    max_iter : int
        Iteration limit.
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
    An active-set Newton method. Weights fixed at zero are excluded; on the face of the
    free ones, the equality-constrained Newton step solves the KKT system
    ``[H_FF 1; 1^T 0] [d; nu] = [-g_F; 0]``. A step that would make a weight negative is
    cut at the boundary and that weight is fixed at exactly zero. When the step on the
    face vanishes, ``-nu`` is the common gradient level ``mu`` of the free weights; a fixed
    weight whose gradient is below ``mu`` would decrease ``f`` and is released. The KKT
    system is solved by a pseudo-inverse, so that directions in which ``f`` is flat (equal
    inputs) get no step and the weights keep their uniform start there. At the
    result the KKT conditions of the simplex hold: ``g_i = mu`` for ``w_i > 0`` and
    ``g_i >= mu`` for ``w_i = 0``.
    """
    def evaluate_rows(w, rows):
        if not subset:
            return evaluate(w)
        f, g = np.zeros(shape), np.zeros(shape + (count,))
        H = np.broadcast_to(np.eye(count), shape + (count, count)).copy()
        index = np.flatnonzero(rows)
        if index.size:
            f[index], g[index], H[index] = evaluate(w[index], index)
        return f, g, H

    def objective_rows(w, rows):
        if not subset:
            return objective(w)
        f = np.zeros(shape)
        index = np.flatnonzero(rows)
        if index.size:
            f[index] = objective(w[index], index)
        return f

    w = np.full(shape + (count,), 1.0 / count)
    free = np.ones(shape + (count,), dtype=bool)
    done = np.zeros(shape, dtype=bool)
    iterations = np.zeros(shape, dtype=int)
    eye = np.eye(count)
    finished = np.zeros(shape, dtype=bool)  # stalled at the rounding level, unconverged
    previous_d = np.zeros(shape + (count,))  # the last step's direction, length and slope
    previous_t = np.zeros(shape)
    previous_slope = np.zeros(shape)
    previous_last = np.zeros(shape, dtype=bool)  # the last step was an unchecked Newton step
    gap = np.full(shape, np.inf)
    for _ in range(max_iter):
        if (done | finished).all():
            break
        f, g, H = evaluate_rows(w, ~done & ~finished)
        active = ~done & ~finished
        both_free = free[..., :, None] & free[..., None, :]
        # Normalise the curvature so that the constraint rows and the Hessian have the same
        # scale; the pseudo-inverse then drops flat directions (sum_i d_i I_i = 0, along
        # which f is constant) instead of amplifying rounding noise along them, so the
        # weights stay where they started in those directions (uniform: permutation-fair).
        diagonal = np.where(free, np.diagonal(H, axis1=-2, axis2=-1), 0.0)
        curvature = np.maximum(diagonal.max(axis=-1), np.finfo(float).tiny)[..., None, None]
        Hm = np.where(both_free, H / curvature, 0.0) + eye * (~free)[..., None, :]
        kkt = np.zeros(shape + (count + 1, count + 1))
        kkt[..., :count, :count] = Hm
        kkt[..., :count, count] = free
        kkt[..., count, :count] = free
        rhs = np.concatenate(
            [np.where(free, -g, 0.0) / curvature[..., 0], np.zeros(shape + (1,))], axis=-1
        )
        solution = (np.linalg.pinv(kkt, rcond=_RCOND) @ rhs[..., None])[..., 0]
        d = np.where(free, solution[..., :count], 0.0)
        mu = -solution[..., count] * curvature[..., 0, 0]

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
