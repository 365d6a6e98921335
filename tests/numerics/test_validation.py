"""Input checking shared by every rule (cifilter._numerics.validation): directly and through
public calls."""

import re

import numpy as np
import pytest
import scipy.linalg
from hypothesis import given
from hypothesis import strategies as st
from strategies import ill_conditioned_sets

from cifilter import covariance_intersection, fuse, naive_fusion
from cifilter._numerics.linalg import IllConditionedError
from cifilter._numerics.validation import (
    PSD_RTOL,
    SYMMETRY_RTOL,
    Estimates,
    as_covariance_stack,
    as_covariances,
    as_estimates,
    as_float_array,
    as_matrix,
    as_mean_stack,
    as_rng,
    check_covariances,
    check_finite,
    check_int,
    check_psd,
    check_psd_weight_matrix,
    check_scalar,
    check_symmetric,
    check_weights,
    restore_style,
    vector_style,
)

I2 = np.eye(2)
Z2 = np.zeros(2)


# ------------------------------------------------------------------ item 8: complex input
@pytest.mark.parametrize("xs, Ps, message", [
    ([np.array([1 + 5j, 0]), Z2], [I2, I2], r"xs\[0\] must be real, got complex"),
    ([Z2, Z2], [I2, I2 * (1 + 0j)], r"Ps\[1\] must be real, got complex"),
    (np.array([[1j, 0], [0, 0]]), np.stack([I2, I2]), r"xs must be real"),
    ([np.array([1j, 0], dtype=object), Z2], [I2, I2], r"xs\[0\] must be a numeric array of real"),
])
@pytest.mark.parametrize("rule", [covariance_intersection, naive_fusion])
def test_complex_input_is_a_type_error_naming_the_argument(rule, xs, Ps, message):
    with pytest.raises(TypeError, match=message):
        rule(xs, Ps)


def test_complex_input_through_fuse_names_the_estimate():
    with pytest.raises(TypeError, match=r"estimates' x\[0\] must be real"):
        fuse([(np.array([1 + 5j, 0]), I2), (Z2, I2)])


@pytest.mark.parametrize("value, message", [
    (np.array([True, False]), "booleans"),
    (["1", "2"], "dtype <U1"),
    (np.array(["2020-01-01"], dtype="datetime64[D]"), "dtype datetime64"),
    ([[1.0, 2.0], [3.0]], "ragged"),
    (None, "NoneType"),
    ("1", "str"),
])
def test_as_float_array_rejects_what_is_not_real_numbers(value, message):
    with pytest.raises(TypeError, match=f"arg must be a numeric array.*{message}"):
        as_float_array(value, "arg")


def test_as_float_array_copies_integers_objects_and_read_only_input():
    source = np.arange(3)
    source.flags.writeable = False
    out = as_float_array(source, "arg")
    assert out.dtype == float and out.flags.writeable and not np.shares_memory(out, source)
    np.testing.assert_array_equal(as_float_array(np.array([1, 2], dtype=object), "a"), [1, 2])


# ------------------------------------------------------------------ item 9: shapes and names
@pytest.mark.parametrize("Ps, message", [
    ([np.ones(2), np.ones(2)],
     r"Ps\[0\] must be a square matrix \(\.\.\., n, n\), got shape \(2,\)"),
    ([I2, 1.0], r"Ps\[1\] must be a square matrix .* got shape \(\)"),
    ([I2, np.ones((2, 3))], r"Ps\[1\] must be a square matrix .* got shape \(2, 3\)"),
    ([np.stack([I2, I2]), I2], r"Ps\[1\] has shape \(2, 2\), but Ps\[0\] has shape \(2, 2, 2\)"),
    (np.ones((2, 2)), r"Ps must be a sequence of covariance matrices or an array"),
    ([np.zeros((0, 0))] * 2, r"dimension n >= 1"),
])
def test_covariances_of_the_wrong_dimension_are_named(Ps, message):
    with pytest.raises(ValueError, match=message):
        covariance_intersection([Z2, Z2], Ps)


@pytest.mark.parametrize("xs, Ps, message", [
    (np.zeros((3, 2, 2)), np.broadcast_to(I2, (4, 2, 2, 2)),
     r"batch shapes of xs \(3,\) and Ps \(4,\) do not broadcast"),
    ([Z2, np.array([np.nan, 0.0])], [I2, I2], r"xs\[1\] contains non-finite"),
    ([Z2, Z2], [I2, np.diag([np.inf, 1.0])], r"Ps\[1\] contains non-finite"),
    ([Z2, Z2], [I2, np.array([[1.0, 2.0], [0.0, 1.0]])], r"Ps\[1\] is not symmetric"),
    ([Z2, Z2], [-I2, I2], r"Ps\[0\] is not positive definite \(smallest eigenvalue -1\)"),
    ([np.float64(1.0), Z2], [I2, I2], r"xs\[0\] must have shape \(\.\.\., 2\)"),
    ([Z2], [I2], "at least 2 estimates"),
])
@pytest.mark.parametrize("rule", [covariance_intersection, naive_fusion])
def test_bad_estimates_are_named(rule, xs, Ps, message):
    with pytest.raises(ValueError, match=message):
        rule(xs, Ps)


