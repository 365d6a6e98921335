"""The exact worst case of fixed fusion gains over every admissible joint covariance.

For gains ``K_i`` (with ``sum_i K_i = I``) the fused error is ``e = sum_i K_i e_i``. Along a
direction ``v`` put ``G_i = K_i P_i K_i^T`` and ``s_i = sqrt(v^T G_i v)``, the standard
deviation of ``v^T K_i e_i``. Over every joint covariance whose diagonal blocks are the
``P_i`` and whose normalised cross blocks ``C_ij = L_i^-1 P_ij L_j^-T`` (``P_i = L_i L_i^T``,
any exact factors) have spectral norm at most ``rho``, the largest error variance along
``v`` is

    worst(v) = (1 - rho) sum_i s_i^2 + rho (sum_i s_i)^2,

attained by ``C_ij = rho u_i u_j^T`` with ``u_i = L_i^T K_i^T v / s_i`` (a positive
semidefinite joint). ``rho = 1`` is arbitrary correlation (Covariance Intersection: any
joint with the given marginals), ``rho = 0`` independence. A fused covariance ``P`` is a
valid bound for the gains exactly when ``v^T P v >= worst(v)`` for every ``v``.

Everything is computed from the *inputs*: the ``P_i`` as given (their symmetric part) and
the returned ``K_i`` and ``P``, in ``DIGITS``-digit arithmetic (mpmath), never from
Cholesky factors or products formed in floating point the way the rules form them. Only
quantities in which no cancellation is left (differences already taken at 50 digits) are
rounded to float64.

The check, with ``tau = tol ||P||`` the rounding tolerance:

* ``rho = 0``: ``worst(v) = v^T W v`` with ``W = sum_i G_i``; the bound holds exactly when
  the smallest eigenvalue of ``P - W`` is at least ``-tau``.
* ``rho > 0``: ``worst`` is not a quadratic form. For every ``t`` on the simplex
  (Cauchy-Schwarz) ``worst(v) <= v^T B(t) v`` with
  ``B(t) = sum_i ((1 - rho) + rho / t_i) G_i``, with equality where ``t_i`` is
  proportional to ``s_i(v)``. So the smallest eigenvalue of ``P - B(t)`` at any ``t`` bounds
  the violation from above (a certificate: the bound holds if it is at least ``-tau``),
  and ``worst(v) - v^T P v`` at any ``v`` bounds it from below (a witness: the bound fails
  if it exceeds ``tau`` at a unit ``v``). The certificate is sought at the ``t`` that best
  writes ``P`` as ``B(t)`` (a least-squares fit of the coefficients, exact for the
  information-form rules, whose ``P`` is ``B(t)`` at their weights) and at the ``t`` of
  each witness; witnesses by a monotone block ascent of ``worst(v) / v^T (P + tau I) v``
  (see :func:`_ascend`) from the eigenvectors of ``P`` and of ``B(t) - P`` and from fixed
  random directions. The check passes when a certificate is found, fails with
  the witness when one exceeds the tolerance, and otherwise fails as not certified.
"""

import mpmath
import numpy as np
from scipy.optimize import linprog, minimize

EPS = np.finfo(float).eps
DIGITS = 50


def _mp_matrix(A):
    """An mpmath matrix holding the float64 entries of ``A`` exactly."""
    return mpmath.matrix(np.asarray(A, dtype=float).tolist())


def _to_float(M):
    """A symmetric mpmath matrix rounded to float64 (symmetrised at full precision)."""
    n = M.rows
    return np.array([[float((M[i, j] + M[j, i]) / 2) for j in range(n)] for i in range(n)])


def _quadratic(M, v):
    """``v^T M v`` at full precision for an mpmath matrix ``M`` and a float vector ``v``."""
    n = M.rows
    vm = [mpmath.mpf(float(x)) for x in v]
    return mpmath.fsum(vm[i] * mpmath.fdot([M[i, j] for j in range(n)], vm) for i in range(n))


def _terms(gains, Ps):
    """``G_i = K_i P_i K_i^T`` at ``DIGITS`` digits from the gains and the inputs."""
    terms = []
    for K, Pi in zip(gains, Ps):
        Km, Pm = _mp_matrix(K), _mp_matrix(Pi)
        terms.append(Km * ((Pm + Pm.T) / 2) * Km.T)
    return terms


