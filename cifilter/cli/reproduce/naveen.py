"""Naveen & Taylor: Ellipsoidal Intersection and its probabilistically conservative variant.

Reproduces Section III (cases 1-3, Fig. 2), Table I and Fig. 4 (Monte Carlo over
inverse-Wishart input sets) and Section V-B (the six-node network, Fig. 6), for both
mutual means of eq. (13) and both placements of the regulariser, and checks how often the
rules are conservative. Every number is printed next to the paper's.

The Monte Carlo parts (Table I over input sets, Section V-B over networks) run through
:func:`cifilter.montecarlo.run`: in process, or with ``--workers N`` / ``--scheduler
ADDRESS`` on Dask, with the same numbers. Every EI variant of Table I sees the same input
sets, and every rule of Section V-B the same initial estimates.
"""

import argparse
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Literal, Optional, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import stats

from ..._numerics.validation import as_rng, check_int
from ...rules.ei import ellipsoidal_intersection
from ...rules.optimal import naive_fusion, optimal_fusion
from ...rules.pcei import pc_ellipsoidal_intersection
from ..args import positive_int
from ._checks import Estimate
from ._common import add_common_arguments, parallel_client, run_study

__all__ = ["NETWORK_EDGES", "case_one", "input_sets", "network", "table_one"]

DESCRIPTION = ("Naveen & Taylor: EI and probabilistically conservative EI "
               "(Section III, Table I / Fig. 4, Section V-B / Fig. 6)")

PAPER_TABLE_ONE = {  # dof: (det PC .05, det PC .01, det EI, MSE PC .05, MSE PC .01, MSE EI)
    2: (0.7229, 0.7418, 0.7946, 1.927, 1.9442, 2.019),
    10: (0.415, 0.435, 0.485, 0.574, 0.588, 0.640),
    100: (0.537, 0.565, 0.651, 0.672, 0.684, 0.867),
}

