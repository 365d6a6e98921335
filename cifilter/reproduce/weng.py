"""Weng & Djurić: Bayesian Monte Carlo fusion against optimal fusion and fast CI.

Reproduces the experiments of the EUSIPCO 2012 paper (Figs. 1-2) and of the journal version
(model 1, Figs. 2-4; model 2, Figs. 5-8; Fig. 9, MSE against the number of nodes; Fig. 10,
MSE against the number of samples M), adds the repeated-fusion NEES experiment the
journal's discussion describes in words, and prints every number next to the papers'
statements. The figures themselves are missing from the papers' text: what can be
compared are the claims the text makes about them (orderings and sizes of gaps).

Every configuration is one batched computation over the runs: the Bayesian rule draws
``runs x M`` joint covariances at once (in memory-sized chunks), so a 10 000-run
configuration takes seconds.

Models
------
*Kalman model* (conference Sec. 5; journal model 2, eqs. (54)-(56)): ``Sigma_0 ~
W_2(nu, sigma_0^2 I)``, ``Sigma_i ~ W_2(nu, sigma^2 I)`` (nu = 4 in the conference, 3 in
the journal), ``x_0 ~ N(0, Sigma_0)``, ``x_i ~ N(x_0, Sigma_i)``; the fusion is told
``P_ii = Sigma_0 + Sigma_i``, the optimal rule the joint covariance (56) whose cross blocks
are ``Sigma_0``. The error can be measured against the common mean 0 (the quantity whose
covariance (56) is) or against the drawn ``x_0``; both are reported.

*Wishart model* (journal model 1): ``P_x ~ W_2k(3k, sigma^2 I)``, ``x ~ N(0, P_x)``, the
error is measured against ``x_0 = 0``.
"""

import sys
import time
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .._validation import as_rng, check_int, check_scalar
from ..bayes import bayesian_fusion
from ..ci import covariance_intersection
from ..optimal import naive_fusion, optimal_fusion

__all__ = [
    "FusionData",
    "compare_estimators",
    "repeated_fusion_nees",
    "simulate_kalman_model",
    "simulate_wishart_model",
]

DESCRIPTION = (
    "Weng & Djurić (EUSIPCO 2012 Figs. 1-2, journal Figs. 2-10): Bayesian Monte Carlo "
    "fusion vs optimal and fast CI; repeated-fusion NEES"
)

ESTIMATORS = (
    "optimal", "bayes", "naive", "ci-fast", "ci-improved-fast", "ci-det-ratio", "ci-trace"
)
LABELS = {
    "optimal": "optimal",
    "bayes": "Bayesian",
    "ci-fast": "CI fast",
    "ci-improved-fast": "CI impr.",
    "ci-det-ratio": "CI det",
    "ci-trace": "CI trace",
    "naive": "naive",
}
GRID = (0.1, 0.2, 0.5, 1.0, 2.0, 5.0)  # sweeps of sigma_0^2 and sigma^2 (not in the text)
NODES = (2, 3, 4, 5, 6)  # Fig. 9 (range not in the text)
SAMPLE_SIZES = (1, 2, 5, 10, 20, 50, 100, 200, 500)  # Fig. 10 (range not in the text)
DIM = 2  # the state dimension of every experiment of both papers
# "About p%" in the text counts as reproduced when the mean over a sweep lies within a
# factor of two of p.
ABOUT_20 = (0.10, 0.40)
ROUGHLY_10 = (0.05, 0.20)


class FusionData(NamedTuple):
    """Simulated estimates of one experiment (returned by the ``simulate_*`` functions).

    The parameters are also the attributes.

    Parameters
    ----------
    xs : ndarray, shape (runs, k, 2)
        The k estimates of every run.
    Ps : ndarray, shape (runs, k, 2, 2)
        Their covariances (the diagonal blocks of ``joint``), what the fusion rules know.
    joint : ndarray, shape (runs, 2k, 2k)
        The joint covariance of the stacked estimates, known to the optimal rule only.
    x0 : ndarray, shape (runs, 2)
        The drawn state (zero in the Wishart model).

    Examples
    --------
    >>> from cifilter.reproduce.weng import simulate_wishart_model
    >>> simulate_wishart_model(k=3, sigma_sq=1.0, runs=4, rng=0).joint.shape
    (4, 6, 6)
    """

    xs: np.ndarray
    Ps: np.ndarray
    joint: np.ndarray
    x0: np.ndarray


def _wishart(rng, dof, scale, dim, shape):
    """Draws of W_dim(dof, scale I) for an integer dof (sums of outer products)."""
    Z = rng.standard_normal(shape + (dof, dim))
    return scale * (np.swapaxes(Z, -1, -2) @ Z)


def _diagonal_blocks(joint, k):
    return np.stack([joint[..., i * DIM:(i + 1) * DIM, i * DIM:(i + 1) * DIM]
                     for i in range(k)], axis=-3)