def _worst(terms, v, rho):
    """``worst(v)`` at full precision (see the module docstring)."""
    squares = [_quadratic(G, v) for G in terms]
    roots = [mpmath.sqrt(max(s, 0)) for s in squares]
    rho = mpmath.mpf(float(rho))
    return (1 - rho) * mpmath.fsum(squares) + rho * mpmath.fsum(roots) ** 2, roots


def worst_case_variance(gains, Ps, v, rho=1.0):
    """``worst(v)`` for directions ``v`` (..., n), from the inputs at ``DIGITS`` digits.

    ``gains`` (..., N, n, n) and ``Ps`` (..., N, n, n) (or sequences of N matrices) may carry
    leading batch axes; the result (float64) has the batch shape.
    """
    K = np.asarray(gains, dtype=float)
    Ps = np.broadcast_to(np.asarray(Ps, dtype=float), K.shape)
    v = np.broadcast_to(np.asarray(v, dtype=float), K.shape[:-3] + K.shape[-1:])
    out = np.empty(K.shape[:-3])
    with mpmath.workdps(DIGITS):
        for index in np.ndindex(out.shape):
            out[index] = float(_worst(_terms(K[index], Ps[index]), v[index], rho)[0])
    return out[()]


def _certificate(terms, P_shifted, coefficients):
    """Largest eigenvalue of ``sum_i c_i G_i - (P + tau I)`` (exact difference, then float)."""
    D = -P_shifted
    for c, G in zip(coefficients, terms):
        if c != 0:
            D = D + c * G
    values, vectors = np.linalg.eigh(_to_float(D))
    return values[-1], vectors[:, -1]


def _coefficients_of(t, rho, used):
    """``c_i = (1 - rho) + rho / t_i`` for ``t`` renormalised to the simplex over the terms
    ``used`` (zero terms get no coefficient: ``B(t)`` does not depend on their ``t_i``)."""
    total = mpmath.fsum(t[i] for i in used)
    rho = mpmath.mpf(float(rho))
    return [(1 - rho) + rho * total / t[i] if i in used else mpmath.mpf(0)
            for i in range(len(t))]


def _fitted_t(terms, P, rho, used):
    """The ``t`` whose ``B(t)`` is closest to ``P`` (Frobenius), or None.

    The coefficients ``c_i`` of ``P ~ sum_i c_i G_i`` by least squares at full precision;
    where they are not unique (``G_i`` that are linearly dependent, as for proportional
    inputs) the one of smallest ``sum_i t_i`` with ``t_i = rho / (c_i - 1 + rho)`` (a
    convex function, minimised by Newton's method over the null space).
    """
    if not used:
        return None
    n = P.rows

    def inner(A, B):
        return mpmath.fsum(A[i, j] * B[i, j] for i in range(n) for j in range(n))

    A = mpmath.matrix(len(used), len(used))
    b = mpmath.matrix(len(used), 1)
    for a, i in enumerate(used):
        b[a] = inner(terms[i], P)
        for c, j in enumerate(used):
            A[a, c] = inner(terms[i], terms[j])
    values, vectors = mpmath.eigsy(A)
    top = max(abs(x) for x in values)
    # singular values below 1e3 eps of the largest: rounding (equal inputs give G_i that are
    # proportional up to the rounding of their gains); the coefficients are not determined
    floor = top * mpmath.mpf(1e3 * EPS) ** 2
    inverse = [1 / x if abs(x) > floor else 0 for x in values]
    c = vectors * mpmath.diag(inverse) * vectors.T * b
    null = [k for k, x in enumerate(inverse) if x == 0]
    rho = mpmath.mpf(float(rho))
    if null:
        Z = np.array([[float(vectors[a, k]) for k in null] for a in range(len(used))])
        y = _least_total(np.array([float(x) for x in c]), Z, float(rho))
        c = c + mpmath.matrix(Z.tolist()) * mpmath.matrix(y.tolist())
    t = [mpmath.mpf(0)] * len(terms)
    for a, i in enumerate(used):
        excess = c[a] - (1 - rho)
        if not excess > 0:
            return None
        t[i] = rho / excess
    return t


