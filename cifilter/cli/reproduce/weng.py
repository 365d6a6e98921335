"""Weng & Djurić: Bayesian Monte Carlo fusion against optimal fusion and fast CI.

Reproduces the experiments of the EUSIPCO 2012 paper (Figs. 1-2) and of the journal version
(model 1, Figs. 2-4; model 2, Figs. 5-8; Fig. 9, MSE against the number of nodes; Fig. 10,
MSE against the number of samples M), adds the repeated-fusion NEES experiment the
journal's discussion describes in words, and prints every number next to the papers'
statements. The figures themselves are missing from the papers' text: what can be
compared are the claims the text makes about them (orderings and sizes of gaps).

Every configuration is a batched computation over the runs (the Bayesian rule draws
``runs x M`` joint covariances at once). The runs go through :func:`cifilter.montecarlo.run`
in chunks (``--workers N`` or ``--scheduler ADDRESS`` spread them over a Dask cluster, with
the same numbers). Every claim is judged with its Monte Carlo standard error: a difference
within two standard errors is reported as "inconclusive at this size", not as a failure.

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

import argparse
import sys
import time
import zlib
from collections.abc import Sequence
from typing import Any, NamedTuple, Optional, TextIO, Union

import numpy as np
from numpy.typing import NDArray

from ..._numerics.validation import as_rng, check_int, check_scalar
from ...rules.bayes import bayesian_fusion
from ...rules.ci import covariance_intersection
from ...rules.optimal import naive_fusion, optimal_fusion
from ..args import positive_float, positive_int
from ._checks import Claims, Estimate, mean_of
from ._common import add_common_arguments, parallel_client, run_study

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
    >>> from cifilter.cli.reproduce.weng import simulate_wishart_model
    >>> simulate_wishart_model(k=3, sigma_sq=1.0, runs=4, rng=0).joint.shape
    (4, 6, 6)
    """

    xs: NDArray[np.float64]
    Ps: NDArray[np.float64]
    joint: NDArray[np.float64]
    x0: NDArray[np.float64]


def _wishart(rng, dof, scale, dim, shape):
    """Draws of W_dim(dof, scale I) for an integer dof (sums of outer products)."""
    Z = rng.standard_normal(shape + (dof, dim))
    return scale * (np.swapaxes(Z, -1, -2) @ Z)


def _diagonal_blocks(joint, k):
    return np.stack([joint[..., i * DIM:(i + 1) * DIM, i * DIM:(i + 1) * DIM]
                     for i in range(k)], axis=-3)


def simulate_kalman_model(k: int, sigma0_sq: float, sigma_sq: float, runs: int,
                          rng: Optional[Union[int, np.random.Generator]] = None,
                          data_dof: int = 3) -> FusionData:
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
    >>> from cifilter.cli.reproduce.weng import simulate_kalman_model
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


def simulate_wishart_model(k: int, sigma_sq: float, runs: int,
                           rng: Optional[Union[int, np.random.Generator]] = None,
                           data_dof: Optional[int] = None) -> FusionData:
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
    >>> from cifilter.cli.reproduce.weng import simulate_wishart_model
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


def compare_estimators(data: FusionData, samples: int = 100, dof: Optional[float] = None,
                       rng: Optional[Union[int, np.random.Generator]] = None,
                       estimators: Sequence[str] = ESTIMATORS) -> dict[str, NDArray[np.float64]]:
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
    >>> from cifilter.cli.reproduce.weng import compare_estimators, simulate_wishart_model
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


def repeated_fusion_nees(rounds: int = 5, nodes: int = 4, runs: int = 2000, samples: int = 100,
                         rng: Optional[Union[int, np.random.Generator]] = None,
                         estimators: Sequence[str] = ("bayes", "ci-trace", "ci-fast", "naive"),
                         ) -> dict[str, NDArray[np.float64]]:
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
    >>> from cifilter.cli.reproduce.weng import repeated_fusion_nees
    >>> nees = repeated_fusion_nees(rounds=2, runs=50, samples=20, rng=0,
    ...                             estimators=("bayes", "ci-trace"))
    >>> nees["bayes"].shape
    (3,)
    """
    per_run = _repeated_fusion_nees_per_run(rounds, nodes, runs, samples, rng, estimators)
    return {name: values.mean(axis=0) for name, values in per_run.items()}


def _repeated_fusion_nees_per_run(rounds, nodes, runs, samples, rng, estimators):
    """``{name: (runs, rounds + 1)}``: every run's NEES averaged over the nodes."""
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
        nees = [_nees_per_run(x, P)]
        for _ in range(rounds):
            xs = np.stack([x, x[:, left], x[:, right]], axis=-2)  # own estimate first
            Ps = np.stack([P, P[:, left], P[:, right]], axis=-3)
            r = _fuse(name, xs, Ps, None, samples, 3 * nodes, rng)
            x, P = r.x, r.P
            nees.append(_nees_per_run(x, P))
        result[name] = np.stack(nees, axis=-1)
    return result