NETWORK_EDGES = ((0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (5, 0), (1, 4))
"""Edges of the six-node network (Fig. 5 is missing from the text: a ring with one chord)."""

VARIANTS = (  # (mutual_mean, regularizer, eps)
    ("as-printed", "covariance", 0.01),
    ("as-printed", "information", 1e-8),
    ("sijs-lazar", "covariance", 0.01),
    ("sijs-lazar", "information", 1e-8),
)


# --------------------------------------------------------------------------- Section III
def case_one(alpha: Optional[float], *,
             mutual_mean: Literal["sijs-lazar", "as-printed"] = "sijs-lazar",
             eps: float = 0.01,
             regularizer: Literal["covariance", "information"] = "covariance",
             ) -> dict[str, Any]:
    """Section III, case 1: two 1-D inputs with variance 1 and means +1 and -1.

    Parameters
    ----------
    alpha : float or None
        Significance of the probabilistic constraint; ``None`` gives EI.
    mutual_mean : {"sijs-lazar", "as-printed"}, optional
        The mutual mean (identical here: the inputs are symmetric).
    eps : float, optional
        Regulariser (the paper's 0.01).
    regularizer : {"covariance", "information"}, optional
        Where ``eps`` enters; ``"covariance"`` is eq. (11) as printed.

    Returns
    -------
    dict
        ``common_P``, ``independent_x`` (2,), ``independent_P`` (2,), ``P`` (fused
        variance), ``psi`` (eq. (17) at the common variance).

    Examples
    --------
    >>> from cifilter.cli.reproduce.naveen import case_one
    >>> r = case_one(None)
    >>> r["independent_x"].round(3).tolist(), r["independent_P"].round(3).tolist()
    ([101.0, -101.0], [101.0, 101.0])
    """
    args = ([1.0], [[1.0]], [-1.0], [[1.0]])
    options: dict[str, Any] = dict(eps=eps, mutual_mean=mutual_mean, regularizer=regularizer)
    if alpha is None:
        r = ellipsoidal_intersection(*args, **options)
    else:
        r = pc_ellipsoidal_intersection(*args, alpha=alpha, **options)
    A = r.info["independent_information"][:, 0, 0]
    eta = r.info["independent_information_vector"][:, 0]
    with np.errstate(divide="ignore"):
        return {"common_P": float(r.info["common_P"][0, 0]), "independent_x": eta / A,
                "independent_P": 1.0 / A, "P": float(r.P[0, 0]), "psi": float(r.info["psi"])}


def case_two(C_a: ArrayLike, alpha: Optional[float], *,
             mutual_mean: Literal["sijs-lazar", "as-printed"], eps: float = 0.01,
             regularizer: Literal["covariance", "information"] = "covariance",
             ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Fig. 2: ``C_b = 1``, means +1 and -1, sweep over ``C_a`` (batched).

    Returns the common variance, the two independent means and the fused variance.
    """
    C_a = np.asarray(C_a, dtype=float)
    size = C_a.size
    xa, xb = np.ones((size, 1)), -np.ones((size, 1))
    Pa, Pb = C_a.reshape(size, 1, 1), np.ones((size, 1, 1))
    options: dict[str, Any] = dict(eps=eps, mutual_mean=mutual_mean, regularizer=regularizer)
    if alpha is None:
        r = ellipsoidal_intersection(xa, Pa, xb, Pb, **options)
    else:
        r = pc_ellipsoidal_intersection(xa, Pa, xb, Pb, alpha=alpha, **options)
    A = r.info["independent_information"][..., 0, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        means = r.info["independent_information_vector"][..., 0] / A
    return r.info["common_P"][:, 0, 0], means, r.P[:, 0, 0]


# --------------------------------------------------------------------------- Table I
@dataclass(frozen=True)
class InputSets:
    """Input sets of Section V-A (see :func:`input_sets`); the parameters are the attributes.

    Parameters
    ----------
    x : ndarray, shape (..., 2, n)
        The means of the two inputs (the truth is 0).
    P : ndarray, shape (..., 2, n, n)
        Their covariances.
    joint : ndarray, shape (..., 2n, 2n)
        The joint error covariance (cross-covariance ``C_a C_c^-1 C_b``).
    """

    x: NDArray[np.float64]
    P: NDArray[np.float64]
    joint: NDArray[np.float64]


def _inverse_wishart(dof, size, n, rng):
    sample = stats.invwishart.rvs(df=dof, scale=dof * np.eye(n), size=size, random_state=rng)
    return np.asarray(sample).reshape((size, n, n))


def input_sets(dof: float, sets: int, rng: Optional[Union[int, np.random.Generator]] = None, *,
               draws: int = 1, n: int = 2) -> InputSets:
    """Section V-A: common and independent parts from an inverse Wishart, inputs by eq. (6).

    ``C_a\\c``, ``C_b\\c`` and ``C_c`` are drawn from an inverse Wishart distribution with
    ``dof`` degrees of freedom and scale ``dof I`` (so they approach the identity as
    ``dof`` grows, as the paper states; it does not give the scale), the three means from
    zero-mean Gaussians with those covariances, and the inputs follow eqs. (5)-(6):
    ``C_a^-1 = C_a\\c^-1 + C_c^-1``, ``x_a = C_a (C_a\\c^-1 x_a\\c + C_c^-1 x_c)``.

    Parameters
    ----------
    dof : float
        Degrees of freedom (> n - 1).
    sets : int
        Number of covariance sets.
    rng : numpy.random.Generator, int or None
        Randomness.
    draws : int, optional
        Independent mean draws per covariance set (for NEES statistics).
    n : int, optional
        Dimension (the paper: 2).

    Returns
    -------
    InputSets
        ``x`` (sets, draws, 2, n), ``P`` (sets, 1, 2, n, n), ``joint`` (sets, 1, 2n, 2n).

    Examples
    --------
    >>> from cifilter.cli.reproduce.naveen import input_sets
    >>> s = input_sets(10, sets=3, rng=0, draws=4)
    >>> s.x.shape, s.P.shape, s.joint.shape
    ((3, 4, 2, 2), (3, 1, 2, 2, 2), (3, 1, 4, 4))
    """
    rng = as_rng(rng)
    sets, draws = check_int(sets, "sets", low=1), check_int(draws, "draws", low=1)
    C_ac, C_bc, C_c = (_inverse_wishart(dof, sets, n, rng) for _ in range(3))
    inv = np.linalg.inv
    C_a, C_b = inv(inv(C_ac) + inv(C_c)), inv(inv(C_bc) + inv(C_c))
    C_a, C_b = 0.5 * (C_a + np.swapaxes(C_a, -1, -2)), 0.5 * (C_b + np.swapaxes(C_b, -1, -2))

    def draw(C):
        z = rng.standard_normal((sets, draws, n))
        return np.einsum("sij,sdj->sdi", np.linalg.cholesky(C), z)

    x_ac, x_bc, x_c = draw(C_ac), draw(C_bc), draw(C_c)
    common = np.einsum("sij,sdj->sdi", inv(C_c), x_c)
    x_a = np.einsum("sij,sdj->sdi", C_a, np.einsum("sij,sdj->sdi", inv(C_ac), x_ac) + common)
    x_b = np.einsum("sij,sdj->sdi", C_b, np.einsum("sij,sdj->sdi", inv(C_bc), x_bc) + common)
    cross = C_a @ inv(C_c) @ C_b
    joint = np.block([[C_a, cross], [np.swapaxes(cross, -1, -2), C_b]])
    return InputSets(np.stack([x_a, x_b], axis=-2), np.stack([C_a, C_b], axis=-3)[:, None],
                     joint[:, None])


def _fuse_sets(s, alpha, mutual_mean, regularizer, eps):
    options = dict(eps=eps, mutual_mean=mutual_mean, regularizer=regularizer)
    if alpha is None:  # the (xs, Ps) form: the covariances broadcast against the means
        return ellipsoidal_intersection(s.x, s.P, **options)
    return pc_ellipsoidal_intersection(s.x, s.P, alpha=alpha, **options)


def table_one(dofs: Sequence[float] = (2, 10, 100), sets: int = 35,
              rng: Optional[Union[int, np.random.Generator]] = None, *,
              mutual_mean: Literal["sijs-lazar", "as-printed"] = "as-printed",
              regularizer: Literal["covariance", "information"] = "covariance",
              eps: float = 0.01, alphas: Sequence[float] = (0.05, 0.01),
              draws: int = 1) -> dict[float, dict[str, Any]]:
    """Table I: average fused determinant and MSE against the optimal fusion.

    Parameters
    ----------
    dofs : sequence of float, optional
        Inverse-Wishart degrees of freedom.
    sets : int, optional
        Input sets per ``dof`` (the paper: 35).
    rng : numpy.random.Generator, int or None
        Randomness (one stream for all ``dofs``, in order).
    mutual_mean, regularizer, eps : optional
        The EI variant (see :func:`~cifilter.ellipsoidal_intersection`).
    alphas : sequence of float, optional
        Significance levels of PC-EI.
    draws : int, optional
        Mean draws per covariance set; with more than one the NEES statistics are over
        independent errors of the same covariances.

    Returns
    -------
    dict
        Per ``dof``: ``det`` and ``mse`` (dict method -> average; methods ``"EI"`` and
        ``alpha``), ``det_all`` (method -> per set, first draw), ``pc_not_above_ei``
        (det(PC) <= det(EI) in every instance), ``nees_inside`` (share of NEES within the
        95% chi-square bound, including ``"optimal"``), ``mean_nees``, ``infeasible``
        (per alpha: instances where no common covariance passes the test),
        ``kkt_max`` (largest KKT residual of PC-EI), ``ei_bounds`` (share of sets whose EI
        covariance bounds EI's true error covariance ``K J K^T``) and ``ei_excess`` (the
        largest eigenvalue of ``P^-1 K J K^T`` over the sets: the factor by which P would
        have to grow to bound it).

    Examples
    --------
    >>> from cifilter.cli.reproduce.naveen import table_one
    >>> out = table_one(dofs=(10,), sets=4, rng=0)
    >>> list(out[10]["det"]), out[10]["pc_not_above_ei"]
    (['EI', 0.05, 0.01], True)
    """
    rng = as_rng(rng)
    results: dict[float, dict[str, Any]] = {}
    for dof in dofs:
        s = input_sets(dof, sets, rng, draws=draws)
        per_set = _table_one_per_set(s, mutual_mean, regularizer, eps, alphas)
        results[dof] = _table_one_row(per_set, alphas)
    return results


def _table_one_per_set(s, mutual_mean, regularizer, eps, alphas):
    """Table I's statistics of every input set (first axis: sets), for one EI variant.

    Keys ``(statistic, method)`` or ``(statistic,)``; :func:`_table_one_row` reduces them
    over the sets to the numbers of :func:`table_one`.
    """
    n = s.x.shape[-1]
    best = optimal_fusion(s.x, np.broadcast_to(s.joint, s.x.shape[:-2] + s.joint.shape[-2:]))
    bound = stats.chi2.ppf(0.95, df=n)
    fused = {"EI": _fuse_sets(s, None, mutual_mean, regularizer, eps)}
    for alpha in alphas:
        fused[alpha] = _fuse_sets(s, alpha, mutual_mean, regularizer, eps)
    out = {}
    for key, r in list(fused.items()) + [("optimal", best)]:
        nees = np.einsum("...i,...ij,...j->...", r.x, np.linalg.inv(r.P), r.x)
        out[("nees_inside", key)] = np.mean(nees <= bound, axis=1)
        out[("mean_nees", key)] = np.mean(nees, axis=1)
        if key == "optimal":
            continue
        det = np.linalg.det(r.P)
        out[("det", key)] = np.mean(det, axis=1)
        out[("det_all", key)] = det[:, 0]
        out[("mse", key)] = np.mean(np.sum((r.x - best.x) ** 2, axis=-1), axis=1)
        out[("mse_truth", key)] = np.mean(np.sum(r.x**2, axis=-1), axis=1)
        if key != "EI":
            out[("infeasible", key)] = np.sum(~r.info["feasible"], axis=1)
            # fmax ignores NaN (an inactive constraint has no KKT residual) without a warning
            out[("kkt_max", key)] = np.fmax.reduce(
                np.where(r.info["active"], r.info["kkt_residual"], 0.0), axis=1)
    # EI's gains do not depend on the means: its true error covariance is K J K^T, and
    # P bounds it when P - K J K^T is positive semidefinite.
    K = np.concatenate([fused["EI"].gains[:, 0, 0], fused["EI"].gains[:, 0, 1]], axis=-1)
    true_cov = K @ s.joint[:, 0] @ np.swapaxes(K, -1, -2)
    gap = np.linalg.eigvalsh(fused["EI"].P[:, 0] - true_cov)[:, 0]
    out[("ei_bounds",)] = gap >= -1e-12 * np.abs(true_cov).max(axis=(-2, -1))
    ratio = np.linalg.eigvals(np.linalg.solve(fused["EI"].P[:, 0], true_cov)).real.max(-1)
    out[("ei_excess",)] = ratio
    det_ei = np.linalg.det(fused["EI"].P)
    out[("pc_not_above_ei",)] = np.all(
        [np.all(np.linalg.det(fused[a].P) <= det_ei * (1 + 1e-9), axis=1) for a in alphas],
        axis=0)
    return out


def _table_one_row(per_set, alphas):
    """One ``dof`` row of :func:`table_one` from the per-set statistics."""
    row = {"det": {}, "mse": {}, "mse_truth": {}, "det_all": {}, "nees_inside": {},
           "mean_nees": {}, "infeasible": {}, "kkt_max": {}}
    for key, values in per_set.items():
        if len(key) == 1:
            continue
        name, method = key
        if name == "det_all":
            row[name][method] = values
        elif name == "infeasible":
            row[name][method] = int(np.sum(values))
        elif name == "kkt_max":
            row[name][method] = float(np.fmax.reduce(values))
        else:
            row[name][method] = float(np.mean(values))
    row["ei_bounds"] = float(np.mean(per_set[("ei_bounds",)]))
    row["ei_excess"] = float(np.max(per_set[("ei_excess",)]))
    row["pc_not_above_ei"] = bool(np.all(per_set[("pc_not_above_ei",)]))
    return row


# --------------------------------------------------------------------------- Section V-B
def network(method: Literal["ei", "pcei"], rounds: int = 25, runs: int = 1,
            rng: Optional[Union[int, np.random.Generator]] = None, *, dof: float = 30,
            edges: Sequence[tuple[int, int]] = NETWORK_EDGES,
            **options: Any) -> dict[str, NDArray[np.float64]]:
    """Section V-B: repeated pairwise fusion along every edge of a six-node network.

    Each node starts with an independent estimate (covariance from an inverse Wishart with
    ``dof`` degrees of freedom and scale ``dof I``, mean drawn from it; the truth is 0).
    In every round the edges are visited in order and both end nodes are replaced by the
    fusion of their estimates. The centralised result fuses the six initial (independent)
    estimates once.

    Parameters
    ----------
    method : {"ei", "pcei"}
        The fusion rule.
    rounds : int, optional
        Rounds of fusion along every edge (the paper: 25).
    runs : int, optional
        Independent networks, fused as one batch.
    rng : numpy.random.Generator, int or None
        Randomness; the same seed gives the same initial estimates for every method.
    dof : float, optional
        Inverse-Wishart degrees of freedom (the paper: 30).
    edges : sequence of (int, int), optional
        The network (Fig. 5 is missing from the text; default a ring with one chord).
    **options
        Options of the rule, e.g. ``alpha`` or ``mutual_mean``.

    Returns
    -------
    dict
        ``x`` (runs, 6, 2) and ``P`` (runs, 6, 2, 2) after the last round, ``x0`` and
        ``P0`` (the initial estimates), ``central_x`` (runs, 2) and ``central_P``
        (runs, 2, 2).

    Examples
    --------
    >>> from cifilter.cli.reproduce.naveen import network
    >>> out = network("ei", rounds=2, rng=0)
    >>> out["P"].shape, out["central_P"].shape
    ((1, 6, 2, 2), (1, 2, 2))
    """
    rng = as_rng(rng)
    rounds, runs = check_int(rounds, "rounds", low=1), check_int(runs, "runs", low=1)
    if method not in ("ei", "pcei"):
        raise ValueError(f"method must be 'ei' or 'pcei', got {method!r}")
    nodes = 1 + max(max(edge) for edge in edges)
    x0, P0 = _initial_estimates(runs, nodes, dof, rng)
    return _fuse_network(x0, P0, method, rounds, edges, options)


def _initial_estimates(runs, nodes, dof, rng):
    """Independent 2-D estimates of every node: covariance inverse Wishart, mean drawn from it."""
    P0 = _inverse_wishart(dof, runs * nodes, 2, rng).reshape(runs, nodes, 2, 2)
    x0 = np.einsum("rnij,rnj->rni", np.linalg.cholesky(P0), rng.standard_normal((runs, nodes, 2)))
    return x0, P0


def _fuse_network(x0, P0, method, rounds, edges, options):
    """Rounds of pairwise fusion along the edges, from the initial estimates (batched)."""
    central = naive_fusion(x0, P0)
    rule = ellipsoidal_intersection if method == "ei" else pc_ellipsoidal_intersection
    x, P = x0.copy(), P0.copy()
    for _ in range(rounds):
        for i, j in edges:
            r = rule(x[:, i], P[:, i], x[:, j], P[:, j], **options)
            x[:, i] = x[:, j] = r.x
            P[:, i] = P[:, j] = r.P
    return {"x": x, "P": P, "x0": x0, "P0": P0, "central_x": central.x, "central_P": central.P}


# --------------------------------------------------------------------------- command line
TABLE_ONE_DOFS = (2, 10, 100)
ALPHAS = (0.05, 0.01)
# Runs per Monte Carlo chunk (the numbers depend on them). A call of a rule costs about a
# millisecond whatever the batch, so chunks are large: the paper's 35 input sets make two
# chunks (one per core of a 2-core machine), and the 25 x 7 sequential fusions of the
# network are batched over 20 networks (more runs than that spread over workers).
TABLE_ONE_CHUNK = 18
NETWORK_CHUNK = 20
NETWORK_METHODS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("EI", "ei", {}),
    ("PC sijs-lazar", "pcei", {"alpha": 0.05}),
    ("PC as-printed", "pcei", {"alpha": 0.05, "mutual_mean": "as-printed"}),
    ("EI as-printed", "ei", {"mutual_mean": "as-printed"}),
)
NETWORK_SEED_KEY = len(TABLE_ONE_DOFS)  # Table I's studies use keys 0, 1, 2 (one per dof)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m cifilter reproduce naveen``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The ``naveen`` sub-command's parser.

    Examples
    --------
    >>> import argparse
    >>> from cifilter.cli.reproduce import naveen
    >>> parser = argparse.ArgumentParser()
    >>> naveen.add_arguments(parser)
    >>> parser.parse_args(["--sets", "10"]).sets
    10
    """
    parser.add_argument("--sets", type=positive_int, default=35,
                        help="input sets per degree of freedom for Table I (paper: 35)")
    parser.add_argument("--draws", type=positive_int, default=20,
                        help="mean draws per input set for the NEES statistics (default 20)")
    parser.add_argument("--runs", type=positive_int, default=20,
                        help="independent six-node networks for Section V-B (default 20)")
    parser.add_argument("--rounds", type=positive_int, default=25,
                        help="rounds of fusion along every edge in Section V-B (paper: 25)")
    add_common_arguments(parser, "write Fig. 2 (a, b), Fig. 4 and Fig. 6 as PNG files to DIR")


def _print_case_one():
    print("Section III, case 1: variances 1, means +1 and -1, eps = 0.01 added to C_c "
          "(eq. (11))")
    ei = case_one(None)
    print(f"  EI  independent parts (mean, var): ({ei['independent_x'][0]:.2f}, "
          f"{ei['independent_P'][0]:.2f}) and ({ei['independent_x'][1]:.2f}, "
          f"{ei['independent_P'][1]:.2f})   paper: (101, 101) and (-101, 101)")
    print(f"  EI  fused variance {ei['P']:.4f}   paper: about 1")
    print(f"  EI  psi {ei['psi']:.2f}   paper: about 100.5  (not reproduced; the formula "
          "gives (2 x 101)^2 / (2 x 101) = 202)")
    paper = {"common_P": 1.43, "x": 3.32, "P": 0.77}
    for alpha in (0.05, 0.01):
        pc = case_one(alpha)
        print(f"  PC alpha={alpha}: common var {pc['common_P']:.4f} (paper 1.43), independent "
              f"means {pc['independent_x'][0]:+.3f}/{pc['independent_x'][1]:+.3f} "
              f"(paper +/-3.32), var {pc['independent_P'][0]:.3f} (paper 3.32), fused "
              f"{pc['P']:.4f} (paper 0.77)")
    match = case_one(0.01)
    ok = (abs(match["common_P"] - paper["common_P"]) < 0.005
          and abs(match["independent_x"][0] - paper["x"]) < 0.005)
    print(f"  -> the paper's numbers are those of alpha = 0.01 (gamma = "
          f"{stats.chi2.ppf(0.99, 1):.3f}), although the text says alpha = 0.05: {ok}")
    info = case_one(0.01, regularizer="information", eps=1e-8)
    print(f"  (with the information regulariser the PC result is the same: common var "
          f"{info['common_P']:.4f})")


def _print_case_two_three():
    grid = np.array([0.25, 0.5, 0.8, 0.9, 0.95, 1.05, 1.1, 1.5, 2.0])
    print("\nSection III, case 2 (Fig. 2): C_b = 1, means +1/-1, sweep over C_a; "
          "alpha = 0.05, eps = 0.01 on C_c")
    for mutual_mean in ("as-printed", "sijs-lazar"):
        c_ei, m_ei, _ = case_two(grid, None, mutual_mean=mutual_mean)
        c_pc, m_pc, _ = case_two(grid, 0.05, mutual_mean=mutual_mean)
        print(f"  {mutual_mean}:")
        print("    C_a          " + " ".join(f"{v:7.2f}" for v in grid))
        print("    EI  C_c      " + " ".join(f"{v:7.2f}" for v in c_ei))
        print("    PC  C_c      " + " ".join(f"{v:7.2f}" for v in c_pc))
        print("    EI  mean a\\c " + " ".join(f"{v:7.1f}" for v in m_ei[:, 0]))
        print("    PC  mean a\\c " + " ".join(f"{v:7.2f}" for v in m_pc[:, 0]))
        left = c_pc[0] - c_ei[0] > c_pc[3] - c_ei[3]
        print(f"    text: 'PC common covariance always larger; the increase grows as C_a "
              f"decreases below 1': always larger {bool(np.all(c_pc > c_ei))}, grows to the "
              f"left {bool(left)}")
    same = pc_ellipsoidal_intersection([1.0], [[0.5]], [1.0], [[1.0]], eps=0.01,
                                       regularizer="covariance", mutual_mean="as-printed")
    ei = ellipsoidal_intersection([1.0], [[0.5]], [1.0], [[1.0]], eps=0.01,
                                  regularizer="covariance", mutual_mean="as-printed")
    print(f"\nSection III, case 3: equal means leave EI unchanged: C_c "
          f"{same.info['common_P'][0, 0]:.4f} = EI {ei.info['common_P'][0, 0]:.4f}, "
          f"solver {same.info['solver']!r}")


def _table_one_study(rng, runs, dof, draws):
    """Monte Carlo study of Table I: ``runs`` input sets, every EI variant on the same sets."""
    s = input_sets(dof, runs, rng, draws=draws)
    out = {}
    for v, (mutual_mean, regularizer, eps) in enumerate(VARIANTS):
        for key, values in _table_one_per_set(s, mutual_mean, regularizer, eps, ALPHAS).items():
            out[(v,) + key] = values
    return out


def _table_one_results(args, client):
    """``{(mutual_mean, regularizer): {dof: (row, per_set)}}`` through montecarlo.run."""
    results = {(mutual_mean, regularizer): {} for mutual_mean, regularizer, _ in VARIANTS}
    for index, dof in enumerate(TABLE_ONE_DOFS):
        arrays = run_study(_table_one_study, f"naveen Table I, dof {dof}", args.sets,
                           args.seed, index, client, chunk_size=TABLE_ONE_CHUNK, dof=dof,
                           draws=args.draws)
        for v, (mutual_mean, regularizer, _) in enumerate(VARIANTS):
            per_set = {key[1:]: values for key, values in arrays.items() if key[0] == v}
            results[(mutual_mean, regularizer)][dof] = (_table_one_row(per_set, ALPHAS),
                                                        per_set)
    return results


def _reduction(per_set, name, alpha):
    """``1 - mean(PC) / mean(EI)`` of a per-set statistic, with its standard error."""
    pc, ei = Estimate.mean(per_set[(name, alpha)]), Estimate.mean(per_set[(name, "EI")])
    return 1 - pc / ei


def _print_table_one(args, client):
    print(f"\nTable I: {args.sets} input sets per dof (inverse Wishart, scale dof I), "
          f"{args.draws} mean draws each; det = average fused determinant, MSE = squared "
          "error against the optimal (known-correlation) fused mean, as the text defines it; "
          "MSE(x) = squared error against the truth (for comparison: the paper's MSE "
          "magnitudes resemble these); -% = decrease against EI with its standard error over "
          "the sets")
    results = _table_one_results(args, client)
    for (mutual_mean, regularizer, eps) in VARIANTS:
        out = results[(mutual_mean, regularizer)]
        print(f"\n  mutual mean {mutual_mean!r}, regulariser {regularizer!r} (eps={eps})")
        print(f"  {'dof':>4} {'':6} {'PC .05':>9} {'PC .01':>9} {'EI':>9} "
              f"{'-%(.05) +/- SE':>16} {'-%(.01) +/- SE':>16} | paper PC .05 / PC .01 / EI")
        for dof, (row, per_set) in out.items():
            paper = PAPER_TABLE_ONE[dof]
            for k, name in enumerate(("det", "mse", "mse_truth")):
                v = row[name]
                red = [_reduction(per_set, name, a) for a in ALPHAS]
                k = min(k, 1)
                label = {"det": "det", "mse": "MSE", "mse_truth": "MSE(x)"}[name]
                print(f"  {dof:>4} {label:6} {v[0.05]:9.4f} {v[0.01]:9.4f} {v['EI']:9.4f} "
                      + " ".join(f"{100 * r.value:7.2f}% +/- {100 * r.se:5.2f}" for r in red)
                      + f" | {paper[3 * k]} / {paper[3 * k + 1]} / {paper[3 * k + 2]}")
            print(f"  {'':4} det(PC) <= det(EI) in every instance: {row['pc_not_above_ei']}; "
                  f"infeasible (test rejects) {row['infeasible']}; max KKT residual "
                  f"{max(row['kkt_max'].values()):.1e}")
        _print_trends({dof: row for dof, (row, _) in out.items()})
    table = {variant: {dof: row for dof, (row, _) in out.items()}
             for variant, out in results.items()}
    _print_nees(table)
    return table


def _print_trends(out):
    dofs = sorted(out)
    gain = [(out[d]["det"]["EI"] - out[d]["det"][0.05]) / out[d]["det"]["EI"] for d in dofs]
    grows = all(b >= a for a, b in zip(gain, gain[1:]))
    closer = all(out[d]["det"][0.01] >= out[d]["det"][0.05] for d in dofs)
    print(f"  trends: advantage grows with dof {grows} "
          f"({', '.join(f'{100 * g:.1f}%' for g in gain)}); alpha = 0.01 closer to EI than "
          f"0.05 {closer}")


def _print_nees(all_results):
    print("\nConservativeness on the Table I simulation: share of NEES within the 95% "
          "chi-square bound (95% or more for a conservative estimator) and mean NEES in "
          "parentheses (2 for a consistent one); the share of sets whose EI covariance bounds "
          "EI's true error covariance, and the worst factor by which it falls short")
    keys = ("optimal", "EI", 0.05, 0.01)
    names = ("optimal", "EI", "PC .05", "PC .01")
    print(f"  {'mutual mean':<11} {'regulariser':<11} {'dof':>4} "
          + " ".join(f"{name:>14}" for name in names) + f" {'EI P bounds':>12} {'excess':>7}")
    for (mutual_mean, regularizer), out in all_results.items():
        for dof, row in out.items():
            inside, mean = row["nees_inside"], row["mean_nees"]
            print(f"  {mutual_mean:<11} {regularizer:<11} {dof:>4} "
                  + " ".join(f"{100 * inside[key]:6.1f}% ({mean[key]:4.2f})" for key in keys)
                  + f" {100 * row['ei_bounds']:11.0f}% {row['ei_excess']:7.2f}")


def _network_study(rng, runs, rounds, dof):
    """Monte Carlo study of Section V-B: the same initial estimates for every method."""
    nodes = 1 + max(max(edge) for edge in NETWORK_EDGES)
    x0, P0 = _initial_estimates(runs, nodes, dof, rng)
    out = {}
    for label, method, options in NETWORK_METHODS:
        for key, values in _fuse_network(x0, P0, method, rounds, NETWORK_EDGES,
                                         options).items():
            out[(label, key)] = values
    return out


def _print_network(args, client):
    rounds = getattr(args, "rounds", 25)
    print(f"\nSection V-B: six-node network {NETWORK_EDGES}, {rounds} rounds, {args.runs} runs; "
          "determinant of node 0's covariance")
    arrays = run_study(_network_study, "naveen Section V-B", args.runs, args.seed,
                       NETWORK_SEED_KEY, client, chunk_size=NETWORK_CHUNK, rounds=rounds,
                       dof=30)
    print(f"  {'method':<14} {'mean det':>8} {'+/- SE':>7} {'centralised':>11} "
          f"{'P >= central':>12} {'nodes agree':>11} {'NEES in 95%':>11}")
    rows = {}
    for label, _, _ in NETWORK_METHODS:
        out = {key: values for (name, key), values in arrays.items() if name == label}
        det = Estimate.mean(np.linalg.det(out["P"][:, 0]))
        spread = np.abs(out["x"] - out["x"][:, :1]).max()
        contains = np.linalg.eigvalsh(out["P"][:, 0] - out["central_P"]).min(axis=-1) >= -1e-12
        nees = np.einsum("ri,rij,rj->r", out["x"][:, 0], np.linalg.inv(out["P"][:, 0]),
                         out["x"][:, 0])
        rows[label] = out
        central = np.linalg.det(out["central_P"]).mean()
        inside = np.mean(nees <= stats.chi2.ppf(0.95, 2))
        print(f"  {label:<14} {det.value:8.4f} {det.se:7.4f} {central:11.4f} "
              f"{100 * contains.mean():11.0f}% {spread:11.1e} {100 * inside:10.0f}%")
    print("  text: 'adding the probabilistic constraints leads to a fused covariance that is "
          "much less conservative than EI'")
    return rows


def _figures(directory, table, networks):
    import os

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plotting import plot_covariance_ellipse

    grid = np.linspace(0.2, 2.0, 181)
    grid = grid[np.abs(grid - 1.0) > 1e-9]
    fig, axes = plt.subplots(2, 2, figsize=(11, 8), layout="constrained")
    for column, mutual_mean in enumerate(("as-printed", "sijs-lazar")):
        c_ei, m_ei, _ = case_two(grid, None, mutual_mean=mutual_mean)
        c_pc, m_pc, _ = case_two(grid, 0.05, mutual_mean=mutual_mean)
        ax = axes[0, column]
        ax.plot(grid, m_ei[:, 0], "C0-", label="EI")
        ax.plot(grid, m_ei[:, 1], "C0-")
        ax.plot(grid, m_pc[:, 0], "C1--", label="PC (alpha 0.05)")
        ax.plot(grid, m_pc[:, 1], "C1--")
        ax.set(ylim=(-15, 15), xlabel="C_a", ylabel="independent means",
               title=f"Fig. 2a, mutual mean {mutual_mean!r}")
        ax.legend()
        ax = axes[1, column]
        ax.plot(grid, c_ei, "r-", label="EI")
        ax.plot(grid, c_pc, "b-", label="PC (alpha 0.05)")
        ax.plot(grid, c_pc - c_ei, "g-", label="difference")
        ax.set(xlabel="C_a", ylabel="common covariance", title="Fig. 2b")
        ax.legend()
    fig.savefig(os.path.join(directory, "naveen_fig2.png"), dpi=100)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(table), figsize=(5 * len(table), 4), layout="constrained")
    for ax, ((mutual_mean, regularizer), out) in zip(np.atleast_1d(axes), table.items()):
        data = [100 * (out[d]["det_all"]["EI"] - out[d]["det_all"][0.01]) / out[d]["det_all"]["EI"]
                for d in sorted(out)]
        boxes = ax.boxplot(data, tick_labels=[str(d) for d in sorted(out)])
        ax.set(xlabel="inverse-Wishart dof", ylabel="decrease of det vs EI [%]",
               title=f"Fig. 4 ({mutual_mean}, {regularizer})")
        ax.legend([boxes["boxes"][0]], ["PC (alpha 0.01) vs EI, per input set"],
                  fontsize="small")
    fig.savefig(os.path.join(directory, "naveen_fig4.png"), dpi=100)
    plt.close(fig)

    fig, axes = plt.subplots(1, len(networks), figsize=(4.5 * len(networks), 4.5),
                             layout="constrained")
    for ax, (label, out) in zip(np.atleast_1d(axes), networks.items()):
        for k in range(out["P0"].shape[1]):
            plot_covariance_ellipse(ax, out["P0"][0, k], confidence=None, color="0.75",
                                    label="initial (nodes)" if k == 0 else None)
        plot_covariance_ellipse(ax, out["central_P"][0], confidence=None, color="k",
                                label="centralised")
        plot_covariance_ellipse(ax, out["P"][0, 0], confidence=None, color="C3", label=label)
        ax.set(aspect="equal", title=f"Fig. 6: {label}")
        ax.legend(fontsize="small")
    fig.savefig(os.path.join(directory, "naveen_fig6.png"), dpi=100)
    plt.close(fig)
    print(f"\nfigures written to {directory}: naveen_fig2.png, naveen_fig4.png, naveen_fig6.png")


def run(args: argparse.Namespace) -> int:
    """Run the reproduction and print every number next to the paper's.

    Parameters
    ----------
    args : argparse.Namespace
        The options of :func:`add_arguments` (``workers``, ``scheduler`` and ``plot`` may
        be missing: in process, no figures).

    Returns
    -------
    int
        0.
    """
    _print_case_one()
    _print_case_two_three()
    with parallel_client(args) as client:
        table = _print_table_one(args, client)
        networks = _print_network(args, client)
    if getattr(args, "plot", None):
        _figures(args.plot, table, networks)
    return 0