def simulate_kalman_model(k, sigma0_sq, sigma_sq, runs, rng=None, data_dof=3):
    """Simulate the distributed Kalman filter model (conference Sec. 5; journal model 2).

    ``Sigma_0 ~ W_2(data_dof, sigma0_sq I)``, ``Sigma_i ~ W_2(data_dof, sigma_sq I)``,
    ``x_0 ~ N(0, Sigma_0)`` and ``x_i ~ N(x_0, Sigma_i)``, so that the stacked estimates
    have the covariance of eq. (56) of the journal (eq. (12) of the conference paper) about
    the common mean 0: diagonal blocks ``Sigma_0 + Sigma_i``, cross blocks ``Sigma_0``.

    Parameters
    ----------
    k : int
        Number of estimates (nodes), >= 2.
    sigma0_sq, sigma_sq : float
        Scales of the common and of the individual covariances, > 0.
    runs : int
        Independent runs, >= 1.
    rng : numpy.random.Generator, int or None, optional
        Randomness source.
    data_dof : int, optional
        Degrees of freedom of the Wishart draws: 3 in the journal (default), 4 in the
        conference paper.

    Returns
    -------
    FusionData
        Estimates, their covariances, the joint covariance (56) and the drawn ``x_0``.

    Raises
    ------
    ValueError
        ``k < 2``, ``runs < 1``, non-positive scales or ``data_dof < 2``.

    References
    ----------
    .. [1] Z. Weng and P. M. Djurić, journal version, eqs. (54)-(56).
    .. [2] Z. Weng and P. M. Djurić, EUSIPCO 2012, eqs. (11)-(12).

    Examples
    --------
    >>> import numpy as np
    >>> from cifilter.reproduce.weng import simulate_kalman_model
    >>> d = simulate_kalman_model(k=2, sigma0_sq=0.2, sigma_sq=1.0, runs=3, rng=0)
    >>> common = d.joint[:, :2, 2:]  # Sigma_0, also inside both diagonal blocks
    >>> bool(np.all(np.linalg.eigvalsh(d.Ps[:, 0] - common) > 0))
    True
    >>> d.xs.shape, d.x0.shape
    ((3, 2, 2), (3, 2))
    """
    k = check_int(k, "k", low=2)
    runs = check_int(runs, "runs", low=1)
    sigma0_sq = check_scalar(sigma0_sq, "sigma0_sq", low=0.0, low_open=True)
    sigma_sq = check_scalar(sigma_sq, "sigma_sq", low=0.0, low_open=True)
    data_dof = check_int(data_dof, "data_dof", low=DIM)
    rng = as_rng(rng)
    common = _wishart(rng, data_dof, sigma0_sq, DIM, (runs,))
    own = _wishart(rng, data_dof, sigma_sq, DIM, (runs, k))
    x0 = (np.linalg.cholesky(common) @ rng.standard_normal((runs, DIM, 1)))[..., 0]
    noise = (np.linalg.cholesky(own) @ rng.standard_normal((runs, k, DIM, 1)))[..., 0]
    xs = x0[:, None, :] + noise
    joint = np.tile(common, (1, k, k))
    for i in range(k):
        block = slice(i * DIM, (i + 1) * DIM)
        joint[:, block, block] += own[:, i]
    return FusionData(xs, _diagonal_blocks(joint, k), joint, x0)


def simulate_wishart_model(k, sigma_sq, runs, rng=None, data_dof=None):
    """Simulate the journal's model 1: a Wishart joint covariance, zero state.

    ``P_x ~ W_2k(data_dof, sigma_sq I)`` with ``data_dof = 3k`` by default and the
    stacked estimates ``x ~ N(0, P_x)``; the state is ``x_0 = 0``.

    Parameters
    ----------
    k : int
        Number of estimates (nodes), >= 2.
    sigma_sq : float
        Scale of the Wishart distribution, > 0.
    runs : int
        Independent runs, >= 1.
    rng : numpy.random.Generator, int or None, optional
        Randomness source.
    data_dof : int, optional
        Degrees of freedom, at least ``2k``; default ``3k`` (the journal's ``n = 3k``).

    Returns
    -------
    FusionData
        Estimates, their covariances, the joint covariance and ``x0 = 0``.

    Raises
    ------
    ValueError
        ``k < 2``, ``runs < 1``, ``sigma_sq <= 0`` or ``data_dof < 2k``.

    References
    ----------
    .. [1] Z. Weng and P. M. Djurić, journal version, Sec. V (model 1).

    Examples
    --------
    >>> from cifilter.reproduce.weng import simulate_wishart_model
    >>> d = simulate_wishart_model(k=2, sigma_sq=1.0, runs=5, rng=0)
    >>> d.xs.shape, d.Ps.shape, float(abs(d.x0).max())
    ((5, 2, 2), (5, 2, 2, 2), 0.0)
    """
    k = check_int(k, "k", low=2)
    runs = check_int(runs, "runs", low=1)
    sigma_sq = check_scalar(sigma_sq, "sigma_sq", low=0.0, low_open=True)
    data_dof = check_int(3 * k if data_dof is None else data_dof, "data_dof", low=DIM * k)
    rng = as_rng(rng)
    joint = _wishart(rng, data_dof, sigma_sq, DIM * k, (runs,))
    x = (np.linalg.cholesky(joint) @ rng.standard_normal((runs, DIM * k, 1)))[..., 0]
    return FusionData(x.reshape(runs, k, DIM), _diagonal_blocks(joint, k), joint,
                      np.zeros((runs, DIM)))