def _nees_per_run(x, P):
    """NEES ``x^T P^-1 x`` averaged over every axis but the first (the runs)."""
    nees = np.einsum("...i,...i->...", x, np.linalg.solve(P, x[..., None])[..., 0])
    return nees.reshape(len(nees), -1).mean(axis=1)



# --------------------------------------------------------------------------- experiments
class _Config(NamedTuple):
    model: str  # "kalman" or "wishart"
    k: int
    sigma0_sq: float
    sigma_sq: float
    samples: int
    prior_dof: float
    data_dof: int


def _config_key(config):
    """A stable integer per configuration (its random stream does not depend on the others)."""
    return zlib.crc32(repr(tuple(config)).encode())


def _simulate(config, runs, rng):
    if config.model == "kalman":
        return simulate_kalman_model(config.k, config.sigma0_sq, config.sigma_sq, runs,
                                     rng, config.data_dof)
    return simulate_wishart_model(config.k, config.sigma_sq, runs, rng, config.data_dof)


def _targets(model):
    return ("mean", "x0") if model == "kalman" else ("mean",)


def _configs_study(rng, runs, configs):
    """Monte Carlo study: every run's squared error of every estimator in every configuration.

    Keys ``"{i}/{target}/{estimator}"`` (runs,) and ``"{i}/seconds"`` (the chunk's time of
    configuration i spread over its runs). Configuration i draws from its own generator,
    seeded by the chunk's generator and the configuration itself, so its numbers do not
    depend on which other configurations are in the list.
    """
    base = [int(v) for v in rng.integers(0, 2**63 - 1, size=2)]
    out = {}
    for i, config in enumerate(configs):
        start = time.perf_counter()
        own = np.random.default_rng(base + [_config_key(config)])
        data = _simulate(config, runs, own)
        fused = compare_estimators(data, config.samples, config.prior_dof, own)
        for target in _targets(config.model):
            truth = 0.0 if target == "mean" else data.x0
            for name, x in fused.items():
                out[f"{i}/{target}/{name}"] = np.sum((x - truth) ** 2, axis=-1)
        out[f"{i}/seconds"] = np.full(runs, (time.perf_counter() - start) / runs)
    return out


def _run_configs(configs, runs, label, key, args, client):
    """``{config: {target: {estimator: MSE Estimate}}}`` and the compute seconds per config."""
    configs = list(dict.fromkeys(configs))  # unique, in order
    arrays = run_study(_configs_study, label, runs, args.seed, key, client, configs=configs)
    results, seconds = {}, []
    for i, config in enumerate(configs):
        results[config] = {target: {e: Estimate.mean(arrays[f"{i}/{target}/{e}"])
                                    for e in ESTIMATORS}
                           for target in _targets(config.model)}
        seconds.append(float(arrays[f"{i}/seconds"].sum()))
    return results, seconds


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
    return [r[target][a] / r[target][b] for r in results]


def _floats(values):
    return np.array([float(v) for v in values])


def _span(values):
    values = _floats(values)
    return f"{values.min():.3f} to {values.max():.3f}"


def _fmt_floats(values):
    return ", ".join(f"{v:.3f}" for v in _floats(values))


def _labelled(axis_name, axis_values, margins):
    return [(f"{axis_name} = {v:g}", m) for v, m in zip(axis_values, margins)]


def _within(estimate, low, high):
    """Margins of ``low <= estimate <= high``."""
    return [("the lower end", estimate - low), ("the upper end", high - estimate)]


FAST_CI = ("ci-fast", "ci-improved-fast", "ci-det-ratio")


