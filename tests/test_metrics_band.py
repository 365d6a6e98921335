"""cifilter.metrics.pooled_anees_band: the band a consistent estimator's pooled ANEES lies
in, from the design effect of the values' correlation (docs/cli.rst derives it)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy import stats

from cifilter.metrics import pooled_anees_band


def test_hand_derived_band():
    # three runs of two values of a 1-D state: run sums 4, 4, 10 (sample variance 12); the
    # values' variances across runs 7 and 1 (sum 8): design effect d = 12 / 8 = 1.5, and
    # 2 * dim * d / (N * R) = 2 * 1 * 1.5 / (2 * 3) = 1/2: half width t_{0.975, 2} / sqrt(2).
    # (The t interval of the run means 2, 2, 5 would be 1 -+ t_{0.975, 2}: sqrt(3) / sqrt(3).)
    nees = np.array([[1.0, 3.0], [2.0, 2.0], [6.0, 4.0]])
    pooled, lower, upper = pooled_anees_band(nees, 1)
    assert pooled == 3.0
    assert lower == 0.0  # 1 - 3.04, clipped at 0
    assert upper == pytest.approx(1.0 + stats.t.ppf(0.975, 2) / np.sqrt(2), rel=1e-15)
    # the runs axis comes first; the other axes are flattened (steps, nodes)
    assert pooled_anees_band(nees.reshape(3, 2, 1), 1) == (pooled, lower, upper)


def test_design_effect_is_clipped_to_one_and_to_the_count():
    t = stats.t.ppf(0.975, 2)
    # negatively correlated values (equal run sums): d = 0, clipped to 1 (the NEES of
    # Gaussian errors are never negatively correlated)
    nees = np.array([[1.0, 3.0], [3.0, 1.0], [2.0, 2.0]])
    assert pooled_anees_band(nees, 2)[2] == pytest.approx(2 + t * np.sqrt(4 / 6), rel=1e-15)
    # no spread at all: nothing to estimate the correlation from, d = N (the widest band)
    assert pooled_anees_band(np.full((3, 2), 2.0), 2)[2] == pytest.approx(
        2 + t * np.sqrt(8 / 6), rel=1e-15)


def test_single_run_has_no_band():
    pooled, lower, upper = pooled_anees_band(np.full((1, 5), 3.0), 4)
    assert pooled == 3.0 and np.isnan(lower) and np.isnan(upper)


# values stay normal after scaling by 2**-40 (a subnormal times 2**k is not exact)
@given(arrays(np.float64, st.tuples(st.integers(2, 8), st.integers(1, 12)),
              elements=st.one_of(st.just(0.0), st.floats(1e-200, 50.0))),
       st.integers(-40, 40), st.integers(1, 6))
def test_band_does_not_depend_on_the_scale_of_the_values(nees, power, dim):
    """An estimator whose P is too small (or too large) by any factor gets the band of a
    consistent one: only the correlation of its values enters, not their spread. Scales
    2**-40 .. 2**40 (1e-12 .. 1e12) multiply exactly, so the band is the same bitwise."""
    scale = 2.0**power
    pooled, lower, upper = pooled_anees_band(nees, dim)
    assert pooled_anees_band(nees * scale, dim) == (pooled * scale, lower, upper)
    assert 0 <= lower < dim < upper
    # the widest band: every value of a run the same (d = N), one chi-square per run
    widest = stats.t.ppf(0.975, nees.shape[0] - 1) * np.sqrt(2 * dim / nees.shape[0])
    assert upper <= dim + widest * (1 + 1e-12)


@given(st.integers(0, 2**32 - 1), st.floats(1e-12, 1e12))
def test_band_of_drawn_nees_does_not_depend_on_any_scale(seed, scale):
    # any factor (it rounds every value): values with a genuine spread keep their band
    nees = np.random.default_rng(seed).chisquare(4, size=(6, 30))
    band = pooled_anees_band(nees, 4)[1:]
    assert pooled_anees_band(nees * scale, 4)[1:] == pytest.approx(band, rel=1e-12)


def _correlated_nees(rng, studies, model, scale=1.0):
    """NEES of consistent Gaussian errors, 10 runs x 40 steps x 6 nodes of a 4-D state:
    'shared' a run-wide error holding 70% of each value's variance, 'ar' an AR(1) over
    the steps (0.97) with node errors correlated 0.95 (a network's fused nodes).
    ``scale``: the NEES of the same errors with P multiplied by 1 / scale."""
    runs, steps, nodes, dim = 10, 40, 6, 4
    if model == "shared":
        shared = rng.standard_normal((studies, runs, 1, 1, dim))
        errors = np.sqrt(0.7) * shared + np.sqrt(0.3) * rng.standard_normal(
            (studies, runs, steps, nodes, dim))
    else:
        mix = np.linalg.cholesky(0.95 * np.ones((nodes, nodes)) + 0.05 * np.eye(nodes))
        errors = np.empty((studies, runs, steps, nodes, dim))
        state = np.einsum("ij,srjd->srid", mix, rng.standard_normal((studies, runs, nodes, dim)))
        for k in range(steps):
            if k:
                noise = np.einsum("ij,srjd->srid", mix,
                                  rng.standard_normal((studies, runs, nodes, dim)))
                state = 0.97 * state + np.sqrt(1 - 0.97**2) * noise
            errors[:, :, k] = state
    return scale * np.sum(errors**2, axis=-1)


@pytest.mark.parametrize("model", ["shared", "ar"])
def test_band_covers_a_consistent_estimator_at_the_nominal_rate(model):
    """2000 studies of a consistent estimator whose values are strongly correlated within
    a run: the band holds the pooled ANEES in at least 95% of them less the Monte Carlo
    error (3 standard errors, 1.5%) and at most 97.5% (with correlation this strong the
    band is a little wide: 95.6% and 96.2% in 10 000 studies; on the six-node network
    94.4% to 95.1%, docs/cli.rst), and it rejects the same estimator with P halved (NEES
    doubled) in at least 99%. The band from the rule's own spread of run means, before,
    covered 92.4% and 92.5% here and rejected P / 2 in 93.5% and 93.3%."""
    rng = np.random.default_rng(20)
    studies = 2000
    nees = _correlated_nees(rng, studies, model)
    covered = rejected = 0
    for values in nees:
        pooled, lower, upper = pooled_anees_band(values, 4)
        covered += lower <= pooled <= upper
        doubled, lower, upper = pooled_anees_band(2 * values, 4)
        rejected += doubled > upper
    error = 3 * np.sqrt(0.95 * 0.05 / studies)
    assert 0.95 - error <= covered / studies <= 0.975
    assert rejected / studies >= 0.99


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="nees_values must have a runs axis"):
        pooled_anees_band(3.0, 4)
    with pytest.raises(ValueError, match="nees_values must have a runs axis"):
        pooled_anees_band(np.zeros((0, 3)), 4)
    with pytest.raises(ValueError, match="nees_values must be finite and non-negative"):
        pooled_anees_band([[1.0, -1.0], [1.0, 2.0]], 4)
    with pytest.raises(ValueError, match="nees_values must be finite and non-negative"):
        pooled_anees_band([[1.0, np.nan], [1.0, 2.0]], 4)
    with pytest.raises(TypeError, match="nees_values must be a numeric array"):
        pooled_anees_band("many", 4)
    with pytest.raises(ValueError, match="dim must be >= 1"):
        pooled_anees_band([[1.0], [2.0]], 0)
    with pytest.raises(TypeError, match="dim must be an integer"):
        pooled_anees_band([[1.0], [2.0]], 4.0)
    with pytest.raises(ValueError, match=r"confidence must lie in \(0, 1\)"):
        pooled_anees_band([[1.0], [2.0]], 4, confidence=1.0)


def test_input_is_not_modified():
    nees = np.random.default_rng(1).chisquare(4, size=(5, 7))
    before = nees.copy()
    pooled_anees_band(nees, 4)
    assert np.array_equal(nees, before)