def compare_estimators(data, samples=100, dof=None, rng=None, estimators=ESTIMATORS):
    """Fuse every run of an experiment with each estimator (one batched call per estimator).

    Parameters
    ----------
    data : FusionData
        From :func:`simulate_kalman_model` or :func:`simulate_wishart_model`.
    samples : int, optional
        Monte Carlo samples M of the Bayesian rule (default 100).
    dof : float, optional
        Prior degrees of freedom of the Bayesian rule (default that of
        :func:`cifilter.bayesian_fusion`).
    rng : numpy.random.Generator, int or None, optional
        Randomness of the Bayesian rule.
    estimators : sequence of str, optional
        Any of ``"optimal"`` (:func:`cifilter.optimal_fusion` with the true joint
        covariance), ``"bayes"``, ``"ci-fast"`` (Niehsen), ``"ci-improved-fast"``
        (Franken & Hupper), ``"ci-det-ratio"`` (eq. (7) of the conference paper),
        ``"ci-trace"`` (trace-optimal CI) and ``"naive"``.

    Returns
    -------
    dict
        ``{name: fused means (runs, 2)}``.

    Raises
    ------
    ValueError
        An unknown estimator name.

    Examples
    --------
    >>> from cifilter.reproduce.weng import compare_estimators, simulate_wishart_model
    >>> d = simulate_wishart_model(k=2, sigma_sq=1.0, runs=50, rng=0)
    >>> fused = compare_estimators(d, samples=20, rng=1, estimators=("optimal", "bayes"))
    >>> sorted(fused), fused["bayes"].shape
    (['bayes', 'optimal'], (50, 2))
    """
    rng = as_rng(rng)
    return {name: _fuse(name, data.xs, data.Ps, data.joint, samples, dof, rng).x
            for name in estimators}


def _fuse(name, xs, Ps, joint, samples, dof, rng):
    """The FusionResult of one of the compared rules (names as in compare_estimators)."""
    if name == "optimal":
        return optimal_fusion(xs, joint)
    if name == "bayes":
        return bayesian_fusion(xs, Ps, dof=dof, samples=samples, rng=rng)
    if name == "naive":
        return naive_fusion(xs, Ps)
    if name == "ci-trace":
        return covariance_intersection(xs, Ps)
    if name in ("ci-fast", "ci-improved-fast", "ci-det-ratio"):
        return covariance_intersection(xs, Ps, omega=name[3:])
    raise ValueError(f"unknown estimator {name!r}; known: {', '.join(LABELS)}")


def _fmt(values):
    return ", ".join(f"{v:.3f}" for v in np.atleast_1d(values))


def _mse(fused, target):
    return {name: float(np.mean(np.sum((x - target) ** 2, axis=-1))) for name, x in fused.items()}


def repeated_fusion_nees(rounds=5, nodes=4, runs=2000, samples=100, rng=None,
                         estimators=("bayes", "ci-trace", "ci-fast", "naive")):
    """Mean NEES when the nodes of a ring fuse with their neighbours round after round.

    The k nodes' errors have the joint covariance ``P_x ~ W_2k(3k, I)`` (the journal's
    model 1, so the Bayesian prior with ``dof = 3k`` is exactly right for the first
    round). In every round each node fuses its current estimate with those of its two
    neighbours (three estimates) and replaces its estimate by the result; nobody tracks
    the cross-covariances the exchanges create. The NEES ``e^T P^-1 e`` of every node is
    averaged over nodes and runs; a consistent estimator of the 2-D state has mean NEES 2.

    Parameters
    ----------
    rounds : int, optional
        Fusion rounds, >= 1.
    nodes : int, optional
        Nodes in the ring, >= 3.
    runs : int, optional
        Independent runs, >= 1.
    samples : int, optional
        Monte Carlo samples of the Bayesian rule.
    rng : numpy.random.Generator, int or None, optional
        Randomness source.
    estimators : sequence of str, optional
        Rules to compare (names as in :func:`compare_estimators`, without ``"optimal"``).

    Returns
    -------
    dict
        ``{name: ndarray (rounds + 1,)}``, the mean NEES before fusion (round 0, the
        local estimates) and after each round.

    Raises
    ------
    ValueError
        Bad sizes or an unknown estimator.

    References
    ----------
    .. [1] Z. Weng and P. M. Djurić, journal version, Sec. VI: "Multiple fusions by using
       the proposed method leads to overconfident estimation".

    Examples
    --------
    >>> from cifilter.reproduce.weng import repeated_fusion_nees
    >>> nees = repeated_fusion_nees(rounds=2, runs=50, samples=20, rng=0,
    ...                             estimators=("bayes", "ci-trace"))
    >>> nees["bayes"].shape
    (3,)
    """
    rounds = check_int(rounds, "rounds", low=1)
    nodes = check_int(nodes, "nodes", low=3)
    if "optimal" in estimators:
        raise ValueError("repeated fusion has no 'optimal' rule: nobody knows the correlations")
    rng = as_rng(rng)
    data = simulate_wishart_model(nodes, 1.0, runs, rng)
    left, right = np.roll(np.arange(nodes), 1), np.roll(np.arange(nodes), -1)
    result = {}
    for name in estimators:
        x, P = data.xs, data.Ps  # the errors are x itself: the state is 0
        nees = [_mean_nees(x, P)]
        for _ in range(rounds):
            xs = np.stack([x, x[:, left], x[:, right]], axis=-2)  # own estimate first
            Ps = np.stack([P, P[:, left], P[:, right]], axis=-3)
            r = _fuse(name, xs, Ps, None, samples, 3 * nodes, rng)
            x, P = r.x, r.P
            nees.append(_mean_nees(x, P))
        result[name] = np.array(nees)
    return result