def test_numerically_singular_covariance_says_ill_conditioned_with_its_condition_number():
    c, s = np.cos(0.3), np.sin(0.3)
    Q = np.array([[c, -s], [s, c]])
    P = Q @ np.diag([1e20, 17.0]) @ Q.T
    P = 0.5 * (P + P.T)  # symmetric, PD in exact arithmetic, Cholesky fails
    with pytest.raises(IllConditionedError, match=r"Ps\[1\] is too ill-conditioned.*condition "
                                                   r"number (infinite|\d)"):
        naive_fusion([Z2, Z2], [I2, P])
    with pytest.raises(IllConditionedError, match=r"Ps\[0\].*condition number infinite"):
        naive_fusion([Z2, Z2], [np.ones((2, 2)), I2])  # PSD, singular


def test_labels_name_the_estimates_instead_of_indices():
    labels = ("this filter", "other")
    with pytest.raises(ValueError, match=r"^other's P is not positive definite"):
        as_estimates([Z2, Z2], [I2, -I2], names=("x", "P"), labels=labels)
    with pytest.raises(ValueError, match=r"^this filter's P is not symmetric"):
        as_estimates([Z2, Z2], [I2 + np.eye(2, k=1), I2], names=("x", "P"), labels=labels)
    with pytest.raises(ValueError, match=r"^other's x contains non-finite"):
        as_estimates([Z2, [np.nan, 0]], [I2, I2], names=("x", "P"), labels=labels)
    with pytest.raises(TypeError, match=r"^this filter's x must be real"):
        as_estimates([Z2 + 1j, Z2], [I2, I2], names=("x", "P"), labels=labels)
    with pytest.raises(ValueError, match=r"^other's P is too ill-conditioned"):
        check_covariances(np.stack([I2, np.ones((2, 2))]), "P", labels=labels)


def test_check_symmetric_accepts_filterpy_rounding_and_names_typos():
    P = np.array([[2.0, 1.0], [1.0 + 1e-15, 3.0]])
    S = check_symmetric(P, "P")
    np.testing.assert_array_equal(S, S.T)
    assert P[1, 0] == 1.0 + 1e-15  # not modified
    with pytest.raises(ValueError, match=r"P\[1\] is not symmetric"):
        check_symmetric(np.stack([I2, I2 + np.eye(2, k=1)]), "P")


# ------------------------------------------------------------------ weights (omega, delta)
def test_check_weights_with_batch_shape_broadcasts_or_names_the_mismatch():
    w = check_weights([0.25, 0.75], 2, batch_shape=(3,))
    assert w.shape == (3, 2) and w.flags.writeable
    np.testing.assert_array_equal(w[2], [0.25, 0.75])
    w = check_weights(np.array(0.25), 2, batch_shape=())  # a 0-d array is a scalar
    np.testing.assert_array_equal(w, [0.25, 0.75])
    with pytest.raises(ValueError, match=r"omega has shape \(2, 2\), whose batch axes \(2,\) do "
                                         r"not broadcast to the estimates' batch shape \(\)"):
        check_weights([[0.5, 0.5], [0.2, 0.8]], 2, batch_shape=())
    with pytest.raises(ValueError, match=r"delta has shape \(4, 2\).*batch shape \(3,\)"):
        check_weights(np.full((4, 2), 0.5), 2, "delta", batch_shape=(3,))
    assert check_weights([[0.5, 0.5], [0.2, 0.8]], 2).shape == (2, 2)  # no batch_shape: as before


@pytest.mark.parametrize("omega, error, message", [
    (np.nan, ValueError, "omega contains non-finite"),
    ([np.nan, 1.0], ValueError, "omega contains non-finite"),
    (True, TypeError, "omega must be a numeric array, got booleans"),
    (0.5 + 0.5j, TypeError, "omega must be real"),
    ([0.5, 0.5, 0.0], ValueError, r"omega must have shape \(\.\.\., 2\)"),
    ([[0.5, 0.5], [0.7, 0.7]], ValueError, r"omega\[1\] must lie on the simplex"),
])
def test_bad_weights_are_named(omega, error, message):
    with pytest.raises(error, match=message):
        check_weights(omega, 2)


def test_check_scalar_accepts_zero_dimensional_arrays_and_rejects_numpy_bools():
    assert check_scalar(np.array(0.5), "alpha", low=0, high=1) == 0.5
    with pytest.raises(TypeError, match="alpha must be a real number"):
        check_scalar(np.bool_(True), "alpha")
    with pytest.raises(TypeError, match="alpha must be a real number"):
        check_scalar(np.array([0.5]), "alpha")


def test_check_psd_accepts_semidefinite_and_names_indefinite():
    M = check_psd(np.diag([1.0, 0.0]), 2, "criterion")
    np.testing.assert_array_equal(M, np.diag([1.0, 0.0]))
    check_psd(np.diag([1.0, -1e-12]), 2, "criterion")  # rounding-level negative: accepted
    with pytest.raises(ValueError, match=r"criterion must be positive semidefinite .*-0\.1"):
        check_psd(np.diag([1.0, -0.1]), 2, "criterion")


# ------------------------------------------------------------------ contracts of the checks
def test_inputs_are_never_modified_or_aliased():
    x = np.array([[1.0], [2.0]])
    P = np.array([[2.0, 0.5], [0.5 + 1e-14, 1.0]])  # symmetrised inside, not here
    for array in (x, P):
        array.flags.writeable = False  # read-only input works and cannot be written
    est = as_estimates([x, np.zeros(2)], [P, I2])
    assert not np.shares_memory(est.P, P) and not np.shares_memory(est.x, x)
    assert P[1, 0] == 0.5 + 1e-14
    r = covariance_intersection([x, np.zeros(2)], [P, I2])
    assert r.x.shape == (2, 1) and np.all(np.isfinite(r.P))