def _least_total(c, Z, rho, steps=50):
    """``y`` minimising ``sum_i rho / x_i`` with ``x = c + Z y - 1 + rho > 0`` (Newton)."""
    y = np.zeros(Z.shape[1])
    x = c - 1.0 + rho
    if np.any(x <= 0.0):  # a feasible start: maximise min_i x_i (a linear programme)
        k = Z.shape[1]
        scale = np.abs(c).max() + 1.0
        found = linprog(np.r_[np.zeros(k), -1.0], A_ub=np.c_[-Z, np.ones(len(c))],
                        b_ub=c - 1.0 + rho, bounds=[(-1e3 * scale, 1e3 * scale)] * k
                        + [(None, scale)])
        if not found.success or found.x[-1] <= 0.0:
            return y
        y = found.x[:k]
        x = c + Z @ y - 1.0 + rho
    for _ in range(steps):
        with np.errstate(divide="ignore", over="ignore", invalid="ignore"):
            gradient = -rho * Z.T @ (1.0 / x**2)
            hessian = 2.0 * rho * (Z.T * (1.0 / x**3)) @ Z
        if not (np.isfinite(gradient).all() and np.isfinite(hessian).all()):
            break  # an x_i near 0 overflowed: keep the last y (the caller checks t itself)
        step = -np.linalg.lstsq(hessian, gradient, rcond=None)[0]
        value = (rho / x).sum()
        length = 1.0
        while length > 1e-12:
            trial = c + Z @ (y + length * step) - 1.0 + rho
            if np.all(trial > 0.0) and (rho / trial).sum() <= value:
                break
            length /= 2.0
        else:
            break
        y = y + length * step
        x = c + Z @ y - 1.0 + rho
        if abs(gradient @ step) <= 1e-15 * value:
            break
    return y


def _ascend(grams, shifted, v, rho, steps=60):
    """Monotone ascent of ``worst(v) / v^T (P + tau I) v`` from ``v`` (float64).

    Its largest value exceeds 1 exactly when some unit ``v`` has
    ``worst(v) - v^T P v > tau``. With ``G_i = M_i M_i^T``,
    ``(sum_i s_i)^2 = max (v^T m)^2`` over ``m = sum_i M_i u_i`` with unit ``u_i``, so
    ``worst(v) = max_m v^T ((1 - rho) sum_i G_i + rho m m^T) v``. Block ascent: the best
    ``u`` for ``v`` gives ``m = sum_i G_i v / s_i``, the best ``v`` for ``m`` is the top
    generalised eigenvector of ``((1 - rho) sum_i G_i + rho m m^T, P + tau I)``; neither
    step lowers the ratio. (Measured in ``P + tau I`` rather than on the unit sphere, so
    that the spread of ``P``'s eigenvalues does not trap the ascent in its small
    directions.)
    """
    factor = np.linalg.cholesky(shifted)
    inverse = np.linalg.inv(factor)
    common = (1.0 - rho) * grams.sum(axis=0)
    best, best_v = -np.inf, v
    for _ in range(steps):
        Gv = grams @ v  # (N, n)
        s = np.sqrt(np.maximum(np.einsum("kj,j->k", Gv, v), 0.0))
        ratio = ((1.0 - rho) * (s**2).sum() + rho * s.sum() ** 2) / (v @ shifted @ v)
        if not ratio > best * (1.0 + 1e-15):
            break
        best, best_v = ratio, v
        with np.errstate(divide="ignore", invalid="ignore"):
            m = np.where(s[:, None] > 0.0, Gv / s[:, None], 0.0).sum(axis=0)
        S = inverse @ (common + rho * np.outer(m, m)) @ inverse.T
        w = inverse.T @ np.linalg.eigh(0.5 * (S + S.T))[1][:, -1]
        v = w / np.linalg.norm(w)
    return best_v