def _mean_nees(x, P):
    return float(np.mean(np.einsum("...i,...i->...", x, np.linalg.solve(P, x[..., None])[..., 0])))


# --------------------------------------------------------------------------- experiments
class _Config(NamedTuple):
    model: str  # "kalman" or "wishart"
    k: int
    sigma0_sq: float
    sigma_sq: float
    runs: int
    samples: int
    prior_dof: float
    data_dof: int


def _simulate(config, rng):
    if config.model == "kalman":
        return simulate_kalman_model(config.k, config.sigma0_sq, config.sigma_sq, config.runs,
                                     rng, config.data_dof)
    return simulate_wishart_model(config.k, config.sigma_sq, config.runs, rng, config.data_dof)


def _mse_by_target(fused, data, model):
    """{target: {estimator: MSE}}: the common mean 0, and for the Kalman model the drawn x0."""
    result = {"mean": _mse(fused, 0.0)}
    if model == "kalman":
        result["x0"] = _mse(fused, data.x0)
    return result


class _Runner:
    """Runs configurations once each (figures share some) and times them."""

    def __init__(self, rng):
        self.rng, self.cache, self.times = rng, {}, []

    def __call__(self, config):
        if config not in self.cache:
            start = time.perf_counter()
            data = _simulate(config, self.rng)
            fused = compare_estimators(data, config.samples, config.prior_dof, self.rng)
            self.cache[config] = _mse_by_target(fused, data, config.model)
            self.times.append((config, time.perf_counter() - start))
        return self.cache[config]


def _print_table(title, axis_name, axis_values, results, target, out):
    """MSE of every estimator and its ratio to the optimal MSE, one row per sweep value."""
    print(f"\n{title}", file=out)
    head = f"{axis_name:>9} " + " ".join(f"{LABELS[e]:>9}" for e in ESTIMATORS)
    head += "  | " + " ".join(f"{LABELS[e]:>9}" for e in ESTIMATORS[1:])
    print(head + "\n" + f"{'':>9} {'MSE':^{10 * len(ESTIMATORS) - 1}}  | "
          f"{'MSE / optimal MSE':^{10 * (len(ESTIMATORS) - 1) - 1}}", file=out)
    for value, result in zip(axis_values, results):
        mse = result[target]
        line = f"{value:>9g} " + " ".join(f"{mse[e]:>9.4f}" for e in ESTIMATORS)
        line += "  | " + " ".join(f"{mse[e] / mse['optimal']:>9.3f}" for e in ESTIMATORS[1:])
        print(line, file=out)


def _ratios(results, a, b, target):
    return np.array([r[target][a] / r[target][b] for r in results])


def _span(values):
    values = np.asarray(values)
    return f"{values.min():.3f} to {values.max():.3f}"


class _Claims:
    """Prints each claim of the text with the paper's statement and our numbers; keeps a list."""

    def __init__(self, out):
        self.out, self.rows = out, []

    def add(self, where, text, paper, ours, holds):
        holds = bool(holds)
        print(f"  [{'holds' if holds else 'FAILS'}] {text}\n      paper: {paper}\n"
              f"      ours:  {ours}", file=self.out)
        self.rows.append((where, text, holds))

    def summary(self):
        print("\n" + "=" * 100 + "\nSummary of the claims", file=self.out)
        for where, text, holds in self.rows:
            print(f"  {'holds' if holds else 'FAILS':<6} {where:<34} {text}", file=self.out)


FAST_CI = ("ci-fast", "ci-improved-fast", "ci-det-ratio")


def _ordering_claims(claims, where, results, target, gap_paper, gap_range):
    """optimal < Bayesian < each fast CI at every point; the size of the Bayesian-optimal gap."""
    bayes_opt = _ratios(results, "bayes", "optimal", target)
    claims.add(where, "optimal < Bayesian at every point", "the optimal method works best",
               f"Bayesian / optimal = {_span(bayes_opt)}", np.all(bayes_opt > 1))
    for ci in FAST_CI:
        ratio = _ratios(results, "bayes", ci, target)
        claims.add(where, f"Bayesian < {LABELS[ci]} at every point",
                   "much better than the (fast) CI", f"Bayesian / {LABELS[ci]} = {_span(ratio)}",
                   np.all(ratio < 1))
    gap = np.mean(bayes_opt - 1)
    claims.add(where, "size of the Bayesian-optimal gap (mean within a factor 2)", gap_paper,
               f"Bayesian / optimal - 1 = {_span(bayes_opt - 1)}, mean {gap:.3f}",
               gap_range[0] <= gap <= gap_range[1])


