"""The horizon study (:mod:`cifilter.horizon.study`): ``horizon_study`` and its
``HorizonStudy`` result.

Ajgl et al. (2014): Figs. 3, 4 and 6 of the dynamical example (omega over the horizon, batch
below recursive, the steady state); the batch optimum is never above the recursive one
(Sec. III); the result's fields and plot; an unstable model's finite limit.
"""


import numpy as np
import pytest
from helpers import (
    F_DYN,
    F_UNSTABLE,
    FILTERS,
    H_A,
    H_B,
    Q_DYN,
    R_A,
    R_B,
    ci_bound,
    criterion_value,
    local_bounds_at_zero,
)
from hypothesis import given
from hypothesis import strategies as st
from strategies import systems

from cifilter.horizon import horizon_study, optimal_omega, propagate_bound, steady_state_covariance


# ----------------------------------------------------------------- dynamical example (IV.B)
@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_fig_3_omega_approaches_0_04_in_A_and_0_85_in_B(criterion):
    PA, PB = local_bounds_at_zero()
    limits = {}
    for name, (H, R) in FILTERS.items():
        s = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, 40, criterion)
        limits[name] = float(s.omega_limit)
        assert s.omega[0] == pytest.approx(0.6 if criterion == "det" else 0.41244, abs=1e-5)
        assert s.omega[-1] == pytest.approx(s.omega_limit, abs=1e-6)
    # the paper: omega ~ 0.04 (A) and ~ 0.85 (B); computed 0.04177 and 0.85317
    assert limits["A"] == pytest.approx(0.04, abs=0.005)
    assert limits["B"] == pytest.approx(0.85, abs=0.005)


def test_fig_3_limits_are_the_same_for_det_and_trace():
    PA, PB = local_bounds_at_zero()
    for H, R in FILTERS.values():
        det = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, 5, "det").omega_limit
        trace = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, 5, "trace").omega_limit
        assert float(det) == pytest.approx(float(trace), abs=1e-8)


def test_fig_3_shape_det_in_A_falls_monotonically_and_B_rises():
    PA, PB = local_bounds_at_zero()
    a = horizon_study(PA, PB, F_DYN, Q_DYN, H_A, R_A, 30, "det").omega
    b = horizon_study(PA, PB, F_DYN, Q_DYN, H_B, R_B, 30, "det").omega
    assert np.all(np.diff(a) <= 1e-12) and a[-1] < 0.05
    assert np.all(np.diff(b) >= -1e-12) and b[-1] > 0.85


@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_fig_4_batch_below_recursive_and_both_reach_the_steady_state(criterion):
    PA, PB = local_bounds_at_zero()
    for H, R in FILTERS.values():
        s = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, 200, criterion)
        assert s.batch[0] == pytest.approx(s.recursive[0], rel=1e-13)
        assert np.all(s.batch <= s.recursive * (1 + 1e-12))
        assert np.any(s.batch[1:] < s.recursive[1:] * (1 - 1e-3))  # a real gain somewhere
        gap = s.recursive - s.batch
        assert gap[-1] < 1e-6 * s.steady_value  # the influence of omega vanishes
        assert s.batch[-1] == pytest.approx(s.steady_value, rel=1e-6)
        np.testing.assert_allclose(s.P_batch[-1], s.steady_P, atol=1e-6)


def test_steady_state_fusion_omegas_and_fig_6_limits():
    PA = steady_state_covariance(F_DYN, Q_DYN, H_A, R_A)
    PB = steady_state_covariance(F_DYN, Q_DYN, H_B, R_B)
    det = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 0, "det")
    trace = optimal_omega(PA, PB, F_DYN, Q_DYN, H_A, R_A, 0, "trace")
    assert float(det.omega) == pytest.approx(0.88, abs=0.005)  # computed 0.8841
    assert float(trace.omega) == pytest.approx(0.69, abs=0.006)  # computed 0.6949
    for criterion in ("det", "trace"):
        a = horizon_study(PA, PB, F_DYN, Q_DYN, H_A, R_A, 5, criterion).omega_limit
        b = horizon_study(PA, PB, F_DYN, Q_DYN, H_B, R_B, 5, criterion).omega_limit
        assert float(a) == pytest.approx(0.14, abs=0.005)  # computed 0.1370
        assert float(b) == pytest.approx(0.69, abs=0.005)  # computed 0.6927


# ----------------------------------------------------------------- Sec. III: batch vs recursive
@given(systems(), st.sampled_from(["det", "trace", "weighted"]))
def test_batch_optimum_never_above_recursive_at_any_horizon(system, criterion):
    F, Q, H, R, PA, PB = system
    crit = np.diag([2.0, 0.5]) if criterion == "weighted" else criterion
    s = horizon_study(PA, PB, F, Q, H, R, 6, crit, limit=False)
    assert np.all(s.batch <= s.recursive * (1 + 1e-9) + 1e-300)
    assert s.batch[0] == pytest.approx(s.recursive[0], rel=1e-9)
    # the recursive bound is the fixed-omega propagation (eqs. 31-33)
    fixed = ci_bound(PA, PB, float(s.omega_recursive))
    history = propagate_bound(fixed, F, Q, H, R, 6, history=True)
    np.testing.assert_allclose(s.P_recursive, history, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(s.recursive, criterion_value(history, crit), rtol=1e-7)


# ----------------------------------------------------------------- the result
def test_a_batched_study_refuses_to_plot():
    # the fields and the plot's lines are checked against an independent filter in
    # test_horizon_scales.py::test_study_values_against_an_independent_filter_and_its_plot
    PA, PB = local_bounds_at_zero()
    batched = horizon_study(np.stack([PA, PB]), PB, F_DYN, Q_DYN, H_A, R_A, 2)
    assert batched.omega.shape == (2, 3)
    with pytest.raises(ValueError, match="batched"):
        batched.plot()


# ----------------------------------------------------------------- overflow and conditioning
def test_study_of_an_unstable_model_has_a_finite_limit_and_values():
    PA, PB = local_bounds_at_zero()
    s = horizon_study(PA, PB, F_UNSTABLE, np.eye(2), None, None, [0, 10, 300, 1000], "det")
    assert np.isfinite(s.batch).all() and np.isfinite(s.recursive).all()
    assert np.all(s.batch <= s.recursive * (1 + 1e-12))
    assert float(s.omega_limit) == pytest.approx(0.1014724336, abs=1e-9)
    assert s.steady_P is None