def _check(P, gains, Ps, rho, tol):
    """``(upper, lower, v_upper, v_lower)``: bounds on ``max_|v|=1 worst(v) - v^T P v - tau``."""
    P = np.asarray(P, dtype=float)
    gains = np.asarray(gains, dtype=float)
    Ps = np.asarray(Ps, dtype=float)
    n, count = P.shape[-1], gains.shape[0]
    if tol is None:
        tol = 64.0 * n * count * EPS
    norm = np.linalg.norm(P, 2)
    tau = tol * norm
    with mpmath.workdps(DIGITS):
        terms = _terms(gains, Ps)
        P_mp = _mp_matrix(P)
        P_mp = (P_mp + P_mp.T) / 2
        P_shifted = P_mp + mpmath.mpf(float(tau)) * mpmath.eye(n)
        if rho == 0.0:  # a quadratic form: the check is one eigenvalue
            upper, v = _certificate(terms, P_shifted, [mpmath.mpf(1)] * count)
            return upper, upper, v, v
        used = [i for i, G in enumerate(terms) if any(G[a, a] != 0 for a in range(n))]
        candidates = []  # (upper, v) at trial t
        trials = []  # the trial t
        fitted = _fitted_t(terms, P_mp, rho, used)
        if fitted is not None:
            trials.append(fitted)
            candidates.append(_certificate(terms, P_shifted, _coefficients_of(fitted, rho, used)))
        # witnesses: ascent from the eigenvectors of P, of the certificate's difference, and
        # from fixed random directions
        grams = np.array([_to_float(G) for G in terms])
        shifted = _to_float(P_shifted)
        starts = list(np.linalg.eigh(P)[1].T) + [v for _, v in candidates]
        starts += list(np.random.default_rng(0).standard_normal((n, n)))
        witnesses = []
        for start in starts:
            v = _ascend(grams, shifted, start / np.linalg.norm(start), rho)
            v = v / np.linalg.norm(v)
            value, roots = _worst(terms, v, rho)
            excess = (value - _quadratic(P_shifted, v)) / mpmath.fdot(v, v)
            witnesses.append((float(excess), v, roots))
        lower, v_lower, roots = max(witnesses, key=lambda item: item[0])
        for _, _, roots in witnesses:  # the t that is tight at each witness
            if sum(roots) > 0:
                t = [r if i in used else mpmath.mpf(0) for i, r in enumerate(roots)]
                if all(t[i] > 0 for i in used):
                    trials.append(t)
                    candidates.append(
                        _certificate(terms, P_shifted, _coefficients_of(t, rho, used)))
        upper, v_upper = min(candidates, key=lambda item: item[0]) if candidates else (
            np.inf, v_lower)
        if upper > 0.0 and lower <= 0.0:  # undecided: search t directly
            found = _search_t(terms, P_shifted, rho, used, norm, trials)
            if found is not None and found[0] < upper:
                upper, v_upper = found
        return upper, lower, v_upper, v_lower


class _Certified(Exception):
    pass


def _search_t(terms, P_shifted, rho, used, norm, trials, evaluations=400):
    """Minimise the certificate ``lambda_max(B(t) - P - tau I)`` over the simplex directly
    (Nelder-Mead on ``t = softmax(z)``; the function is convex in ``t`` but not smooth),
    stopping at the first ``t`` that certifies. For the cases the least-squares fit leaves
    undecided: nearly dependent ``G_i`` (equal inputs) or terms below rounding (weights
    near zero), where the fitted coefficients are rounding noise."""
    if len(used) < 2:
        return None
    best = [np.inf, None]

    def certificate(z):
        t = np.exp(z - z.max())
        full = [mpmath.mpf(0)] * len(terms)
        for a, i in enumerate(used):
            full[i] = mpmath.mpf(float(t[a]))
        if not all(full[i] > 0 for i in used):
            return np.inf
        value, v = _certificate(terms, P_shifted, _coefficients_of(full, rho, used))
        if value < best[0]:
            best[:] = [value, v]
        if value <= 0.0:
            raise _Certified
        return value / norm

    starts = [np.log([float(t[i]) for i in used]) for t in trials
              if all(t[i] > 0 for i in used)][:3] + [np.zeros(len(used))]
    for start in starts:
        try:
            minimize(certificate, start, method="Nelder-Mead",
                     options={"maxfev": evaluations, "xatol": 1e-12, "fatol": 0.0})
        except _Certified:
            break
    return (best[0], best[1]) if best[1] is not None else None