def _heading(text, out):
    print("\n" + "=" * 100 + "\n" + text, file=out)


def _target_name(target):
    return "the common mean 0" if target == "mean" else "the drawn x0"


# --------------------------------------------------------------------------- sections
def _conference(args, runner, claims, out, figures):
    """EUSIPCO 2012, Figs. 1-2: two 2-D estimates, Sigma's from W(4, .), 200 runs, M = 500."""
    _heading(f"EUSIPCO 2012, Figs. 1-2 (two estimates, data Wishart dof 4, "
             f"{args.conference_runs} runs, M = {args.conference_samples})\n"
             "The paper's Theorem 1 draws S ~ W_2(n) with n = 4; by Lemma 3 that is the "
             "conditional of a prior with dof n + 2 = 6\n(the journal's S ~ W(n - l_1)). "
             "Both readings of 'n = 4' are run: prior dof 6 (the paper's sampler) and 4.", out)
    sweeps = {}
    for dof in (6.0, 4.0):
        for fig, axis_name in (("1", "sigma0^2"), ("2", "sigma^2")):
            configs = [
                _Config("kalman", 2, v if fig == "1" else 0.2, 1.0 if fig == "1" else v,
                        args.conference_runs, args.conference_samples, dof, 4)
                for v in GRID
            ]
            results = [runner(c) for c in configs]
            sweeps[f"Fig. {fig}, prior dof {dof:g}"] = (axis_name, GRID, results)
            for target in ("mean", "x0"):
                fixed = "sigma^2 = 1" if fig == "1" else "sigma0^2 = 0.2"
                _print_table(f"Fig. {fig}, prior dof {dof:g}, error against "
                             f"{_target_name(target)} ({fixed})",
                             axis_name, GRID, results, target, out)
                _ordering_claims(claims, f"conf. Fig. {fig}, dof {dof:g}, vs {target}", results,
                                 target, "Bayesian about 20% worse than optimal", ABOUT_20)
    figures.append(("conference", sweeps))


def _model1(args, runner, claims, out, figures):
    """Journal model 1, Figs. 2-4: P_x ~ W_2k(3k, sigma^2 I), k = 2, 3, prior dof 3k."""
    _heading(f"Journal model 1, Figs. 2-4 (P_x ~ W(3k, sigma^2 I), prior dof 3k, "
             f"M = {args.samples}, {args.runs} runs)", out)
    sweeps = {}
    for k in (2, 3):
        configs = [_Config("wishart", k, 0.0, v, args.runs, args.samples, 3.0 * k, 3 * k)
                   for v in GRID]
        results = [runner(c) for c in configs]
        sweeps[f"Fig. {k} (k = {k})"] = ("sigma^2", GRID, results)
        _print_table(f"Fig. {k} (k = {k}): MSE against sigma^2", "sigma^2", GRID, results,
                     "mean", out)
        bayes_opt = _ratios(results, "bayes", "optimal", "mean")
        claims.add(f"model 1 Fig. {k}", "optimal < Bayesian at every point",
                   "the optimal method works best", f"Bayesian / optimal = {_span(bayes_opt)}",
                   np.all(bayes_opt > 1))
        for ci in FAST_CI:
            gain = 1 - _ratios(results, "bayes", ci, "mean")
            claims.add(f"model 1 Fig. {k}", f"Bayesian roughly 10% better than {LABELS[ci]} "
                       "(mean within a factor 2)",
                       "roughly 10% better than the CI method",
                       f"1 - Bayesian / {LABELS[ci]} = {_span(gain)}, mean {gain.mean():.3f}",
                       ROUGHLY_10[0] <= gain.mean() <= ROUGHLY_10[1])
    normalised = {k: {e: _ratios(sweeps[f"Fig. {k} (k = {k})"][2], e, "optimal", "mean").mean()
                      for e in ("bayes",) + FAST_CI} for k in (2, 3)}
    print("\nFig. 4: normalised MSE (MSE / optimal MSE, mean over the sweep; in model 1 it does "
          "not depend on sigma^2)", file=out)
    for k in (2, 3):
        print(f"  k = {k}: " + ", ".join(f"{LABELS[e]} {v:.3f}" for e, v in normalised[k].items()),
              file=out)
    for k in (2, 3):
        best_ci = min(normalised[k][ci] for ci in FAST_CI)
        claims.add("model 1 Fig. 4", f"k = {k}: the Bayesian estimator outperforms CI",
                   "the proposed estimator outperforms the other",
                   f"Bayesian {normalised[k]['bayes']:.3f}, best fast CI {best_ci:.3f}",
                   normalised[k]["bayes"] < best_ci)
    claims.add("model 1 Fig. 4", "the gap to the optimal grows with the number of nodes",
               "the gap between the optimal estimator and the others becomes larger",
               f"Bayesian / optimal {normalised[2]['bayes']:.3f} (k = 2) -> "
               f"{normalised[3]['bayes']:.3f} (k = 3)",
               normalised[3]["bayes"] > normalised[2]["bayes"])
    figures.append(("model1", sweeps))


