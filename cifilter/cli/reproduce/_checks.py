"""Monte Carlo checks with standard errors, shared by the reproductions.

A reproduction compares a paper's claim ("the Bayesian MSE is lower than CI's at every
point") with simulated numbers. A simulated number is a smooth function of means over
independent runs, so it carries a standard error; :class:`Estimate` carries it along by
first-order propagation (the delta method): an estimate keeps, for every run, its
*influence*, the run's contribution to the estimate's deviation from its mean, and
``SE = sqrt(sum(influence^2) / (n (n - 1)))``. Sums, differences, products and ratios of
estimates over the same runs combine their influences, which keeps the pairing of runs
(two estimators fused on the same data are compared with the paired standard error).

A claim is a set of *margins*, estimates that are positive when the claim holds. Its
verdict is ``holds`` when every margin exceeds :data:`Z` standard errors, ``FAILS`` when
some margin is below ``-Z`` standard errors, and otherwise ``inconclusive at this size``:
the difference is within the Monte Carlo noise of the runs at hand.
"""

from collections.abc import Iterable, Sequence
from typing import Any, Optional, SupportsFloat, TextIO, Union

import numpy as np
from numpy.typing import ArrayLike, NDArray

__all__ = []

Z = 2.0  # standard errors a margin needs to count (about 95% two-sided)

HOLDS, FAILS, INCONCLUSIVE = "holds", "FAILS", "inconclusive at this size"


class Estimate:
    """A value computed from ``n`` independent runs, with its first-order influence per run."""

    __slots__ = ("influence", "value")

    def __init__(self, value: SupportsFloat, influence: Optional[NDArray[Any]]) -> None:
        self.value = float(value)
        self.influence = influence  # ndarray (n,) or None for a constant

    @classmethod
    def mean(cls, samples: ArrayLike) -> "Estimate":
        """The mean of per-run samples (first axis: runs; further axes are averaged too)."""
        samples = np.asarray(samples, dtype=float)
        per_run = samples.reshape(len(samples), -1).mean(axis=1)
        value = per_run.mean()
        return cls(value, per_run - value)

    @property
    def se(self) -> float:
        """The standard error (0 for a constant)."""
        if self.influence is None or len(self.influence) < 2:
            return 0.0
        n = len(self.influence)
        return float(np.sqrt(np.sum(self.influence**2) / (n * (n - 1))))

    def __float__(self):
        return self.value

    def __format__(self, spec):
        return format(self.value, spec)

    def __repr__(self):
        return f"Estimate({self.value:.6g} +/- {self.se:.2g})"

    # ------------------------------------------------------------------ arithmetic
    @staticmethod
    def _lift(other):
        return other if isinstance(other, Estimate) else Estimate(other, None)

    @staticmethod
    def _combine(a, b, ca, cb):
        """Influence ca * a + cb * b (either may be None)."""
        parts = [c * x for c, x in ((ca, a), (cb, b)) if x is not None]
        if not parts:
            return None
        if len(parts) == 2 and len(parts[0]) != len(parts[1]):
            raise ValueError("estimates from different numbers of runs cannot be combined")
        return parts[0] if len(parts) == 1 else parts[0] + parts[1]

    def __add__(self, other):
        other = self._lift(other)
        return Estimate(self.value + other.value,
                        self._combine(self.influence, other.influence, 1.0, 1.0))

    __radd__ = __add__

    def __neg__(self):
        return Estimate(-self.value, None if self.influence is None else -self.influence)

    def __sub__(self, other):
        return self + (-self._lift(other))

    def __rsub__(self, other):
        return self._lift(other) - self

    def __mul__(self, other):
        other = self._lift(other)
        return Estimate(self.value * other.value,
                        self._combine(self.influence, other.influence, other.value, self.value))

    __rmul__ = __mul__

    def __truediv__(self, other):
        other = self._lift(other)
        ratio = self.value / other.value
        return Estimate(ratio, self._combine(self.influence, other.influence,
                                             1.0 / other.value, -ratio / other.value))

    def __rtruediv__(self, other):
        return self._lift(other) / self


def mean_of(estimates: Iterable[Estimate]) -> Estimate:
    """The average of several estimates (e.g. over the points of a sweep)."""
    estimates = list(estimates)
    return sum(estimates[1:], estimates[0]) / len(estimates)


def verdict(margins: Sequence[tuple[str, Estimate]]) -> tuple[str, str, Estimate, float]:
    """The verdict of a claim and the margin that decides it.

    Parameters
    ----------
    margins : list of (str, Estimate)
        Labelled estimates, positive where the claim holds.

    Returns
    -------
    (str, str, Estimate, float)
        The verdict (``HOLDS``, ``FAILS`` or ``INCONCLUSIVE``), the deciding margin's label,
        the margin and its value in standard errors.
    """
    def z(estimate):
        se = estimate.se
        if se == 0.0:
            return np.inf if estimate.value > 0 else (-np.inf if estimate.value < 0 else 0.0)
        return estimate.value / se

    scored = [(label, m, z(m)) for label, m in margins]
    worst = min(scored, key=lambda item: item[2])
    if worst[2] < -Z:
        return (FAILS,) + worst
    if worst[2] > Z:
        return (HOLDS,) + worst
    return (INCONCLUSIVE,) + worst


class Claims:
    """Prints each claim with the paper's statement, our numbers and the decisive margin."""

    rows: list[tuple[str, str, str]]

    def __init__(self, out: TextIO) -> None:
        self.out, self.rows = out, []

    def add(self, where: str, text: str, paper: str, ours: str,
            margins: Sequence[Union[Estimate, tuple[str, Estimate]]]) -> str:
        """Judge and print one claim; ``margins`` as in :func:`verdict` (or bare estimates)."""
        margins = [m if isinstance(m, tuple) else (f"#{i}", m) for i, m in enumerate(margins)]
        # every item is a (label, estimate) pair now; mypy types the list by the parameter's
        # declared type
        result, label, margin, z = verdict(margins)  # type: ignore[arg-type]
        where_text = f" at {label}" if len(margins) > 1 else ""
        closest = ", the closest of " + str(len(margins)) if len(margins) > 1 else ""
        print(f"  [{result}] {text}\n      paper: {paper}\n      ours:  {ours}\n"
              f"      check: margin {margin.value:+.4g} +/- {margin.se:.2g} "
              f"({_z_text(z)}){where_text}{closest}", file=self.out)
        self.rows.append((where, text, result))
        return result

    def counts(self) -> dict[str, int]:
        """``{verdict: number of claims}``."""
        return {v: sum(1 for *_, r in self.rows if r == v) for v in (HOLDS, FAILS, INCONCLUSIVE)}

    def summary(self) -> None:
        """The table of every claim and the counts of each verdict."""
        print("\n" + "=" * 100 + "\nSummary of the claims (a margin must exceed "
              f"{Z:g} standard errors; 'inconclusive' = within the Monte Carlo noise)",
              file=self.out)
        print(f"  {'verdict':<26} {'where':<36} claim", file=self.out)
        for where, text, result in self.rows:
            print(f"  {result:<26} {where:<36} {text}", file=self.out)
        counts = self.counts()
        print(f"\n  {counts[HOLDS]} hold, {counts[FAILS]} fail, {counts[INCONCLUSIVE]} "
              "inconclusive at this size", file=self.out)


def _z_text(z):
    return "exact" if not np.isfinite(z) else f"{z:+.1f} SE"