def worst_violation(P, gains, Ps, rho=1.0, tol=None):
    """Largest ``worst(v) - v^T P v`` over unit ``v`` beyond the rounding tolerance.

    The tolerance is ``tol * ||P||`` with ``tol`` defaulting to ``64 n N eps`` (rounding of
    the products that form ``P``: the bound is exact for the returned gains). Returns
    ``(excess, v)``: where a certificate is found (see the module docstring) ``excess <= 0``
    is its upper bound of the violation and ``v`` its top direction; otherwise ``excess``
    is the largest violation found at a witness ``v`` if that is positive (the bound fails),
    else the smallest certificate's upper bound (positive: not certified).
    """
    upper, lower, v_upper, v_lower = _check(P, gains, Ps, rho, tol)
    if upper <= 0.0:
        return upper, v_upper
    if lower > 0.0:
        return lower, v_lower
    return upper, v_upper


def assert_bound_holds(P, gains, Ps, rho=1.0, tol=None, what="P"):
    """Assert that ``P`` dominates the worst-case error covariance of ``gains``."""
    upper, lower, v_upper, v_lower = _check(P, gains, Ps, rho, tol)
    norm = np.linalg.norm(np.asarray(P, dtype=float), 2)
    assert upper <= 0.0, (
        f"{what} is not a bound: along v = {v_lower.tolist()} the worst admissible error "
        f"variance exceeds v^T P v by {lower:.3g} beyond rounding (||P|| = {norm:.3g})"
        if lower > 0.0 else
        f"{what} is not certified as a bound: no t on the simplex gives P >= B(t) to "
        f"rounding (best excess {upper:.3g} along {v_upper.tolist()}; the largest violation "
        f"found is {lower:.3g}, ||P|| = {norm:.3g})"
    )


def assert_unbiased(gains, tol=None):
    """Assert ``sum_i K_i = I`` to rounding (the fused error is then ``sum_i K_i e_i``)."""
    gains = np.asarray(gains, dtype=float)
    n = gains.shape[-1]
    scale = 1.0 + np.abs(gains).sum(axis=-3).max()
    tol = 64.0 * n * EPS * scale if tol is None else tol
    residual = np.abs(gains.sum(axis=-3) - np.eye(n)).max()
    assert residual <= tol * max(1.0, np.abs(gains).max()), f"sum of gains - I = {residual:.3g}"


def padded(gains, Ps):
    """Gains (n x m_i) and covariances (m_i x m_i) padded to (n x M), (M x M): the padding
    columns of the gains are zero, so ``K P K^T`` is unchanged (estimates of parts
    ``H_i x`` of the state for :func:`assert_bound_holds`)."""
    M = max(P.shape[0] for P in Ps)
    K_pad, P_pad = [], []
    for K, P in zip(gains, Ps):
        m = P.shape[0]
        k = np.zeros((K.shape[0], M))
        k[:, :m] = K
        p = np.eye(M)
        p[:m, :m] = P
        K_pad.append(k)
        P_pad.append(p)
    return np.array(K_pad), np.array(P_pad)


def gain_bound_difference(P, gains, Ps, weights):
    """The largest entry of ``P - sum_i K_i P_i K_i^T / w_i`` in 50-digit arithmetic from
    the returned gains and the input covariances (the rule's bound of its gains, formed
    independently of its factors). An estimate of weight 0 must have a zero gain and
    contributes no term."""
    n = P.shape[-1]
    with mpmath.workdps(50):
        exact = mpmath.zeros(n, n)
        for K, P_i, w in zip(gains, Ps, weights):
            if w == 0.0:  # an ignored estimate: zero gain, no term
                assert not np.asarray(K).any()
                continue
            Km = mpmath.matrix(np.asarray(K).tolist())
            exact += Km * mpmath.matrix(np.asarray(P_i).tolist()) * Km.T / mpmath.mpf(float(w))
        return max(abs(float(P[i, j] - exact[i, j])) for i in range(n) for j in range(n))