def test_validation_does_not_compute_eigenvalues_on_success(monkeypatch):
    """Latency: the success path is one symmetry test and one Cholesky factorisation."""
    def forbidden(*args, **kwargs):
        raise AssertionError("eigendecomposition on the success path")

    for name in ("eig", "eigh", "eigvals", "eigvalsh", "svd"):
        monkeypatch.setattr(np.linalg, name, forbidden)
    P1, P2 = np.diag([1.0, 4.0]), np.array([[2.0, 0.3], [0.3, 1.0]])
    naive_fusion([Z2, Z2], [P1, P2])
    covariance_intersection([Z2, Z2], [P1, P2], omega=0.3)
    covariance_intersection([Z2, Z2], [P1, P2], omega=0.3, criterion=np.diag([1.0, 0.0]))
    as_estimates(np.zeros((5, 3, 2)), np.broadcast_to(P2, (5, 3, 2, 2)))


# ------------------------------------------------------------------ vector styles
@pytest.mark.parametrize("x, column", [
    ([np.zeros(3), np.ones(3)], False),
    ([np.zeros((3, 1)), np.ones(3)], True),
    (np.zeros((2, 3)), False),
    (np.zeros((2, 3, 1)), True),
    (np.zeros((7, 2, 3)), False),
    (np.zeros((7, 2, 3, 1)), True),
])
def test_vector_styles_are_recognised(x, column):
    est = as_estimates(x, np.stack([np.eye(3)] * 2))
    assert est.column is column
    assert est.x.shape[-2:] == (2, 3)


def test_one_dimensional_styles_are_unambiguous():
    P = np.ones((2, 1, 1))
    assert not as_estimates(np.zeros((2, 1)), P).column  # two scalars in a row
    assert as_estimates(np.zeros((2, 1, 1)), P).column  # two 1x1 columns
    est = as_estimates(np.zeros((5, 2, 1)), P)  # a batch of five
    assert not est.column and est.batch_shape == (5,)


def test_helpers_reject_bad_scalars_weights_and_rngs():
    with pytest.raises(ValueError, match=r"alpha must lie in \(0, 1\)"):
        check_scalar(1.0, "alpha", low=0, high=1, low_open=True, high_open=True)
    with pytest.raises(TypeError, match="alpha must be a real number"):
        check_scalar("0.1", "alpha")
    with pytest.raises(ValueError, match="finite"):
        check_scalar(float("nan"), "alpha")
    with pytest.raises(ValueError, match="simplex"):
        check_weights([0.7, 0.7], 2)
    with pytest.raises(TypeError, match="rng"):
        as_rng("seed")
    assert as_rng(3).integers(1000) == np.random.default_rng(3).integers(1000)