def _model2(args, runner, claims, out, figures):
    """Journal model 2, Figs. 5-8: the Kalman model with Wishart dof 3, k = 2, 3."""
    dof_text = "3k" if args.model2_dof is None else f"{args.model2_dof:g}"
    _heading(f"Journal model 2, Figs. 5-8 (Kalman model, data Wishart dof 3, prior dof "
             f"{dof_text}, M = {args.samples}, {args.runs} runs)", out)
    sweeps = {}
    for fig, axis_name in (("5", "sigma0^2"), ("6", "sigma^2")):
        for k in (2, 3):
            dof = 3.0 * k if args.model2_dof is None else args.model2_dof
            configs = [
                _Config("kalman", k, v if fig == "5" else 0.2, 1.0 if fig == "5" else v,
                        args.runs, args.samples, dof, 3)
                for v in GRID
            ]
            sweeps[(fig, k)] = (axis_name, GRID, [runner(c) for c in configs])
    for target in ("mean", "x0"):
        print(f"\n--- error measured against {_target_name(target)}", file=out)
        for (fig, k), (axis_name, values, results) in sweeps.items():
            fixed = "sigma^2 = 1" if fig == "5" else "sigma0^2 = 0.2"
            _print_table(f"Fig. {fig}, k = {k}: MSE against {axis_name} ({fixed})",
                         axis_name, values, results, target, out)
            _ordering_claims(claims, f"model 2 Fig. {fig}, k = {k}, vs {target}", results,
                             target, "Bayesian about 20% worse than optimal", ABOUT_20)
        print(f"\n  across k and the sweeps (error against {_target_name(target)}):", file=out)
        for fig in ("5", "6"):
            mse2 = np.array([r[target]["bayes"] for r in sweeps[(fig, 2)][2]])
            mse3 = np.array([r[target]["bayes"] for r in sweeps[(fig, 3)][2]])
            claims.add(f"model 2 Fig. {fig}, vs {target}", "three nodes: lower MSE than two",
                       "three nodes lead to better estimation than two",
                       f"Bayesian MSE(k=3) / MSE(k=2) = {_span(mse3 / mse2)}",
                       np.all(mse3 < mse2))
        for fig, trend, sign in (("6", "lower with increasing sigma^2", -1),
                                 ("5", "higher with increasing sigma0^2", +1)):
            for k in (2, 3):
                norm = _ratios(sweeps[(fig, k)][2], "bayes", "optimal", target)
                claims.add(f"model 2 Fig. {'7' if fig == '6' else '8'}, k = {k}, vs {target}",
                           f"normalised MSE {trend}",
                           "better with increasing sigma^2, worse with increasing sigma0^2",
                           f"Bayesian / optimal = {_fmt(norm)}", np.all(sign * np.diff(norm) > 0))
        for fig in ("5", "6"):
            n2 = _ratios(sweeps[(fig, 2)][2], "bayes", "optimal", target)
            n3 = _ratios(sweeps[(fig, 3)][2], "bayes", "optimal", target)
            claims.add(f"model 2 Figs. 7-8 ({'sigma0^2' if fig == '5' else 'sigma^2'}), "
                       f"vs {target}", "normalised MSE worse for three nodes",
                       "deteriorates with the increase in the number of nodes",
                       f"k = 2: {_fmt(n2)}; k = 3: {_fmt(n3)}", np.all(n3 > n2))
    figures.append(("model2", {f"Fig. {fig}, k = {k}": sweep
                               for (fig, k), sweep in sweeps.items()}))


def _nodes(args, runner, claims, out, figures):
    """Journal Fig. 9: MSE against the number of nodes, both models."""
    _heading(f"Journal Fig. 9: MSE against the number of nodes k (model 1 sigma^2 = 1; model 2 "
             f"sigma^2 = 1, sigma0^2 = 0.2; {args.runs} runs)", out)
    sweeps = {}
    for model in ("wishart", "kalman"):
        configs = []
        for k in NODES:
            dof = 3.0 * k if model == "wishart" or args.model2_dof is None else args.model2_dof
            configs.append(_Config(model, k, 0.2 if model == "kalman" else 0.0, 1.0, args.runs,
                                   args.samples, dof, 3 * k if model == "wishart" else 3))
        sweeps[model] = ("k", NODES, [runner(c) for c in configs])
        for target in ("mean",) if model == "wishart" else ("mean", "x0"):
            _print_table(f"{'model 1' if model == 'wishart' else 'model 2'}, error against "
                         f"{_target_name(target)}", "k", NODES, sweeps[model][2], target, out)
    n1 = _ratios(sweeps["wishart"][2], "bayes", "optimal", "mean")
    for target in ("mean", "x0"):
        n2 = _ratios(sweeps["kalman"][2], "bayes", "optimal", target)
        claims.add(f"Fig. 9, model 2 vs {target}", "Bayesian works better in model 2",
                   "the proposed algorithm works better in model 2",
                   f"Bayesian / optimal: model 1 {_fmt(n1)}; model 2 {_fmt(n2)}",
                   np.all(n2 < n1))
    figures.append(("nodes", {f"Fig. 9, model {1 if model == 'wishart' else 2}": sweep
                              for model, sweep in sweeps.items()}))