def _ordering_claims(claims, where, axis, results, target, gap_paper, gap_range):
    """optimal < Bayesian < each fast CI at every point; the size of the Bayesian-optimal gap."""
    axis_name, axis_values = axis
    bayes_opt = _ratios(results, "bayes", "optimal", target)
    claims.add(where, "optimal < Bayesian at every point", "the optimal method works best",
               f"Bayesian / optimal = {_span(bayes_opt)}",
               _labelled(axis_name, axis_values, [r - 1 for r in bayes_opt]))
    for ci in FAST_CI:
        ratio = _ratios(results, "bayes", ci, target)
        claims.add(where, f"Bayesian < {LABELS[ci]} at every point",
                   "much better than the (fast) CI", f"Bayesian / {LABELS[ci]} = {_span(ratio)}",
                   _labelled(axis_name, axis_values, [1 - r for r in ratio]))
    gap = mean_of(r - 1 for r in bayes_opt)
    claims.add(where, "size of the Bayesian-optimal gap (mean within a factor 2)", gap_paper,
               f"Bayesian / optimal - 1 = {_span([r - 1 for r in bayes_opt])}, "
               f"mean {gap:.3f} +/- {gap.se:.3f}", _within(gap, *gap_range))


def _heading(text, out):
    print("\n" + "=" * 100 + "\n" + text, file=out)


def _target_name(target):
    return "the common mean 0" if target == "mean" else "the drawn x0"


# --------------------------------------------------------------------------- sections
def _conference_configs(args):
    """Figs. 1-2 of the conference paper, both readings of its prior dof."""
    sweeps = {}
    for dof in (6.0, 4.0):
        for fig in ("1", "2"):
            sweeps[(dof, fig)] = [
                _Config("kalman", 2, v if fig == "1" else 0.2, 1.0 if fig == "1" else v,
                        args.conference_samples, dof, 4)
                for v in GRID
            ]
    return sweeps


def _conference(args, results, claims, out, figures):
    """EUSIPCO 2012, Figs. 1-2: two 2-D estimates, Sigma's from W(4, .), 200 runs, M = 500."""
    _heading(f"EUSIPCO 2012, Figs. 1-2 (two estimates, data Wishart dof 4, "
             f"{args.conference_runs} runs, M = {args.conference_samples})\n"
             "The paper's Theorem 1 draws S ~ W_2(n) with n = 4; by Lemma 3 that is the "
             "conditional of a prior with dof n + 2 = 6\n(the journal's S ~ W(n - l_1)). "
             "Both readings of 'n = 4' are run: prior dof 6 (the paper's sampler) and 4.", out)
    sweeps = {}
    for (dof, fig), configs in _conference_configs(args).items():
        axis_name = "sigma0^2" if fig == "1" else "sigma^2"
        sweep = [results[c] for c in configs]
        sweeps[f"Fig. {fig}, prior dof {dof:g}"] = (axis_name, GRID, sweep)
        for target in ("mean", "x0"):
            fixed = "sigma^2 = 1" if fig == "1" else "sigma0^2 = 0.2"
            _print_table(f"Fig. {fig}, prior dof {dof:g}, error against "
                         f"{_target_name(target)} ({fixed})",
                         axis_name, GRID, sweep, target, out)
            _ordering_claims(claims, f"conf. Fig. {fig}, dof {dof:g}, vs {target}",
                             (axis_name, GRID), sweep, target,
                             "Bayesian about 20% worse than optimal", ABOUT_20)
    figures.append(("conference", sweeps))


def _model1_configs(args):
    return {k: [_Config("wishart", k, 0.0, v, args.samples, 3.0 * k, 3 * k) for v in GRID]
            for k in (2, 3)}


