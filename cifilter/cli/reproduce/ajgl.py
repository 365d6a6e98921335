"""Ajgl, Šimandl, Reinhardt, Noack & Hanebeck (2014): batch versus recursive CI, Sec. IV.

``python -m cifilter reproduce ajgl [--plot DIR] [--horizons K]`` prints every number of
the static example (eqs. 22-28) and of the dynamical example (eqs. 29-35, Figs. 3-8) next
to the paper's, and with ``--plot`` writes Figs. 3-8 as PNG files.
"""

import argparse
import os

import numpy as np
from numpy.typing import NDArray

from ...horizon import horizon_study, optimal_omega, propagate_bound, steady_state_covariance
from ...rules.ci import covariance_intersection
from ..args import plot_directory, positive_int

DESCRIPTION = "Ajgl et al. 2014: horizon-aware omega, static and dynamical examples, Figs. 3-8"

# Eqs. (29)-(30)
F = 0.95 * np.eye(2)
Q = np.array([[1.0, 0.95], [0.95, 1.0]])
P0 = 10.0 * np.eye(2)
MODELS = {"A": (np.array([[1.0, 0.0]]), 1.0), "B": (np.array([[0.0, 1.0]]), 3.0)}
# Eqs. (22)-(23)
R_STATIC = {"A": np.diag([1.0, 2.0]), "B": np.diag([2.0, 1.0])}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``python -m cifilter reproduce ajgl``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The sub-command's parser.

    Returns
    -------
    None

    Examples
    --------
    >>> import argparse
    >>> from cifilter.cli.reproduce import ajgl
    >>> parser = argparse.ArgumentParser()
    >>> ajgl.add_arguments(parser)
    >>> parser.parse_args(["--horizons", "20"]).horizons
    20
    """
    parser.add_argument("--plot", metavar="DIR", type=plot_directory,
                        help="write Figs. 3-8 as PNG files to DIR")
    parser.add_argument("--horizons", type=positive_int, default=50,
                        help="largest horizon kappa of Figs. 3, 4, 6, 7 (default 50)")


def local_bounds_at_zero() -> tuple[NDArray[np.float64], ...]:
    """MMSE bounds of filters A and B at k = 0 (P_0 = 10 I, one local measurement each).

    Returns
    -------
    PA, PB : ndarray, shape (2, 2)
        ``diag(10/11, 10)`` and ``diag(10, 30/13)``, the inputs of eq. (34).

    Examples
    --------
    >>> from cifilter.cli.reproduce.ajgl import local_bounds_at_zero
    >>> [P.diagonal().round(4).tolist() for P in local_bounds_at_zero()]
    [[0.9091, 10.0], [10.0, 2.3077]]
    """
    bounds = []
    for H, R in MODELS.values():
        information = np.linalg.inv(P0) + H.T @ H / R
        bounds.append(np.linalg.inv(information))
    return tuple(bounds)


def _row(label, paper, computed):
    print(f"  {label:<46} {paper:>22}   {computed}")


def _matrix(M):
    return "[" + "; ".join(" ".join(f"{v:.4f}" for v in row) for row in M) + "]"


def _static():
    print("Static system, eqs. (22)-(28)")
    RA, RB = R_STATIC["A"], R_STATIC["B"]
    identity = np.eye(2)
    for criterion in ("det", "trace"):
        r = optimal_omega(RA, RB, identity, 0.0, identity, RA, 0, criterion)
        _row(f"omega without future data ({criterion}), eq. (24)", "1/2", f"{float(r.omega):.6f}")
    error = 0.0
    for omega in np.linspace(0.0, 1.0, 11):
        fused = covariance_intersection([np.zeros(2)] * 2, [RA, RB], omega=omega).P
        bound = propagate_bound(fused, identity, 0.0, identity, RA, 1)
        expected = np.diag([2 / (3 + omega), 2 / (3 - omega)])
        error = max(error, float(np.abs(bound - expected).max()))
    _row("eq. (28) diag(2/(3+w), 2/(3-w)): max error", "0", f"{error:.1e}")
    for name, paper in (("A", "0"), ("B", "1")):
        for criterion in ("det", "trace"):
            r = optimal_omega(RA, RB, identity, 0.0, identity, R_STATIC[name], 1, criterion)
            _row(f"omega, one future measurement in {name} ({criterion})", paper,
                 f"{float(r.omega):.6f}")


def _dynamic(horizons, at_steady_state):
    if at_steady_state:
        PA = steady_state_covariance(F, Q, *MODELS["A"])
        PB = steady_state_covariance(F, Q, *MODELS["B"])
        print("Dynamical system, fusion in the steady state (k -> infinity)")
        _row("P_inf^A, eq. (35)", "[0.6076 0.5772; 0.5772 1.5483]", _matrix(PA))
        _row("P_inf^B, eq. (35)", "[2.1216 1.1806; 1.1806 1.2427]", _matrix(PB))
        fusion_paper = {"det": "0.88", "trace": "0.69"}
        limit_paper = {"A": "0.14", "B": "0.69"}
    else:
        PA, PB = local_bounds_at_zero()
        print("Dynamical system, eqs. (29)-(34), fusion at k = 0")
        _row("P_0^A, P_0^B (eq. 34 inputs)", "diag(10/11,10), diag(10,30/13)",
             f"diag({PA[0, 0]:.4f},{PA[1, 1]:.4f}), diag({PB[0, 0]:.4f},{PB[1, 1]:.4f})")
        fusion_paper = {"det": "0.6", "trace": "~0.41"}
        limit_paper = {"A": "~0.04", "B": "~0.85"}
    studies = {}
    for criterion in ("det", "trace"):
        r = optimal_omega(PA, PB, F, Q, *MODELS["A"], 0, criterion)
        _row(f"omega at the fusion time ({criterion})", fusion_paper[criterion],
             f"{float(r.omega):.4f}")
    for name in ("A", "B"):
        for criterion in ("det", "trace"):
            s = horizon_study(PA, PB, F, Q, *MODELS[name], horizons, criterion)
            studies[name, criterion] = s
            _row(f"omega for kappa -> inf, filter {name} ({criterion})", limit_paper[name],
                 f"{float(s.omega_limit):.4f}")
    for name in ("A", "B"):
        for criterion in ("det", "trace"):
            s = studies[name, criterion]
            gain = 1.0 - s.batch / s.recursive
            worst = int(np.argmax(gain))
            _row(f"largest gain batch vs recursive, {name} ({criterion})", "(figure only)",
                 f"{100 * gain[worst]:.1f}% at kappa = {s.horizons[worst]}")
            _row("  batch <= recursive for all kappa; limit", "yes; steady value",
                 f"{bool(np.all(s.batch <= s.recursive * (1 + 1e-12)))}; "
                 f"{s.batch[-1]:.4f} -> {float(s.steady_value):.4f}")
    return PA, PB, studies


def run(args: argparse.Namespace) -> int:
    """Print the paper's numbers next to the computed ones; optionally draw Figs. 3-8.

    Parameters
    ----------
    args : argparse.Namespace
        ``plot`` (a directory or None) and ``horizons``.

    Returns
    -------
    int
        0.

    Examples
    --------
    >>> import argparse
    >>> from cifilter.cli.reproduce import ajgl
    >>> ajgl.run(argparse.Namespace(plot=None, horizons=10))  # doctest: +ELLIPSIS
    Static system, eqs. (22)-(28)
    ...
    0
    """
    horizons = max(int(args.horizons), 1)
    _static()
    print()
    at_zero = _dynamic(horizons, at_steady_state=False)
    print()
    at_steady = _dynamic(horizons, at_steady_state=True)
    if args.plot:
        os.makedirs(args.plot, exist_ok=True)
        written = _plot(args.plot, at_zero, at_steady)
        print()
        print("wrote " + ", ".join(written))
    return 0


def _plot(directory, at_zero, at_steady):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..plotting import covariance_ellipse

    written = []

    def save(fig, name):
        path = os.path.join(directory, name)
        fig.savefig(path, dpi=120)
        plt.close(fig)
        written.append(path)

    for (PA, PB, studies), first, when in ((at_zero, 3, "k = 0"),
                                           (at_steady, 6, "k -> infinity")):
        fig, ax = plt.subplots(figsize=(6, 4), layout="constrained")
        for name, color in (("A", "C0"), ("B", "C1")):
            for criterion, style in (("det", "-"), ("trace", "-.")):
                s = studies[name, criterion]
                ax.plot(s.horizons, s.omega, style, color=color, label=f"{name}, {criterion}")
        ax.set(xlabel="$\\kappa$", ylabel="optimal $\\omega$", ylim=(-0.02, 1.02),
               title=f"Fig. {first}: optimal omega, fusion at {when}")
        ax.legend()
        save(fig, f"ajgl_fig{first}.png")

        fig, axes = plt.subplots(2, 2, figsize=(9, 6), layout="constrained")
        for column, name in enumerate(("A", "B")):
            for row, criterion in enumerate(("det", "trace")):
                s, ax = studies[name, criterion], axes[row, column]
                ax.plot(s.horizons, s.batch, "-", label="omega optimised for each kappa")
                ax.plot(s.horizons, s.recursive, "--", label="omega fixed at the fusion")
                ax.axhline(float(s.steady_value), ls=":", color="k", label="steady state")
                ax.set(title=f"filter {name}, {criterion}", xlabel="$\\kappa$")
        axes[0, 0].legend(fontsize="small")
        fig.suptitle(f"Fig. {first + 1}: bounds, fusion at {when}")
        save(fig, f"ajgl_fig{first + 1}.png")

        fig, ax = plt.subplots(figsize=(8, 5), layout="constrained")
        for P, style, label in ((PA, "-", "$P^A$"), (PB, ":", "$P^B$")):
            points = covariance_ellipse(P, confidence=None)
            ax.plot(*points, style, color="gray", lw=1, label=label)
        choices = [
            (float(studies["A", "det"].omega_recursive), "--", "det at the fusion"),
            (float(studies["A", "trace"].omega_recursive), "-.", "trace at the fusion"),
            (float(studies["A", "det"].omega_limit), "-", "steady, filter A"),
            (float(studies["B", "det"].omega_limit), ":", "steady, filter B"),
        ]
        for omega, style, label in choices:
            fused = covariance_intersection([np.zeros(2)] * 2, [PA, PB], omega=omega).P
            points = covariance_ellipse(fused, confidence=None)
            ax.plot(*points, style, color="k", lw=2, label=f"{label} ($\\omega$={omega:.2f})")
        ax.set(aspect="equal", xlabel="$\\tilde x_1$", ylabel="$\\tilde x_2$",
               title=f"Fig. {first + 2}: ellipses, fusion at {when}")
        ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.02, 1.0))
        save(fig, f"ajgl_fig{first + 2}.png")
    return written