def _samples(args, rng, claims, out, figures):
    """Journal Fig. 10: MSE of the Bayesian estimator against M (five nodes, model 2)."""
    k = 5
    dof = 3.0 * k if args.model2_dof is None else args.model2_dof
    _heading(f"Journal Fig. 10: MSE against the number of samples M (model 2, k = {k}, "
             f"sigma^2 = 1, sigma0^2 = 0.2, prior dof {dof:g}, {args.runs} runs; the same data "
             "for every M)", out)
    data = simulate_kalman_model(k, 0.2, 1.0, args.runs, rng, 3)
    reference = _mse_by_target(compare_estimators(data, rng=rng, estimators=("optimal",)),
                               data, "kalman")
    rows = []
    for M in SAMPLE_SIZES:
        start = time.perf_counter()
        fused = compare_estimators(data, M, dof, rng, estimators=("bayes",))
        rows.append((M, _mse_by_target(fused, data, "kalman"), time.perf_counter() - start))
    print(f"{'M':>6} {'MSE vs 0':>10} {'MSE vs x0':>10} {'/ optimal':>10} {'time [s]':>9}",
          file=out)
    for M, mse, seconds in rows:
        print(f"{M:>6} {mse['mean']['bayes']:>10.4f} {mse['x0']['bayes']:>10.4f} "
              f"{mse['x0']['bayes'] / reference['x0']['optimal']:>10.3f} {seconds:>9.2f}",
              file=out)
    print(f"optimal: {reference['mean']['optimal']:.4f} (vs 0), "
          f"{reference['x0']['optimal']:.4f} (vs x0); '/ optimal' is against x0", file=out)
    by_m = {M: mse["x0"]["bayes"] for M, mse, _ in rows}
    if 100 in by_m and max(by_m) > 100:
        gain = 1 - by_m[max(by_m)] / by_m[100]
        claims.add("Fig. 10", "100 samples are almost enough",
                   "100 samples are almost enough for the Monte Carlo method",
                   f"M = 100 -> {max(by_m)} lowers the MSE (vs x0) by {100 * gain:.2f}%",
                   abs(gain) < 0.02)
    figures.append(("samples", (rows, reference)))


def _dof_sensitivity(args, rng, out):
    """The prior dof as belief about correlation: MSE and NEES against dof on fixed data."""
    _heading(f"Prior degrees of freedom (k = 2, {args.runs} runs, M = {args.samples}; the same "
             "data for every dof). NEES of a consistent P: 2", out)
    for model in ("wishart", "kalman"):
        data = (simulate_wishart_model(2, 1.0, args.runs, rng) if model == "wishart"
                else simulate_kalman_model(2, 0.2, 1.0, args.runs, rng, 3))
        base = _mse(compare_estimators(data, rng=rng, estimators=("optimal", "ci-det-ratio")),
                    0.0)
        print(f"\n{'model 1 (data dof 6)' if model == 'wishart' else 'model 2 (vs 0)'}: "
              f"optimal {base['optimal']:.4f}, CI det {base['ci-det-ratio']:.4f}", file=out)
        print(f"{'dof':>6} {'Bayesian MSE':>13} {'/ optimal':>10} {'mean NEES':>10}", file=out)
        for dof in (4.5, 5.0, 6.0, 8.0, 12.0, 24.0, 100.0):
            r = bayesian_fusion(data.xs, data.Ps, dof=dof, samples=args.samples, rng=rng)
            mse = float(np.mean(np.sum(r.x**2, axis=-1)))
            print(f"{dof:>6g} {mse:>13.4f} {mse / base['optimal']:>10.3f} "
                  f"{_mean_nees(r.x, r.P):>10.3f}", file=out)