def _model1(args, results, claims, out, figures):
    """Journal model 1, Figs. 2-4: P_x ~ W_2k(3k, sigma^2 I), k = 2, 3, prior dof 3k."""
    _heading(f"Journal model 1, Figs. 2-4 (P_x ~ W(3k, sigma^2 I), prior dof 3k, "
             f"M = {args.samples}, {args.runs} runs)", out)
    sweeps = {}
    for k, configs in _model1_configs(args).items():
        sweep = [results[c] for c in configs]
        sweeps[f"Fig. {k} (k = {k})"] = ("sigma^2", GRID, sweep)
        _print_table(f"Fig. {k} (k = {k}): MSE against sigma^2", "sigma^2", GRID, sweep,
                     "mean", out)
        bayes_opt = _ratios(sweep, "bayes", "optimal", "mean")
        claims.add(f"model 1 Fig. {k}", "optimal < Bayesian at every point",
                   "the optimal method works best", f"Bayesian / optimal = {_span(bayes_opt)}",
                   _labelled("sigma^2", GRID, [r - 1 for r in bayes_opt]))
        for ci in FAST_CI:
            gain = [1 - r for r in _ratios(sweep, "bayes", ci, "mean")]
            mean_gain = mean_of(gain)
            claims.add(f"model 1 Fig. {k}", f"Bayesian roughly 10% better than {LABELS[ci]} "
                       "(mean within a factor 2)",
                       "roughly 10% better than the CI method",
                       f"1 - Bayesian / {LABELS[ci]} = {_span(gain)}, mean "
                       f"{mean_gain:.3f} +/- {mean_gain.se:.3f}", _within(mean_gain, *ROUGHLY_10))
    normalised = {k: {e: mean_of(_ratios(sweeps[f"Fig. {k} (k = {k})"][2], e, "optimal",
                                         "mean"))
                      for e in ("bayes",) + FAST_CI} for k in (2, 3)}
    print("\nFig. 4: normalised MSE (MSE / optimal MSE, mean over the sweep; in model 1 it does "
          "not depend on sigma^2)", file=out)
    print(f"{'k':>3} " + " ".join(f"{LABELS[e]:>16}" for e in ("bayes",) + FAST_CI), file=out)
    for k in (2, 3):
        print(f"{k:>3} " + " ".join(f"{v.value:>8.3f} +/- {v.se:.3f}"
                                    for v in normalised[k].values()), file=out)
    for k in (2, 3):
        best_ci = min(normalised[k][ci].value for ci in FAST_CI)
        claims.add("model 1 Fig. 4", f"k = {k}: the Bayesian estimator outperforms CI",
                   "the proposed estimator outperforms the other",
                   f"Bayesian {normalised[k]['bayes']:.3f}, best fast CI {best_ci:.3f}",
                   [(LABELS[ci], normalised[k][ci] - normalised[k]["bayes"]) for ci in FAST_CI])
    claims.add("model 1 Fig. 4", "the gap to the optimal grows with the number of nodes",
               "the gap between the optimal estimator and the others becomes larger",
               f"Bayesian / optimal {normalised[2]['bayes']:.3f} (k = 2) -> "
               f"{normalised[3]['bayes']:.3f} (k = 3)",
               [normalised[3]["bayes"] - normalised[2]["bayes"]])
    figures.append(("model1", sweeps))


def _model2_configs(args):
    sweeps = {}
    for fig in ("5", "6"):
        for k in (2, 3):
            dof = 3.0 * k if args.model2_dof is None else args.model2_dof
            sweeps[(fig, k)] = [
                _Config("kalman", k, v if fig == "5" else 0.2, 1.0 if fig == "5" else v,
                        args.samples, dof, 3)
                for v in GRID
            ]
    return sweeps


