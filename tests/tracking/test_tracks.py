"""Source tracks, central tracks and the checks of a scan (:mod:`cifilter.tracking.tracks`)."""

import dataclasses

import numpy as np
import pytest

from cifilter.tracking import CentralTrack, SourceTrack, checked_tracks, scan_time

H2 = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]])


def track(source="radar", id=1, x=None, P=None, time=0.0, H=None):
    return SourceTrack(source, id, np.zeros(4) if x is None else x,
                       np.eye(4) if P is None else P, time, H)


def test_source_and_central_tracks_are_frozen():
    t = track()
    with pytest.raises(dataclasses.FrozenInstanceError):
        t.x = np.ones(4)  # type: ignore[misc]
    c = CentralTrack(1, np.zeros(2), np.eye(2), 0.0, False, {}, 1, 0, 0.0, {})
    with pytest.raises(dataclasses.FrozenInstanceError):
        c.confirmed = True  # type: ignore[misc]


def test_checked_tracks_copies_symmetrises_and_sets_the_dimension():
    P = np.array([[2.0, 0.5], [0.5 + 1e-12, 1.0]])
    x = np.array([[1.0], [2.0]])  # a column is accepted
    scan = [SourceTrack("cam", "p", x, P, 1.0, np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])),
            track("radar", 3)]
    checked, n = checked_tracks(scan, 1.0, None)
    assert n == 4  # the partial track came first: its H gives n
    first = checked[0]
    assert first.x.shape == (2,) and first.label == "source 'cam' track 'p'"
    np.testing.assert_array_equal(first.P, first.P.T)
    np.testing.assert_allclose(first.L @ first.L.T, first.P, rtol=1e-15)
    assert first.x is not x and first.P is not P
    # inputs untouched
    assert x.shape == (2, 1) and P[1, 0] == 0.5 + 1e-12


def test_an_empty_scan():
    assert checked_tracks([], 0.0, None) == ([], None)
    assert checked_tracks((), 0.0, 3) == ([], 3)


@pytest.mark.parametrize("scan, n, error, match", [
    ([track(id=1), track(id=1)], None, ValueError,
     r"source 'radar' track 1 appears twice in the scan \(tracks\[0\] and tracks\[1\]\)"),
    ([track(x=np.array([0.0, np.nan, 0, 0]))], None, ValueError,
     r"source 'radar' track 1's x contains non-finite"),
    ([track(P=np.diag([1.0, 1.0, np.nan, 1.0]))], None, ValueError,
     r"source 'radar' track 1's P contains non-finite"),
    ([track(P=np.array([[1.0, 0.5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))], None,
     ValueError, r"source 'radar' track 1's P is not symmetric"),
    ([track(P=np.diag([1.0, -1.0, 1.0, 1.0]))], None, ValueError,
     r"source 'radar' track 1's P is not positive definite"),
    ([track(P=np.eye(3))], None, ValueError, r"source 'radar' track 1's P has shape \(3, 3\)"),
    ([track(time=2.0)], None, ValueError,
     r"source 'radar' track 1 is at time 2, later than the scan time 1"),
    ([track(time=np.nan)], None, ValueError, r"source 'radar' track 1's time must be finite"),
    ([track(time="now")], None, TypeError, r"source 'radar' track 1's time must be a real"),
    ([track(x=np.zeros(2), P=np.eye(2))], 4, ValueError,
     r"source 'radar' track 1 has a state of size 2 but the central state has size 4, and no "
     r"H says which part"),
    ([track(), track("cam", 2, x=np.zeros(2), P=np.eye(2))], None, ValueError,
     r"source 'cam' track 2 has a state of size 2"),
    ([track("cam", 2, x=np.zeros(2), P=np.eye(2), H=np.eye(2, 3))], 4, ValueError,
     r"source 'cam' track 2's H has shape \(2, 3\).* must be \(2, 4\)"),
    ([track("cam", 2, x=np.zeros(2), P=np.eye(2), H=np.ones((3, 4)))], 4, ValueError,
     r"source 'cam' track 2's H has shape \(3, 4\); with x of size 2"),
    ([track("cam", 2, x=np.zeros(2), P=np.eye(2), H=np.ones((2, 4)))], 4, ValueError,
     r"source 'cam' track 2's H .* does not have full row rank"),
    ([track("cam", 2, x=np.zeros(2), P=np.eye(2), H=np.full((2, 4), np.inf))], 4, ValueError,
     r"source 'cam' track 2's H contains non-finite"),
    ([track(x=np.array(["a", "b", "c", "d"]))], None, TypeError,
     r"source 'radar' track 1's x must be a numeric"),
    ([track(id=[1])], None, TypeError, r"must be hashable"),
    ([(np.zeros(4), np.eye(4))], None, TypeError, r"tracks\[0\] must be a SourceTrack"),
])
def test_bad_tracks_are_named(scan, n, error, match):
    with pytest.raises(error, match=match):
        checked_tracks(scan, 1.0, n)


def test_tracks_must_be_a_sequence():
    with pytest.raises(TypeError, match="tracks must be a sequence of SourceTrack"):
        checked_tracks(track(), 0.0, None)  # type: ignore[arg-type]


def test_scan_time():
    assert scan_time(np.float64(3.0), 2.0) == 3.0
    assert scan_time(2, 2.0) == 2.0
    with pytest.raises(ValueError, match="the scan time 1 is earlier than the fuser's time 2"):
        scan_time(1.0, 2.0)
    with pytest.raises(ValueError, match="the scan time must be finite"):
        scan_time(np.inf, None)
    with pytest.raises(TypeError, match="the scan time must be a real number"):
        scan_time(True, None)