def _nees(args, rng, claims, out, figures):
    """Repeated fusion in a ring: NEES of Bayesian fusion against CI (journal Sec. VI)."""
    runs = max(1, args.runs // 5)
    _heading("Repeated fusion (journal Sec. VI): ring of 4 nodes, each fuses itself and its two "
             f"neighbours every round;\nP_x ~ W_8(12, I), prior dof 12, M = {args.samples}, "
             f"{runs} runs. Mean NEES; consistent = 2.", out)
    nees = repeated_fusion_nees(rounds=5, nodes=4, runs=runs, samples=args.samples, rng=rng)
    print(f"{'round':>6} " + " ".join(f"{LABELS[name]:>10}" for name in nees), file=out)
    for r in range(6):
        print(f"{r:>6} " + " ".join(f"{values[r]:>10.3f}" for values in nees.values()),
              file=out)
    bayes, ci = nees["bayes"], nees["ci-trace"]
    claims.add("repeated fusion", "Bayesian NEES grows round after round, CI's does not",
               "multiple fusions lead to overconfident estimation; CI stays the same",
               f"Bayesian {_fmt(bayes)}; CI trace {_fmt(ci)}",
               np.all(np.diff(bayes[1:]) > 0) and bayes[-1] > 4 and ci[-1] <= 1.05 * ci[1])
    figures.append(("nees", nees))


# --------------------------------------------------------------------------- figures
def _plot(figures, directory, out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    styles = dict(zip(ESTIMATORS, ("k-", "C0-", "C5-.", "C1--", "C2--", "C3--", "C4:")))
    written = []

    def sweep_panel(ax, axis_name, values, results, title):
        target = "x0" if "x0" in results[0] else "mean"
        for e in ESTIMATORS:
            ax.plot(values, [r[target][e] for r in results], styles[e], label=LABELS[e])
        ax.set(xscale="log", yscale="log", xlabel=axis_name, title=title,
               ylabel=f"MSE against {'x0' if target == 'x0' else '0'}")

    for name, content in figures:
        if name in ("conference", "model1", "model2", "nodes"):
            panels = list(content.items())
            fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8),
                                     layout="constrained", squeeze=False)
            for ax, (title, (axis_name, values, results)) in zip(axes[0], panels):
                sweep_panel(ax, axis_name, values, results, title)
            axes[0, 0].legend(fontsize="small")
        elif name == "samples":
            rows, reference = content
            fig, ax = plt.subplots(figsize=(5, 3.8), layout="constrained")
            ax.plot([r[0] for r in rows], [r[1]["x0"]["bayes"] for r in rows], "C0o-",
                    label="Bayesian")
            ax.axhline(reference["x0"]["optimal"], color="k", label="optimal")
            ax.set(xscale="log", yscale="log", xlabel="samples M", ylabel="MSE against x0",
                   title="Fig. 10 (k = 5, model 2)")
            ax.legend()
        else:  # nees
            fig, ax = plt.subplots(figsize=(5, 3.8), layout="constrained")
            for method, values in content.items():
                ax.plot(range(len(values)), values, "o-", label=LABELS[method])
            ax.axhline(2.0, color="k", lw=0.8, ls="--", label="consistent")
            ax.set(yscale="log", xlabel="fusion round", ylabel="mean NEES",
                   title="repeated fusion in a ring")
            ax.legend()
        path = directory / f"weng_{name}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    print("\nfigures written: " + ", ".join(map(str, written)), file=out)


# --------------------------------------------------------------------------- command line
SECTIONS = ("conference", "model1", "model2", "nodes", "samples", "dof", "nees")


def add_arguments(parser):
    """Options of ``python -m cifilter reproduce weng``."""
    parser.add_argument("--runs", type=int, default=10_000,
                        help="runs per journal configuration (default 10000, as the journal)")
    parser.add_argument("--samples", type=int, default=100,
                        help="Monte Carlo samples M of the journal's experiments (default 100)")
    parser.add_argument("--conference-runs", type=int, default=200,
                        help="runs per conference configuration (default 200)")
    parser.add_argument("--conference-samples", type=int, default=500,
                        help="samples M of the conference experiments (default 500)")
    parser.add_argument("--model2-dof", type=float, default=None,
                        help="prior dof of the Bayesian rule in model 2 (default 3k, the "
                             "journal's model-1 value; the journal does not state it)")
    parser.add_argument("--only", default=",".join(SECTIONS),
                        help=f"comma-separated sections (default all): {', '.join(SECTIONS)}")
    parser.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    parser.add_argument("--figures", metavar="DIR", help="write PNG figures to DIR")


def run(args, out=None):
    """Run the selected sections and print every number next to the papers' statements."""
    out = sys.stdout if out is None else out
    sections = [s.strip() for s in args.only.split(",") if s.strip()]
    unknown = sorted(set(sections) - set(SECTIONS))
    if unknown:
        raise SystemExit(f"unknown section(s) {', '.join(unknown)}; known: {', '.join(SECTIONS)}")
    rng = as_rng(args.seed)
    runner, claims, figures = _Runner(rng), _Claims(out), []
    start = time.perf_counter()
    for section in sections:
        if section == "conference":
            _conference(args, runner, claims, out, figures)
        elif section == "model1":
            _model1(args, runner, claims, out, figures)
        elif section == "model2":
            _model2(args, runner, claims, out, figures)
        elif section == "nodes":
            _nodes(args, runner, claims, out, figures)
        elif section == "samples":
            _samples(args, rng, claims, out, figures)
        elif section == "dof":
            _dof_sensitivity(args, rng, out)
        else:
            _nees(args, rng, claims, out, figures)
    if claims.rows:
        claims.summary()
    if runner.times:
        seconds = np.array([t for _, t in runner.times])
        total = time.perf_counter() - start
        print(f"\n{len(seconds)} configurations, {seconds.min():.1f} to {seconds.max():.1f} s "
              f"each (median {np.median(seconds):.1f} s); total {total:.0f} s", file=out)
    if args.figures:
        _plot(figures, args.figures, out)
    return 0