# ------------------------------------------------------------------ layouts and broadcasting
def test_sequences_and_stacked_arrays_give_the_same_estimates():
    rng = np.random.default_rng(2)
    xs = [rng.standard_normal((4, 3)) for _ in range(3)]  # a batch of 4, N = 3, n = 3
    A = rng.standard_normal((3, 4, 3, 3))
    Ps = [a @ np.swapaxes(a, -1, -2) + np.eye(3) for a in A]
    from_sequences = as_estimates(xs, Ps)
    from_arrays = as_estimates(np.stack(xs, axis=-2), np.stack(Ps, axis=-3))
    assert isinstance(from_sequences, Estimates)
    assert (from_sequences.count, from_sequences.dim, from_sequences.batch_shape) == (3, 3, (4,))
    for a, b in zip(from_sequences[:3], from_arrays[:3]):
        np.testing.assert_array_equal(a, b)
    assert from_sequences.x.shape == (4, 3, 3) and from_sequences.P.shape == (4, 3, 3, 3)
    np.testing.assert_array_equal(from_sequences.x[:, 1], xs[1])
    np.testing.assert_allclose(from_sequences.L @ np.swapaxes(from_sequences.L, -1, -2),
                               from_sequences.P, rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(np.triu(from_sequences.L, 1), 0.0)


def test_style_follows_the_first_input_only():
    est = as_estimates([np.zeros((2, 1)), np.zeros(2)], [I2, I2])
    assert est.column and est.x.shape == (2, 2)
    est = as_estimates([np.zeros(2), np.zeros((2, 1))], [I2, I2])
    assert not est.column
    np.testing.assert_array_equal(restore_style(np.arange(2.0), True), [[0.0], [1.0]])
    np.testing.assert_array_equal(restore_style(np.ones((5, 2)), True).shape, (5, 2, 1))
    np.testing.assert_array_equal(restore_style(np.arange(2.0), False), [0.0, 1.0])


@pytest.mark.parametrize("shape, n, style", [
    ((3,), 3, "row"), ((3, 1), 3, "column"), ((5, 3), 3, "row"), ((5, 3, 1), 3, "column"),
    ((1, 1), 1, "column"), ((1,), 1, "row"), ((4,), 3, None), ((3, 2), 3, None), ((), 1, None),
])
def test_vector_style(shape, n, style):
    assert vector_style(np.zeros(shape), n) == style


@pytest.mark.parametrize("x_shape, P_shape, batch", [
    ((3, 2, 2), (2, 2, 2), (3,)),  # batch of means, one pair of covariances
    ((2, 2), (4, 2, 2, 2), (4,)),  # one pair of means, batch of covariances
    ((5, 1, 2, 2), (1, 3, 2, 2, 2), (5, 3)),  # both broadcast
])
def test_batch_axes_of_means_and_covariances_broadcast_into_private_copies(x_shape, P_shape,
                                                                          batch):
    x = np.arange(np.prod(x_shape), dtype=float).reshape(x_shape)
    P = np.broadcast_to(np.diag([2.0, 3.0]), P_shape)  # read-only view
    est = as_estimates(x, P)
    assert est.batch_shape == batch
    assert est.x.shape == batch + (2, 2) and est.P.shape == est.L.shape == batch + (2, 2, 2)
    for array in est[:3]:
        assert array.flags.writeable
        assert not np.shares_memory(array, x) and not np.shares_memory(array, P)
    est.x[...] = -1.0  # writing the result cannot touch the input
    est.P[...] = 0.0
    assert x.min() >= 0.0 and P[(0,) * (len(P_shape) - 2)][0, 0] == 2.0
    np.testing.assert_array_equal(est.L[(0,) * len(batch) + (1,)], np.diag(np.sqrt([2.0, 3.0])))


def test_counts_and_minimum_counts():
    with pytest.raises(ValueError, match=r"^xs has 3 estimates but the covariances have 2"):
        as_estimates([Z2, Z2, Z2], [I2, I2])
    with pytest.raises(ValueError, match=r"^xs must be a sequence of 2 vectors or an array of "
                                         r"shape \(\.\.\., 2, 2\).*got shape \(3, 2\)"):
        as_estimates(np.zeros((3, 2)), [I2, I2])
    with pytest.raises(ValueError, match="at least 3 estimates are needed, got 2"):
        as_estimates([Z2, Z2], [I2, I2], min_count=3)
    assert as_estimates([Z2], [I2], min_count=1).count == 1
    with pytest.raises(ValueError, match=r"^Ps is empty"):
        as_estimates([], [])


def test_as_covariances_has_zero_means_and_checks_the_covariances():
    est = as_covariances(np.broadcast_to(np.diag([1.0, 4.0]), (3, 2, 2)), min_count=3)
    assert est.x.shape == (3, 2) and not est.x.any() and not est.column
    np.testing.assert_array_equal(est.L[2], np.diag([1.0, 2.0]))
    with pytest.raises(ValueError, match="at least 2 estimates are needed, got 1"):
        as_covariances([I2])
    with pytest.raises(ValueError, match=r"^Q\[1\] is not positive definite"):
        as_covariances([I2, -I2], name="Q")
    with pytest.raises(IllConditionedError, match=r"^Q\[0\] is too ill-conditioned"):
        as_covariances([np.ones((2, 2)), I2], name="Q")


def test_as_mean_stack_and_as_covariance_stack_directly():
    x, column = as_mean_stack([np.zeros((2, 1)), np.ones((2, 1))], 2, 2, "means")
    assert column and x.shape == (2, 2)
    np.testing.assert_array_equal(x[1], [1.0, 1.0])
    with pytest.raises(ValueError, match=r"^means\[1\] must have shape \(\.\.\., 2\) or "
                                         r"\(\.\.\., 2, 1\) to match its 2x2 covariance, "
                                         r"got shape \(3,\)"):
        as_mean_stack([Z2, np.zeros(3)], 2, 2, "means")
    with pytest.raises(ValueError, match=r"^other's x must have shape"):
        as_mean_stack([Z2, np.zeros(3)], 2, 2, "x", labels=("mine", "other"))
    P = as_covariance_stack((I2, 2 * I2))  # a tuple is a sequence too
    assert P.shape == (2, 2, 2) and P[1, 0, 0] == 2.0
    with pytest.raises(ValueError, match=r"^other's P has shape \(3, 3\), but mine's P"):
        as_covariance_stack([I2, np.eye(3)], "P", labels=("mine", "other"))


# ------------------------------------------------------------------ bad values, named
@pytest.mark.parametrize("xs, Ps, error, message", [
    (["a", "b"], [I2, I2], TypeError, r"^xs\[0\] must be a numeric array, got str"),
    ([Z2, Z2], [I2.astype(bool)] * 2, TypeError, r"^Ps\[0\] must be a numeric array, got bool"),
    (np.zeros((2, 2)), np.array([[["1", "0"], ["0", "1"]]] * 2), TypeError,
     r"^Ps must be a numeric array, got dtype <U1"),
    ([None, Z2], [I2, I2], TypeError, r"^xs\[0\] must be a numeric array, got NoneType"),
    ([Z2, Z2], None, TypeError, r"^Ps must be a numeric array, got NoneType"),
    (np.array([[0.0, np.inf], [0.0, 0.0]]), [I2, I2], ValueError,
     r"^xs\[0\] contains non-finite"),
    (np.zeros((3, 2, 2)), np.stack([I2, I2]), ValueError, None),  # fine: a batch of means
    ([Z2, Z2], np.stack([[I2, I2], [I2, I2 + np.eye(2, k=-1)]]), ValueError,
     r"^Ps\[1, 1\] is not symmetric"),
    ([Z2, Z2], np.stack([[I2, I2], [I2, np.diag([1.0, np.nan])]]), ValueError,
     r"^Ps\[1, 1\] contains non-finite"),
])
def test_as_estimates_names_the_bad_argument(xs, Ps, error, message):
    if message is None:
        as_estimates(xs, Ps)
        return
    with pytest.raises(error, match=message):
        as_estimates(xs, Ps)


def test_as_estimates_names_the_ill_conditioned_covariance():
    c, s = np.cos(0.3), np.sin(0.3)
    Q = np.array([[c, -s], [s, c]])
    P = Q @ np.diag([1e20, 17.0]) @ Q.T
    P = 0.5 * (P + P.T)  # PD in exact arithmetic, not numerically
    with pytest.raises(IllConditionedError, match=r"^Ps\[2\] is too ill-conditioned"):
        as_estimates([Z2] * 3, [I2, I2, P])
    with pytest.raises(IllConditionedError, match=r"^other's P is too ill-conditioned.*"
                                                   r"condition number"):
        as_estimates([Z2] * 2, [I2, P], names=("x", "P"), labels=("this filter", "other"))
    with pytest.raises(ValueError, match=r"^Ps\[0, 1\] is not positive definite"):
        as_estimates(np.zeros((2, 2, 2)), np.stack([[I2, I2], [I2, -I2]])[::-1])


def test_symmetry_tolerance_is_relative_to_the_diagonal():
    for scale in (1e-12, 1.0, 1e12):
        nearly = scale * np.array([[1.0, 0.5], [0.5 + 0.1 * SYMMETRY_RTOL, 1.0]])
        S = check_symmetric(nearly, "P")
        np.testing.assert_array_equal(S, S.T)
        assert S[0, 1] == pytest.approx(scale * (0.5 + 0.05 * SYMMETRY_RTOL), rel=1e-15)
        typo = scale * np.array([[1.0, 0.5], [0.5 + 10 * SYMMETRY_RTOL, 1.0]])
        with pytest.raises(ValueError, match=r"^P is not symmetric \(max \|P - P\^T\| = "):
            check_symmetric(typo, "P")
    with pytest.raises(ValueError, match=r"must hold square matrices"):
        check_symmetric(np.ones((2, 3)), "P")
    with pytest.raises(ValueError, match=r"dimension n >= 1"):
        check_symmetric(np.ones((2, 0, 0)), "P")
    with pytest.raises(ValueError, match=r"^P is empty"):
        check_symmetric(np.ones((0, 2, 2)), "P")


def test_check_covariances_with_known_factors_skips_the_factorisation():
    P = np.stack([I2, np.diag([4.0, 9.0])])
    L = np.full_like(P, 7.0)  # trusted as given
    P_out, L_out = check_covariances(P, "P", L)
    assert L_out is L
    np.testing.assert_array_equal(P_out, P)


@given(st.integers(1, 4).flatmap(lambda n: ill_conditioned_sets(3, n, common_scale=False)))
def test_ill_conditioned_inputs_within_the_contract_are_accepted_unchanged(Ps):
    """Condition numbers up to 1e12 and scales 1e-12..1e12 validate; P is only symmetrised."""
    copies = [P.copy() for P in Ps]
    est = as_estimates([np.zeros(len(P)) for P in Ps], Ps)
    for P, copy in zip(Ps, copies):
        np.testing.assert_array_equal(P, copy)  # not modified
    np.testing.assert_array_equal(est.P, 0.5 * (np.stack(Ps) + np.swapaxes(np.stack(Ps), 1, 2)))
    np.testing.assert_array_equal(est.P, np.swapaxes(est.P, -1, -2))
    assert (np.diagonal(est.L, axis1=-2, axis2=-1) > 0).all()
    scale = np.abs(est.P).max(axis=(-2, -1), keepdims=True)
    residual = np.abs(est.L @ np.swapaxes(est.L, -1, -2) - est.P) / scale
    assert residual.max() < 1e-12


# ------------------------------------------------------------------ weights
def test_scalar_weights_are_for_two_estimates_only():
    for omega in (0.3, np.float32(0.25), np.array(0.25), 1, np.int64(0)):
        w = check_weights(omega, 2)
        assert w.shape == (2,) and w.sum() == 1.0
        np.testing.assert_allclose(w, [float(omega), 1.0 - float(omega)])
    with pytest.raises(ValueError, match=r"^a scalar omega is only defined for two estimates; "
                                         r"give an array of 3 weights"):
        check_weights(0.3, 3)
    with pytest.raises(ValueError, match=r"^a scalar delta is only defined"):
        check_weights(np.array(0.5), 1, "delta")
    with pytest.raises(TypeError, match="booleans"):
        check_weights(np.bool_(True), 2)
    with pytest.raises(ValueError, match=r"omega must lie on the simplex"):
        check_weights(1.5, 2)


def test_simplex_tolerance_accepts_rounding_and_renormalises():
    w = check_weights([1.0 + 5e-10, -5e-10], 2)
    np.testing.assert_array_equal(w, [1.0, 0.0])  # clipped and renormalised exactly
    w = check_weights([0.2, 0.3, 0.5 + 9e-10], 3)
    assert (w >= 0).all() and w.sum() == pytest.approx(1.0, abs=1e-15)
    with pytest.raises(ValueError, match=r"^omega must lie on the simplex .*-2\.e-09"):
        check_weights([1.0 + 2e-9, -2e-9], 2)
    with pytest.raises(ValueError, match=r"^omega must lie on the simplex"):
        check_weights([0.2, 0.3, 0.5 + 2e-9], 3)
    with pytest.raises(ValueError, match=r"^omega\[0, 1\] must lie on the simplex"):
        check_weights(np.array([[[0.5, 0.5], [0.9, 0.2]]]).reshape(1, 2, 2), 2)


@pytest.mark.parametrize("shape, batch_shape, ok", [
    ((2,), (), True), ((2,), (4, 3), True), ((1, 2), (3,), True), ((3, 2), (4, 3), True),
    ((4, 1, 2), (4, 3), True), ((3, 2), (3,), True),
    ((2, 2), (), False), ((3, 2), (4,), False), ((4, 3, 2), (3,), False),
    ((2, 3, 2), (1, 3), False),
])
def test_weights_broadcast_to_the_batch_shape_or_are_rejected(shape, batch_shape, ok):
    omega = np.broadcast_to([0.25, 0.75], shape)
    if not ok:
        with pytest.raises(ValueError, match=r"do not broadcast to the estimates' batch shape"):
            check_weights(omega, 2, batch_shape=batch_shape)
        return
    w = check_weights(omega, 2, batch_shape=batch_shape)
    assert w.shape == tuple(batch_shape) + (2,) and w.flags.writeable
    assert not np.shares_memory(w, omega)
    np.testing.assert_array_equal(w, np.broadcast_to([0.25, 0.75], w.shape))


def test_check_weights_does_not_modify_its_input():
    omega = np.array([1.0 + 5e-10, -5e-10])
    w = check_weights(omega, 2)
    w[:] = 7.0
    np.testing.assert_array_equal(omega, [1.0 + 5e-10, -5e-10])


# ------------------------------------------------------------------ scalars, integers, rngs
@pytest.mark.parametrize("kwargs, value, accepted", [
    ({"low": 0, "high": 1}, 0.0, True),
    ({"low": 0, "high": 1}, 1.0, True),
    ({"low": 0, "high": 1, "low_open": True}, 0.0, False),
    ({"low": 0, "high": 1, "high_open": True}, 1.0, False),
    ({"low": 0, "low_open": True}, 1e300, True),
    ({"high": -1}, -1e300, True),
    ({"high": -1}, 0.0, False),
])
def test_check_scalar_bounds(kwargs, value, accepted):
    if accepted:
        out = check_scalar(value, "alpha", **kwargs)
        assert out == value and type(out) is float
    else:
        with pytest.raises(ValueError, match=r"^alpha must lie in [\[(].*[\])], got"):
            check_scalar(value, "alpha", **kwargs)


def test_check_scalar_message_shows_the_interval():
    with pytest.raises(ValueError, match=r"^alpha must lie in \(0, 1\], got 0\.0$"):
        check_scalar(0, "alpha", low=0, high=1, low_open=True)
    with pytest.raises(ValueError, match=r"^alpha must lie in \(-inf, 2\), got 3\.0$"):
        check_scalar(3, "alpha", high=2, high_open=True)
    assert check_scalar(np.int64(3), "alpha") == 3.0
    for bad in (np.inf, -np.inf, np.nan):
        with pytest.raises(ValueError, match=r"^alpha must be finite"):
            check_scalar(bad, "alpha")
    for bad in (True, np.array(True), 1j, None, [0.5], np.array([0.5])):
        with pytest.raises(TypeError, match=r"^alpha must be a real number"):
            check_scalar(bad, "alpha")


def test_check_scalar_unbounded_side_is_shown_open():
    with pytest.raises(ValueError, match=r"must lie in \[0, inf\), got -1\.0"):
        check_scalar(-1, "alpha", low=0)


def test_check_int():
    assert check_int(3, "k") == 3 and type(check_int(np.int64(3), "k")) is int
    assert check_int(4, "k", low=4) == 4
    with pytest.raises(ValueError, match=r"^k must be >= 4, got 3"):
        check_int(np.int32(3), "k", low=4)
    for bad in (True, np.bool_(False), 2.0, "2", None):
        with pytest.raises(TypeError, match=r"^k must be an integer"):
            check_int(bad, "k")


def test_as_rng():
    generator = np.random.default_rng(5)
    assert as_rng(generator) is generator
    assert as_rng(3).integers(1000) == np.random.default_rng(3).integers(1000)
    assert as_rng(np.int64(3)).integers(1000) == np.random.default_rng(3).integers(1000)
    sequence = np.random.SeedSequence(8)
    assert as_rng(sequence).random() == np.random.default_rng(np.random.SeedSequence(8)).random()
    assert isinstance(as_rng(None), np.random.Generator)
    assert as_rng(None).random() != as_rng(None).random()  # fresh entropy each time
    for bad in ("seed", 1.5, np.random.RandomState(0), [1, 2]):
        with pytest.raises(TypeError, match=r"^rng must be a numpy.random.Generator, an integer "
                                            r"seed or None, got"):
            as_rng(bad)


# ------------------------------------------------------------------ matrices, weight matrices
def test_as_matrix_and_check_finite():
    M = as_matrix([[1, 2, 3]], "H", (None, 3))
    assert M.dtype == float and M.shape == (1, 3)
    with pytest.raises(ValueError, match=r"^H must be a matrix \(\.\.\., rows, columns\)"):
        as_matrix([1.0, 2.0], "H")
    with pytest.raises(ValueError, match=r"^H must have shape \(\.\.\., p, 2\), got shape "
                                         r"\(1, 3\)"):
        as_matrix(M, "H", (None, 2))
    with pytest.raises(ValueError, match=r"^H must have shape \(\.\.\., 2, 3\)"):
        as_matrix(M, "H", (2, 3))
    with pytest.raises(ValueError, match=r"^H contains non-finite"):
        as_matrix([[np.nan]], "H")
    check_finite(np.ones(3), "v")
    with pytest.raises(ValueError, match=r"^v contains non-finite"):
        check_finite(np.array([1.0, -np.inf]), "v")


def test_check_psd_numbers_shapes_symmetry_and_batches():
    np.testing.assert_array_equal(check_psd(2, 3, "Q"), 2.0 * np.eye(3))
    np.testing.assert_array_equal(check_psd(0.0, 2, "Q"), np.zeros((2, 2)))  # PSD, allowed
    with pytest.raises(ValueError, match=r"^Q must be positive semidefinite \(smallest "
                                         r"eigenvalue -2\)"):
        check_psd(-2.0, 2, "Q")
    with pytest.raises(TypeError, match=r"^Q must be a numeric array, got booleans"):
        check_psd(True, 2, "Q")
    with pytest.raises(ValueError, match=r"^Q must have shape \(\.\.\., 2, 2\)"):
        check_psd(np.eye(3), 2, "Q")
    with pytest.raises(ValueError, match=r"^Q must be symmetric"):
        check_psd(np.array([[1.0, 1.0], [0.0, 1.0]]), 2, "Q")
    with pytest.raises(ValueError, match=r"^Q contains non-finite"):
        check_psd(np.diag([1.0, np.nan]), 2, "Q")
    batch = np.stack([np.eye(2), np.diag([1.0, -1.0])])
    with pytest.raises(ValueError, match=r"^Q must be positive semidefinite"):
        check_psd(batch, 2, "Q")
    # the tolerance is relative to the largest entry, at any scale
    for scale in (1e-12, 1.0, 1e12):
        check_psd(scale * np.diag([1.0, -0.5 * PSD_RTOL]), 2, "Q")
        with pytest.raises(ValueError, match="positive semidefinite"):
            check_psd(scale * np.diag([1.0, -2.0 * PSD_RTOL]), 2, "Q")


def test_check_psd_weight_matrix():
    W = np.diag([1.0, 0.0])
    out = check_psd_weight_matrix(W, 2)
    np.testing.assert_array_equal(out, W)
    assert not np.shares_memory(out, W)
    with pytest.raises(ValueError, match=r"^criterion must not be the zero matrix"):
        check_psd_weight_matrix(np.zeros((2, 2)), 2)
    with pytest.raises(ValueError, match=r"^criterion must not be the zero matrix"):
        check_psd_weight_matrix(np.stack([np.eye(2), np.zeros((2, 2))]), 2)
    with pytest.raises(ValueError, match=r"^criterion must be a 2x2 weight matrix, got shape "
                                         r"\(3, 3\)"):
        check_psd_weight_matrix(np.eye(3), 2)
    with pytest.raises(ValueError, match=r"^W must be a 2x2 weight matrix, got shape \(2,\)"):
        check_psd_weight_matrix([1.0, 1.0], 2, "W")
    with pytest.raises(TypeError, match=r"^criterion must be real"):
        check_psd_weight_matrix(np.eye(2) * 1j, 2)
    with pytest.raises(ValueError, match=r"^criterion must be positive semidefinite"):
        check_psd_weight_matrix(-np.eye(2), 2)


# ------------------------------------------------------------------ pinned tolerances
# The documented thresholds, written as numbers (not derived from the constants they pin).
@pytest.mark.parametrize("scale", [1e-12, 1.0, 1e12])
def test_symmetry_tolerance_is_one_part_in_1e8_of_the_largest_diagonal_entry(scale):
    """|P - P^T| up to 1e-8 max|P_ii| is rounding (accepted and symmetrised), above is a
    typo: at every scale, through the checks and through both paths of the front door
    (float64 arrays take a fast path, nested lists the general one)."""
    def matrix(asymmetry):  # max diagonal entry 2 (the smaller one is 1)
        return scale * np.array([[2.0, 0.5], [0.5 + asymmetry, 1.0]])

    accepted, rejected = matrix(0.9 * 2e-8), matrix(1.1 * 2e-8)
    S = check_symmetric(accepted, "P")
    np.testing.assert_array_equal(S, S.T)
    with pytest.raises(ValueError, match="not symmetric"):
        check_symmetric(rejected, "P")
    other = scale * np.eye(2)
    for P, ok in ((accepted, True), (rejected, False)):
        for form in (np.asarray, lambda A: A.tolist()):
            pairs = [(np.zeros(2), form(P)), (np.ones(2), form(other))]
            if ok:
                fuse(pairs, method="naive")
            else:
                with pytest.raises(ValueError, match=r"P\[0\] is not symmetric"):
                    fuse(pairs, method="naive")


@pytest.mark.parametrize("where", ["mean", "covariance"])
@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_non_finite_input_is_rejected_on_the_fast_path(where, bad):
    x, P = np.zeros(2), np.eye(2)
    if where == "mean":
        x = np.array([bad, 0.0])
    else:
        P = np.array([[1.0, 0.0], [0.0, bad]])
    with pytest.raises(ValueError, match="non-finite"):
        fuse([(x, P), (np.ones(2), np.eye(2))], method="ci")
    with pytest.raises(ValueError, match="non-finite"):
        naive_fusion([x, np.ones(2)], [P, np.eye(2)])


def test_semidefinite_tolerance_is_1e_10_of_the_largest_entry():
    for scale in (1e-6, 1.0, 1e6):
        check_psd(scale * np.diag([1.0, -0.5e-10]), 2, "Q")  # rounding: accepted
        with pytest.raises(ValueError, match="Q must be positive semidefinite"):
            check_psd(scale * np.diag([1.0, -2e-10]), 2, "Q")


# ------------------------------------------------------------------ the lean paths (issue 24)
def _set(M, where, value):
    M[where] = value


def _huge_off_diagonal(M):
    M[0, 0] = M[2, 2] = 1e308
    M[2, 0] = M[0, 2] = 9.5e307


# Every way a covariance can be bad that the one pass over finiteness and symmetry tells
# apart, with the message the general path has always given (Ps[...] names the matrix)
EDITS = [
    (lambda M: _set(M, (1, 1), np.nan), r"contains non-finite values \(NaN or inf\)$"),
    (lambda M: _set(M, (2, 0), np.inf), r"contains non-finite values \(NaN or inf\)$"),
    (lambda M: _set(M, (0, 2), -np.inf), r"contains non-finite values \(NaN or inf\)$"),
    (lambda M: (_set(M, (2, 0), np.inf), _set(M, (0, 2), np.inf)),  # symmetric infinities
     r"contains non-finite values \(NaN or inf\)$"),
    # finite entries whose P + P^T overflows: the symmetrised copy is not finite
    (lambda M: _set(M, (1, 1), 1.5e308),
     r"is not positive definite: it has non-finite entries \(NaN or inf\)$"),
    (_huge_off_diagonal, r"is not positive definite: it has non-finite entries \(NaN or inf\)$"),
    # finite entries whose difference overflows: asymmetric, not non-finite
    (lambda M: (_set(M, (2, 0), 1.5e308), _set(M, (0, 2), -1.5e308)),
     r"is not symmetric \(max \|P - P\^T\| = inf\)$"),
    (lambda M: _set(M, (2, 0), M[2, 0] + 1e-3), r"is not symmetric \(max \|P - P\^T\| = 0\.001\)$"),
    (lambda M: _set(M, (1, 1), -50.0), r"is not positive definite \(smallest eigenvalue -"),
]


def _estimates_input(batch, seed=3, n=3):
    g = np.random.default_rng(seed)
    A = g.standard_normal(batch + (2, n, n))
    return g.standard_normal(batch + (2, n)), A @ np.swapaxes(A, -1, -2) + 0.1 * np.eye(n)


@pytest.mark.parametrize("batch, where", [((), "Ps[1]"), ((5,), "Ps[3, 1]"),
                                          ((300,), "Ps[298, 1]")])  # 600 matrices: by columns
@pytest.mark.parametrize("form", ["array", "sequence"])
@pytest.mark.parametrize("edit, message", EDITS)
def test_every_path_rejects_bad_covariances_with_the_same_message(batch, where, form, edit,
                                                                  message):
    """One pair (LAPACK per matrix), a short stack (P - P^T at once) and a long one (tested
    column by column), given as one array or as a sequence (the lean path for float64
    arrays): the same checks, the same messages, naming the same matrix."""
    xs, Ps = _estimates_input(batch)
    index = (batch[0] - 2,) if batch else ()
    edit(Ps[index + (1,)])
    if form == "sequence":
        xs, Ps = [xs[..., i, :] for i in range(2)], [Ps[..., i, :, :] for i in range(2)]
    with np.errstate(over="ignore", invalid="ignore"):
        with pytest.raises(ValueError, match=f"^{re.escape(where)} " + message):
            as_estimates(xs, Ps)


@pytest.mark.parametrize("batch", [(), (5,), (300,)])
@pytest.mark.parametrize("column", [False, True])
@pytest.mark.parametrize("asymmetric", [False, True])
def test_lean_paths_return_what_the_general_path_returns(batch, column, asymmetric):
    """Sequences of float64 arrays (the lean path) and the same numbers as nested lists (the
    general path) give the same Estimates, bit for bit; exactly symmetric covariances come
    back unchanged, rounding-asymmetric ones as (P + P^T) / 2; nothing aliases the input.
    One pair without batch axes is factorised matrix by matrix by LAPACK (as before)."""
    xs, Ps = _estimates_input(batch, seed=4)
    if asymmetric:  # filterpy-style rounding, far inside SYMMETRY_RTOL
        Ps[..., 2, 0] *= 1.0 + 1e-13
    x_items = [xs[..., i, :, None] if column else xs[..., i, :] for i in range(2)]
    P_items = [Ps[..., i, :, :].copy() for i in range(2)]
    lean = as_estimates(x_items, P_items)
    general = as_estimates([x.tolist() for x in x_items], [P.tolist() for P in P_items])
    expected_P = 0.5 * (Ps + np.swapaxes(Ps, -1, -2))
    np.testing.assert_array_equal(lean.P, expected_P)
    np.testing.assert_array_equal(lean.x, xs)
    assert lean.column is general.column is column
    np.testing.assert_array_equal(general.P, lean.P)
    np.testing.assert_array_equal(general.x, lean.x)
    if batch:
        np.testing.assert_array_equal(lean.L, general.L)
    else:
        for i in range(2):
            np.testing.assert_array_equal(lean.L[i], scipy.linalg.cholesky(lean.P[i],
                                                                           lower=True))
    for array in (*x_items, *P_items):
        for result in (lean.x, lean.P, lean.L):
            assert not np.shares_memory(array, result)
    if not asymmetric:  # P_items unchanged: exactly symmetric in, the same numbers out
        np.testing.assert_array_equal(lean.P, np.stack(P_items, axis=-3))


def test_check_symmetric_and_check_covariances_still_return_new_arrays():
    """The public checks keep returning the symmetrised copy, also for an exactly symmetric
    long stack (only as_estimates may hand back its own private copy unchanged)."""
    _, Ps = _estimates_input((300,), seed=5)
    S = check_symmetric(Ps)
    P, L = check_covariances(Ps)
    for result in (S, P, L):
        assert not np.shares_memory(result, Ps)
    np.testing.assert_array_equal(S, Ps)
    np.testing.assert_array_equal(P, Ps)
    np.testing.assert_array_equal(L, np.linalg.cholesky(Ps))