def _model2(args, results, claims, out, figures):
    """Journal model 2, Figs. 5-8: the Kalman model with Wishart dof 3, k = 2, 3."""
    dof_text = "3k" if args.model2_dof is None else f"{args.model2_dof:g}"
    _heading(f"Journal model 2, Figs. 5-8 (Kalman model, data Wishart dof 3, prior dof "
             f"{dof_text}, M = {args.samples}, {args.runs} runs)", out)
    sweeps = {key: ("sigma0^2" if key[0] == "5" else "sigma^2", GRID,
                    [results[c] for c in configs])
              for key, configs in _model2_configs(args).items()}
    for target in ("mean", "x0"):
        print(f"\n--- error measured against {_target_name(target)}", file=out)
        for (fig, k), (axis_name, values, sweep) in sweeps.items():
            fixed = "sigma^2 = 1" if fig == "5" else "sigma0^2 = 0.2"
            _print_table(f"Fig. {fig}, k = {k}: MSE against {axis_name} ({fixed})",
                         axis_name, values, sweep, target, out)
            _ordering_claims(claims, f"model 2 Fig. {fig}, k = {k}, vs {target}",
                             (axis_name, values), sweep, target,
                             "Bayesian about 20% worse than optimal", ABOUT_20)
        print(f"\n  across k and the sweeps (error against {_target_name(target)}):", file=out)
        for fig in ("5", "6"):
            axis_name = sweeps[(fig, 2)][0]
            mse2 = [r[target]["bayes"] for r in sweeps[(fig, 2)][2]]
            mse3 = [r[target]["bayes"] for r in sweeps[(fig, 3)][2]]
            claims.add(f"model 2 Fig. {fig}, vs {target}", "three nodes: lower MSE than two",
                       "three nodes lead to better estimation than two",
                       f"Bayesian MSE(k=3) / MSE(k=2) = "
                       f"{_span([a / b for a, b in zip(mse3, mse2)])}",
                       _labelled(axis_name, GRID, [b - a for a, b in zip(mse3, mse2)]))
        for fig, trend, sign in (("6", "lower with increasing sigma^2", -1),
                                 ("5", "higher with increasing sigma0^2", +1)):
            axis_name = sweeps[(fig, 2)][0]
            for k in (2, 3):
                norm = _ratios(sweeps[(fig, k)][2], "bayes", "optimal", target)
                steps = [(f"{axis_name} {a:g} -> {b:g}", sign * (n1 - n0))
                         for a, b, n0, n1 in zip(GRID, GRID[1:], norm, norm[1:])]
                claims.add(f"model 2 Fig. {'7' if fig == '6' else '8'}, k = {k}, vs {target}",
                           f"normalised MSE {trend}",
                           "better with increasing sigma^2, worse with increasing sigma0^2",
                           f"Bayesian / optimal = {_fmt_floats(norm)}", steps)
        for fig in ("5", "6"):
            axis_name = sweeps[(fig, 2)][0]
            n2 = _ratios(sweeps[(fig, 2)][2], "bayes", "optimal", target)
            n3 = _ratios(sweeps[(fig, 3)][2], "bayes", "optimal", target)
            claims.add(f"model 2 Figs. 7-8 ({axis_name}), vs {target}",
                       "normalised MSE worse for three nodes",
                       "deteriorates with the increase in the number of nodes",
                       f"k = 2: {_fmt_floats(n2)}; k = 3: {_fmt_floats(n3)}",
                       _labelled(axis_name, GRID, [b - a for a, b in zip(n2, n3)]))
    figures.append(("model2", {f"Fig. {fig}, k = {k}": sweep
                               for (fig, k), sweep in sweeps.items()}))


def _nodes_configs(args):
    sweeps = {}
    for model in ("wishart", "kalman"):
        configs = []
        for k in NODES:
            dof = 3.0 * k if model == "wishart" or args.model2_dof is None else args.model2_dof
            configs.append(_Config(model, k, 0.2 if model == "kalman" else 0.0, 1.0,
                                   args.samples, dof, 3 * k if model == "wishart" else 3))
        sweeps[model] = configs
    return sweeps


def _nodes(args, results, claims, out, figures):
    """Journal Fig. 9: MSE against the number of nodes, both models."""
    _heading(f"Journal Fig. 9: MSE against the number of nodes k (model 1 sigma^2 = 1; model 2 "
             f"sigma^2 = 1, sigma0^2 = 0.2; {args.runs} runs)", out)
    sweeps = {model: ("k", NODES, [results[c] for c in configs])
              for model, configs in _nodes_configs(args).items()}
    for model, (_, _, sweep) in sweeps.items():
        for target in _targets(model):
            _print_table(f"{'model 1' if model == 'wishart' else 'model 2'}, error against "
                         f"{_target_name(target)}", "k", NODES, sweep, target, out)
    n1 = _ratios(sweeps["wishart"][2], "bayes", "optimal", "mean")
    for target in ("mean", "x0"):
        n2 = _ratios(sweeps["kalman"][2], "bayes", "optimal", target)
        claims.add(f"Fig. 9, model 2 vs {target}", "Bayesian works better in model 2",
                   "the proposed algorithm works better in model 2",
                   f"Bayesian / optimal: model 1 {_fmt_floats(n1)}; model 2 {_fmt_floats(n2)}",
                   _labelled("k", NODES, [a - b for a, b in zip(n1, n2)]))
    figures.append(("nodes", {f"Fig. 9, model {1 if model == 'wishart' else 2}": sweep
                              for model, sweep in sweeps.items()}))


