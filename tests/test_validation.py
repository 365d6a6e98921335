"""Input checking shared by every rule (cifilter._validation), mostly through public calls."""

import numpy as np
import pytest

from cifilter import covariance_intersection, fuse, naive_fusion
from cifilter._linalg import IllConditionedError
from cifilter._validation import (
    as_estimates,
    as_float_array,
    check_covariances,
    check_psd,
    check_scalar,
    check_symmetric,
    check_weights,
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
