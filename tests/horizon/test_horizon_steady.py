"""Long horizons (issue 21, item 5): the recursion's steady state is detected, so any
horizon answers without running every step, and the answers equal the plain step-by-step
recursion where both can be computed; a recursion that never repeats is refused above a
documented maximum.

The plain recursion is obtained by raising ``cifilter.horizon._model.STEADY_FROM`` (the
horizon from which the detection runs) above the horizon asked for.
"""

import numpy as np
import pytest
from helpers import F_DYN, FILTERS, Q_DYN, local_bounds_at_zero, random_system

from cifilter import fuse
from cifilter.horizon import (
    _model,
    horizon_study,
    horizon_weights,
    optimal_omega,
    propagate_bound,
    steady_state_covariance,
)


@pytest.fixture
def plain(monkeypatch):
    """Run the step-by-step recursion (no steady-state detection) inside the block."""
    class Plain:
        def __enter__(self):
            monkeypatch.setattr(_model, "STEADY_FROM", 10**15)

        def __exit__(self, *exc):
            monkeypatch.undo()

    return Plain()


def _same_choice(a, b):
    np.testing.assert_array_equal(a.omega, b.omega)
    np.testing.assert_array_equal(a.P, b.P)
    np.testing.assert_array_equal(a.value, b.value)


@pytest.mark.parametrize("name", ["A", "B"])
@pytest.mark.parametrize("criterion", ["trace", "det"])
@pytest.mark.parametrize("rho", [None, 0.5])
def test_horizon_a_million_is_the_steady_state_and_the_plain_recursion(plain, name, criterion,
                                                                      rho):
    PA, PB = local_bounds_at_zero()
    H, R = FILTERS[name]
    args = (PA, PB, F_DYN, Q_DYN, H, R)
    with plain:
        reference = optimal_omega(*args, 5000, criterion, rho=rho)
    # Above STEADY_FROM the detection runs: bitwise the plain recursion at 5000 (the
    # recursion of this model reaches a fixed point, so nothing but s is extrapolated) ...
    _same_choice(optimal_omega(*args, 5000, criterion, rho=rho), reference)
    for horizon in (10**6, 10**12):
        r = optimal_omega(*args, horizon, criterion, rho=rho)
        # ... and at any longer horizon the same answer (the fixed point repeats).
        _same_choice(r, reference)
        # The bound is the local filter's steady state (eq. 35): the fused information has
        # been forgotten.
        np.testing.assert_allclose(r.P, steady_state_covariance(F_DYN, Q_DYN, H, R),
                                   rtol=1e-12, atol=0)
    model = dict(F=F_DYN, Q=Q_DYN, H=H, R=R)
    options = {} if rho is None else {"rho": rho}
    method = "ci" if rho is None else "pci"
    estimates = [(np.zeros(2), PA), (np.ones(2), PB)]
    long = fuse(estimates, method=method, horizon=10**9, model=model, criterion=criterion,
                **options)
    with plain:
        short = fuse(estimates, method=method, horizon=5000, model=model, criterion=criterion,
                     **options)
    np.testing.assert_array_equal(long.P, short.P)
    np.testing.assert_array_equal(long.x, short.x)


def test_propagate_bound_beyond_the_steady_state_is_bitwise_the_plain_recursion(plain):
    PA, _ = local_bounds_at_zero()
    H, R = FILTERS["B"]
    with plain:
        reference = propagate_bound(PA, F_DYN, Q_DYN, H, R, 5000, history=True)
    history = propagate_bound(PA, F_DYN, Q_DYN, H, R, 5000, history=True)
    np.testing.assert_array_equal(history, reference)
    for horizon in (5000, 10**6, 10**15):
        np.testing.assert_array_equal(propagate_bound(PA, F_DYN, Q_DYN, H, R, horizon),
                                      reference[-1])
    np.testing.assert_allclose(reference[-1], steady_state_covariance(F_DYN, Q_DYN, H, R),
                               rtol=1e-12)


@pytest.mark.parametrize("seed", [0, 9, 31])
@pytest.mark.parametrize("criterion", ["trace", "det"])
def test_random_systems_at_5000_steps_equal_the_plain_recursion(plain, seed, criterion):
    """Models whose recursion repeats (with a period, seed 31 not a fixed point): at 5000
    steps the skipped periods change only the log scale ``s``, whose weighted term has
    long underflowed, so the answers are bitwise those of the plain recursion."""
    F, Q, H, R, P1, P2 = random_system(seed)
    with plain:
        reference = horizon_weights([P1, P2, P1 + P2], F, Q, H, R, 5000, criterion)
    _same_choice(horizon_weights([P1, P2, P1 + P2], F, Q, H, R, 5000, criterion), reference)
    # At 10^6 the phase of the cycle may differ from 5000's: the same to rounding.
    far = horizon_weights([P1, P2, P1 + P2], F, Q, H, R, 10**6, criterion)
    np.testing.assert_allclose(far.P, reference.P, rtol=1e-13, atol=0)
    np.testing.assert_allclose(far.omega, reference.omega, rtol=0, atol=1e-10)


def test_batched_models_and_studies(plain):
    PA, PB = local_bounds_at_zero()
    H, R = FILTERS["A"]
    F = np.stack([F_DYN, 0.9 * np.eye(2)])  # a batch of models: the batched recursion
    with plain:
        reference = optimal_omega(PA, PB, F, Q_DYN, H, R, 5000)
        study_ref = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, [0, 1, 50, 5000])
    _same_choice(optimal_omega(PA, PB, F, Q_DYN, H, R, 5000), reference)
    _same_choice(optimal_omega(PA, PB, F, Q_DYN, H, R, 10**7), reference)
    study = horizon_study(PA, PB, F_DYN, Q_DYN, H, R, [0, 1, 50, 5000, 10**8])
    np.testing.assert_array_equal(study.omega[:4], study_ref.omega)
    np.testing.assert_array_equal(study.batch[:4], study_ref.batch)
    assert study.omega[4] == study.omega[3] and study.batch[4] == study.batch[3]


def test_a_recursion_that_never_repeats_is_refused_above_the_maximum():
    """A rotating prediction-only model: the normalised transition turns by 1 rad per step
    and never repeats; beyond MAX_PLAIN_STEPS steps the horizon is refused, naming it."""
    c, s = np.cos(1.0), np.sin(1.0)
    F = 0.9 * np.array([[c, -s], [s, c]])
    P = np.diag([1.0, 2.0])
    with pytest.raises(ValueError, match=r"horizon=1000000 is too long: the Riccati recursion "
                                         r"of this model has not reached a steady state.*"
                                         r"within 50000 steps"):
        optimal_omega(P, 2.0 * P, F, np.eye(2), None, None, 10**6)
    # The bound alone (no transition to track) settles: the Lyapunov solution.
    np.testing.assert_allclose(propagate_bound(P, F, np.eye(2), None, None, 10**6),
                               steady_state_covariance(F, np.eye(2), None, None), rtol=0,
                               atol=1e-13 * 5.3)