def _samples_study(rng, runs, k, dof, sample_sizes):
    """Monte Carlo study of Fig. 10: the same data for every M; squared errors per run."""
    data = simulate_kalman_model(k, 0.2, 1.0, runs, rng, 3)
    out = {}
    reference = compare_estimators(data, rng=rng, estimators=("optimal",))["optimal"]
    out["optimal/mean"] = np.sum(reference**2, axis=-1)
    out["optimal/x0"] = np.sum((reference - data.x0) ** 2, axis=-1)
    for M in sample_sizes:
        start = time.perf_counter()
        x = compare_estimators(data, M, dof, rng, estimators=("bayes",))["bayes"]
        out[f"{M}/seconds"] = np.full(runs, (time.perf_counter() - start) / runs)
        out[f"{M}/mean"] = np.sum(x**2, axis=-1)
        out[f"{M}/x0"] = np.sum((x - data.x0) ** 2, axis=-1)
    return out


def _samples(args, client, claims, out, figures):
    """Journal Fig. 10: MSE of the Bayesian estimator against M (five nodes, model 2)."""
    k = 5
    dof = 3.0 * k if args.model2_dof is None else args.model2_dof
    _heading(f"Journal Fig. 10: MSE against the number of samples M (model 2, k = {k}, "
             f"sigma^2 = 1, sigma0^2 = 0.2, prior dof {dof:g}, {args.runs} runs; the same data "
             "for every M)", out)
    arrays = run_study(_samples_study, "weng Fig. 10", args.runs, args.seed,
                       SECTIONS.index("samples"), client, k=k, dof=dof,
                       sample_sizes=SAMPLE_SIZES)
    reference = {t: Estimate.mean(arrays[f"optimal/{t}"]) for t in ("mean", "x0")}
    rows = [(M, {t: Estimate.mean(arrays[f"{M}/{t}"]) for t in ("mean", "x0")},
             float(arrays[f"{M}/seconds"].sum())) for M in SAMPLE_SIZES]
    print(f"{'M':>6} {'MSE vs 0':>10} {'MSE vs x0':>10} {'+/- SE':>8} {'/ optimal':>10} "
          f"{'time [s]':>9}", file=out)
    for M, mse, seconds in rows:
        print(f"{M:>6} {mse['mean']:>10.4f} {mse['x0']:>10.4f} {mse['x0'].se:>8.4f} "
              f"{mse['x0'] / reference['x0']:>10.3f} {seconds:>9.2f}", file=out)
    print(f"optimal: {reference['mean']:.4f} (vs 0), {reference['x0']:.4f} (vs x0); "
          "'/ optimal' is against x0; time: compute seconds summed over chunks", file=out)
    by_m = {M: mse["x0"] for M, mse, _ in rows}
    if 100 in by_m and max(by_m) > 100:
        gain = 1 - by_m[max(by_m)] / by_m[100]
        claims.add("Fig. 10", "100 samples are almost enough",
                   "100 samples are almost enough for the Monte Carlo method",
                   f"M = 100 -> {max(by_m)} lowers the MSE (vs x0) by {100 * gain.value:.2f}% "
                   f"+/- {100 * gain.se:.2f}%", _within(gain, -0.02, 0.02))
    figures.append(("samples", ([(M, float(mse["x0"]), float(mse["x0"].se)) for M, mse, _ in rows],
                                float(reference["x0"]))))


DOF_GRID = (4.5, 5.0, 6.0, 8.0, 12.0, 24.0, 100.0)


def _dof_study(rng, runs, samples):
    """Monte Carlo study of the prior-dof sensitivity: per run, squared errors and NEES."""
    out = {}
    for model in ("wishart", "kalman"):
        data = (simulate_wishart_model(2, 1.0, runs, rng) if model == "wishart"
                else simulate_kalman_model(2, 0.2, 1.0, runs, rng, 3))
        base = compare_estimators(data, rng=rng, estimators=("optimal", "ci-det-ratio"))
        for name, x in base.items():
            out[f"{model}/{name}"] = np.sum(x**2, axis=-1)
        for dof in DOF_GRID:
            r = bayesian_fusion(data.xs, data.Ps, dof=dof, samples=samples, rng=rng)
            out[f"{model}/{dof}/mse"] = np.sum(r.x**2, axis=-1)
            out[f"{model}/{dof}/nees"] = _nees_per_run(r.x, r.P)
    return out


def _dof_sensitivity(args, client, out):
    """The prior dof as belief about correlation: MSE and NEES against dof on fixed data."""
    _heading(f"Prior degrees of freedom (k = 2, {args.runs} runs, M = {args.samples}; the same "
             "data for every dof). NEES of a consistent P: 2", out)
    arrays = run_study(_dof_study, "weng prior dof", args.runs, args.seed,
                       SECTIONS.index("dof"), client, samples=args.samples)
    for model in ("wishart", "kalman"):
        optimal = Estimate.mean(arrays[f"{model}/optimal"])
        ci = Estimate.mean(arrays[f"{model}/ci-det-ratio"])
        print(f"\n{'model 1 (data dof 6)' if model == 'wishart' else 'model 2 (vs 0)'}: "
              f"optimal {optimal:.4f}, CI det {ci:.4f}", file=out)
        print(f"{'dof':>6} {'Bayesian MSE':>13} {'/ optimal':>10} {'mean NEES':>10} "
              f"{'+/- SE':>8}", file=out)
        for dof in DOF_GRID:
            mse = Estimate.mean(arrays[f"{model}/{dof}/mse"])
            nees = Estimate.mean(arrays[f"{model}/{dof}/nees"])
            print(f"{dof:>6g} {mse:>13.4f} {mse / optimal:>10.3f} {nees:>10.3f} "
                  f"{nees.se:>8.3f}", file=out)


NEES_ESTIMATORS = ("bayes", "ci-trace", "ci-fast", "naive")


def _nees_study(rng, runs, samples):
    """Monte Carlo study of repeated fusion: per run, the node-averaged NEES of every round."""
    return _repeated_fusion_nees_per_run(5, 4, runs, samples, rng, NEES_ESTIMATORS)


def _nees(args, client, claims, out, figures):
    """Repeated fusion in a ring: NEES of Bayesian fusion against CI (journal Sec. VI)."""
    runs = max(1, args.runs // 5)
    _heading("Repeated fusion (journal Sec. VI): ring of 4 nodes, each fuses itself and its two "
             f"neighbours every round;\nP_x ~ W_8(12, I), prior dof 12, M = {args.samples}, "
             f"{runs} runs. Mean NEES; consistent = 2.", out)
    arrays = run_study(_nees_study, "weng repeated fusion", runs, args.seed,
                       SECTIONS.index("nees"), client, samples=args.samples)
    nees = {name: [Estimate.mean(arrays[name][:, r]) for r in range(6)]
            for name in NEES_ESTIMATORS}
    print(f"{'round':>6} " + " ".join(f"{LABELS[name]:>17}" for name in nees), file=out)
    for r in range(6):
        print(f"{r:>6} " + " ".join(f"{values[r].value:>8.3f} +/- {values[r].se:<5.3f}"
                                    for values in nees.values()), file=out)
    bayes, ci = nees["bayes"], nees["ci-trace"]
    margins = [(f"Bayesian round {r} -> {r + 1}", bayes[r + 1] - bayes[r]) for r in range(1, 5)]
    margins += [("Bayesian last round above 4", bayes[-1] - 4),
                ("CI last round within 5% of round 1", 1.05 * ci[1] - ci[-1])]
    claims.add("repeated fusion", "Bayesian NEES grows round after round, CI's does not",
               "multiple fusions lead to overconfident estimation; CI stays the same",
               f"Bayesian {_fmt_floats(bayes)}; CI trace {_fmt_floats(ci)}", margins)
    figures.append(("nees", {name: _floats(values) for name, values in nees.items()}))


# --------------------------------------------------------------------------- figures
def _plot(figures, directory, out):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    styles = dict(zip(ESTIMATORS, ("k-", "C0-", "C5-.", "C1--", "C2--", "C3--", "C4:")))
    written = []

    def sweep_panel(ax, axis_name, values, results, title):
        target = "x0" if "x0" in results[0] else "mean"
        for e in ESTIMATORS:
            ax.plot(values, [float(r[target][e]) for r in results], styles[e], label=LABELS[e])
        ax.set(xscale="log", yscale="log", xlabel=axis_name, title=title,
               ylabel=f"MSE against {'x0' if target == 'x0' else '0'}")

    for name, content in figures:
        if name in ("conference", "model1", "model2", "nodes"):
            panels = list(content.items())
            fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 3.8),
                                     layout="constrained", squeeze=False)
            for ax, (title, (axis_name, values, results)) in zip(axes[0], panels):
                sweep_panel(ax, axis_name, values, results, title)
                ax.legend(fontsize="x-small")
        elif name == "samples":
            rows, reference = content
            fig, ax = plt.subplots(figsize=(5, 3.8), layout="constrained")
            ax.errorbar([r[0] for r in rows], [r[1] for r in rows], [2 * r[2] for r in rows],
                        fmt="C0o-", capsize=3, label="Bayesian (+/- 2 SE)")
            ax.axhline(reference, color="k", label="optimal")
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
JOURNAL = {"model1": _model1_configs, "model2": _model2_configs, "nodes": _nodes_configs}


def _section_list(text):
    """``--only``: comma-separated section names, checked when the arguments are parsed."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in SECTIONS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"unknown section(s) {', '.join(map(repr, unknown)) or '(none given)'}; "
            f"known: {', '.join(SECTIONS)}")
    return names


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m cifilter reproduce weng``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The ``weng`` sub-command's parser.

    Examples
    --------
    >>> import argparse
    >>> from cifilter.cli.reproduce import weng
    >>> parser = argparse.ArgumentParser()
    >>> weng.add_arguments(parser)
    >>> parser.parse_args(["--runs", "200", "--workers", "2"]).runs
    200
    """
    parser.add_argument("--runs", type=positive_int, default=10_000,
                        help="runs per journal configuration (default 10000, as the journal)")
    parser.add_argument("--samples", type=positive_int, default=100,
                        help="Monte Carlo samples M of the journal's experiments (default 100)")
    parser.add_argument("--conference-runs", type=positive_int, default=200,
                        help="runs per conference configuration (default 200)")
    parser.add_argument("--conference-samples", type=positive_int, default=500,
                        help="samples M of the conference experiments (default 500)")
    parser.add_argument("--model2-dof", type=positive_float, default=None,
                        help="prior dof of the Bayesian rule in model 2 (default 3k, the "
                             "journal's model-1 value; the journal does not state it; at "
                             "least 2k for k nodes, i.e. 12 with the Fig. 9 sweep)")
    parser.add_argument("--only", type=_section_list, default=list(SECTIONS),
                        help=f"comma-separated sections (default all): {', '.join(SECTIONS)}")
    add_common_arguments(parser, "write PNG figures (weng_*.png) to DIR")


def run(args: argparse.Namespace, out: Optional[TextIO] = None) -> int:
    """Run the selected sections and print every number next to the papers' statements.

    Parameters
    ----------
    args : argparse.Namespace
        The options of :func:`add_arguments` (``workers``, ``scheduler`` and ``plot`` may
        be missing: in process, no figures).
    out : file-like, optional
        Where the report goes (default ``sys.stdout``).

    Returns
    -------
    int
        0 (a claim that fails is a finding, not an error).
    """
    out = sys.stdout if out is None else out
    sections = args.only if isinstance(args.only, list) else _section_list(args.only)
    figures: list[tuple[str, Any]]
    claims, figures = Claims(out), []
    start = time.perf_counter()
    seconds: Union[list[float], NDArray[np.float64]] = []
    with parallel_client(args) as client:
        results = {}
        if "conference" in sections:
            configs = [c for sweep in _conference_configs(args).values() for c in sweep]
            found, spent = _run_configs(configs, args.conference_runs, "weng conference",
                                        SECTIONS.index("conference"), args, client)
            results.update(found)
            seconds += spent
        journal = [c for name in sections if name in JOURNAL
                   for sweep in JOURNAL[name](args).values() for c in sweep]
        if journal:
            found, spent = _run_configs(journal, args.runs, "weng journal",
                                        SECTIONS.index("model1"), args, client)
            results.update(found)
            seconds += spent
        for section in sections:
            if section == "conference":
                _conference(args, results, claims, out, figures)
            elif section == "model1":
                _model1(args, results, claims, out, figures)
            elif section == "model2":
                _model2(args, results, claims, out, figures)
            elif section == "nodes":
                _nodes(args, results, claims, out, figures)
            elif section == "samples":
                _samples(args, client, claims, out, figures)
            elif section == "dof":
                _dof_sensitivity(args, client, out)
            else:
                _nees(args, client, claims, out, figures)
    if claims.rows:
        claims.summary()
    total = time.perf_counter() - start
    if seconds:
        seconds = np.array(seconds)
        print(f"\n{len(seconds)} configurations, {seconds.min():.1f} to {seconds.max():.1f} s "
              f"of compute each (median {np.median(seconds):.1f} s)", file=out)
    print(f"total {total:.0f} s", file=out)
    if getattr(args, "plot", None):
        _plot(figures, args.plot, out)
    return 0
