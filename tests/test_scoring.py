"""Scores against hand-made truth: matching, identification rules, attitude error split, aggregation."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from starenv.scenario import AvailabilityThreshold
from starenv.scoring import StepFrame, attitude_error, score_stars, summarize, trail_distance
from starenv.sim.conventions import ARCSEC
from starenv.sim.render import StarTruth


def truth(xy, ids, detectable=None):
    xy = np.asarray(xy, dtype=float)
    n = len(xy)
    return StarTruth(
        catalog_id=np.asarray(ids), magnitude=np.full(n, 5.0), xy_mid=xy, xy_centroid=xy, xy_start=xy, xy_end=xy,
        electrons=np.full(n, 1e4), peak_electrons=np.full(n, 1e3),
        detectable=np.ones(n, bool) if detectable is None else np.asarray(detectable),
    )


def test_either_member_of_an_unresolved_double_is_a_correct_id():
    t = truth([[100.0, 100.0], [100.6, 100.0], [300.0, 50.0], [40.0, 400.0]], [11, 12, 13, 14])
    blend = np.array([[100.3, 100.0], [300.0, 50.0], [40.0, 400.0]])
    for label in (11, 12):
        s = score_stars(t, blend, np.array([label, 13, 14]))
        assert (s.ids_correct, s.ids_wrong, s.solved) == (3, 0, True)
    s = score_stars(t, blend, np.array([13, 13, 14]))  # star 13 is 200 px away from the blend
    assert (s.ids_correct, s.ids_wrong, s.solved) == (2, 1, False)
    assert s.false_id_rate == pytest.approx(1 / 3)
    assert s.id_rate == pytest.approx(2 / 4)


def test_ids_claimed_on_a_frame_without_stars_are_all_wrong():
    empty = truth(np.zeros((0, 2)), np.zeros(0, dtype=np.int64))
    s = score_stars(empty, np.array([[10.0, 10.0], [50.0, 60.0]]), np.array([7, -1]))
    assert (s.ids_correct, s.ids_wrong, s.false_id_rate, s.id_rate, s.solved) == (0, 1, 1.0, None, False)
    t = truth([[10.0, 10.0]], [7])
    s = score_stars(t, np.array([[10.5, 10.0], [50.0, 60.0]]), np.array([7, 99]))  # 99 is not on this frame
    assert (s.ids_correct, s.ids_wrong) == (1, 1)


def test_a_trail_placed_along_itself_is_still_its_star():
    """A 20 px trail along x (centroid at its middle): a detection 6 px along the trail from the centroid and 0.5 px
    off it is that star (its trail passes 0.5 px away); 4 px across the trail it is not, nor 4 px beyond the end."""
    t = truth([[100.0, 100.0], [300.0, 50.0], [40.0, 400.0]], [11, 13, 14])
    t.xy_start = t.xy_start.copy()
    t.xy_end = t.xy_end.copy()
    t.xy_start[0], t.xy_end[0] = [90.0, 100.0], [110.0, 100.0]
    others = [[300.0, 50.0], [40.0, 400.0]]
    for xy, correct in (([106.0, 100.5], True), ([100.0, 104.0], False), ([114.0, 100.0], False)):
        s = score_stars(t, np.array([xy, *others]), np.array([11, 13, 14]))
        assert (s.ids_correct, s.solved) == ((3, True) if correct else (2, False))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-50.0, 50.0), min_size=6, max_size=6))
def test_trail_distance_is_the_distance_to_the_closest_point_of_the_segment(values):
    """Against a dense sampling of the segment (2001 points: at most half a step, 1/2000 of its length, above the
    exact distance)."""
    xy, start, end = np.array(values).reshape(3, 1, 2)
    points = start + np.linspace(0.0, 1.0, 2001)[:, None] * (end - start)
    sampled = np.min(np.linalg.norm(points - xy, axis=1))
    exact = trail_distance(xy, start, end)[0]
    step = np.linalg.norm(end - start) / 2000
    assert exact <= sampled + 1e-9 and sampled <= exact + step / 2 + 1e-9


def test_matching_is_one_to_one_within_the_gate():
    t = truth([[10.0, 10.0], [20.0, 10.0]], [1, 2], detectable=[True, False])
    det = np.array([[10.5, 10.0], [10.4, 10.0], [50.0, 50.0]])  # two detections compete for star 1; one is noise
    s = score_stars(t, det)
    assert s.centroid_error_px_mean == pytest.approx(0.4)  # the nearer one wins
    assert s.detection_precision == pytest.approx(1 / 3)
    assert s.detection_recall == 1.0  # the only detectable star was found


def test_attitude_error_splits_into_cross_boresight_and_roll_per_head():
    true = Rotation.from_euler("xyz", [10, 20, 30], degrees=True)
    heads = [Rotation.identity(), Rotation.from_matrix([[0, 0, 1], [0, 1, 0], [-1, 0, 0.0]])]
    est = Rotation.from_rotvec([0.0, 0.0, 20 * ARCSEC]) * true  # 20 arcsec about body +Z
    e = attitude_error(est, true, heads)
    assert e["total_arcsec"] == pytest.approx(20.0, rel=1e-9)
    assert e["heads"][0]["roll_arcsec"] == pytest.approx(20.0) and e["heads"][0]["cross_boresight_arcsec"] < 1e-9
    assert e["heads"][1]["cross_boresight_arcsec"] == pytest.approx(20.0) and abs(e["heads"][1]["roll_arcsec"]) < 1e-9
    assert e["heads"][1]["x_arcsec"] == pytest.approx(20.0)  # head 1's camera +X is body +Z


# The scores are computed in double precision from unit quaternions: each component of the error rotation vector
# carries a rounding error of a few 1e-16 rad (~1e-10 arcsec); 1e-8 arcsec leaves two orders of margin.
EXACT_ARCSEC = 1e-8
ROTATIONS = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(
    lambda q: np.linalg.norm(q) > 0.1).map(Rotation.from_quat)
ANGLES_ARCSEC = st.floats(0.01, 3600.0) | st.floats(-3600.0, -0.01)
CAMERA_AXES = ("x_arcsec", "y_arcsec", "roll_arcsec")
BODY_AXES = ("x_arcsec", "y_arcsec", "z_arcsec")


@settings(max_examples=200, deadline=None)
@given(ROTATIONS, st.lists(ROTATIONS, min_size=1, max_size=4), st.data(), ANGLES_ARCSEC)
def test_a_rotation_about_one_camera_axis_scores_its_signed_angle_on_that_axis(true, mountings, data, angle):
    """The estimate is the truth turned by ``angle`` about camera axis ``axis`` of head ``h`` (body axis ``u = M_h^-1
    axis``): that head scores exactly ``angle`` on it and 0 on the others; every head ``j`` scores ``angle * M_j u``,
    the body ``angle * u``; the opposite turn flips every sign."""
    h = data.draw(st.integers(0, len(mountings) - 1))
    axis = data.draw(st.integers(0, 2))
    u = mountings[h].inv().apply(np.eye(3)[axis])
    for sign in (1.0, -1.0):
        est = Rotation.from_rotvec(sign * angle * ARCSEC * u) * true
        e = attitude_error(est, true, mountings)
        expected = np.zeros(3)
        expected[axis] = sign * angle
        np.testing.assert_allclose([e["heads"][h][k] for k in CAMERA_AXES], expected, rtol=0, atol=EXACT_ARCSEC)
        for j, m in enumerate(mountings):
            in_camera = sign * angle * m.apply(u)
            np.testing.assert_allclose([e["heads"][j][k] for k in CAMERA_AXES], in_camera, rtol=0, atol=EXACT_ARCSEC)
            assert e["heads"][j]["cross_boresight_arcsec"] == pytest.approx(np.hypot(*in_camera[:2]), abs=EXACT_ARCSEC)
        np.testing.assert_allclose([e["body"][k] for k in BODY_AXES], sign * angle * u, rtol=0, atol=EXACT_ARCSEC)
        assert e["total_arcsec"] == pytest.approx(abs(angle), abs=EXACT_ARCSEC)


@settings(max_examples=100, deadline=None)
@given(ROTATIONS, ROTATIONS, st.integers(0, 2), ANGLES_ARCSEC)
def test_a_rotation_about_one_body_axis_scores_its_signed_angle_on_that_axis(true, mounting, axis, angle):
    est = Rotation.from_rotvec(angle * ARCSEC * np.eye(3)[axis]) * true
    body = attitude_error(est, true, [mounting])["body"]
    expected = np.zeros(3)
    expected[axis] = angle
    np.testing.assert_allclose([body[k] for k in BODY_AXES], expected, rtol=0, atol=EXACT_ARCSEC)
    back = attitude_error(Rotation.from_rotvec(-angle * ARCSEC * np.eye(3)[axis]) * true, true, [mounting])["body"]
    np.testing.assert_allclose([back[k] for k in BODY_AXES], -expected, rtol=0, atol=EXACT_ARCSEC)


# Two heads at right angles: head 0 looks along body +Z, head 1 along body +X (its camera +X is body -Z), so a turn
# about body +Z is head 0's roll and across head 1's boresight.
ORTHOGONAL = [Rotation.identity(), Rotation.from_euler("y", -90, degrees=True)]
TABLE = AvailabilityThreshold(cross_boresight_arcsec=50.0, roll_arcsec=200.0)


@pytest.mark.parametrize("heads, rotvec_arcsec, threshold, within", [
    (ORTHOGONAL[:1], [0.0, 0.0, 150.0], TABLE, True),  # roll 150 < 200, cross 0
    (ORTHOGONAL[:1], [0.0, 0.0, -150.0], TABLE, True),  # the roll's size counts, not its sign
    (ORTHOGONAL[:1], [0.0, 0.0, 250.0], TABLE, False),  # roll 250 > 200
    (ORTHOGONAL[:1], [40.0, 0.0, 150.0], TABLE, True),  # cross 40 < 50, roll 150 < 200
    (ORTHOGONAL[:1], [30.0, -41.0, 0.0], TABLE, False),  # cross hypot(30, 41) > 50
    (ORTHOGONAL, [0.0, 0.0, 150.0], TABLE, False),  # head 0's roll, head 1's cross-boresight 150 > 50
    (ORTHOGONAL, [0.0, 40.0, 0.0], TABLE, True),  # across both boresights, 40 < 50
    (ORTHOGONAL[:1], [0.0, 0.0, 150.0], AvailabilityThreshold(total_arcsec=100.0), False),  # total 150 > 100
    (ORTHOGONAL, [0.0, 60.0, 80.0], AvailabilityThreshold(total_arcsec=100.5), True),  # total 100 < 100.5
])
def test_within_threshold_follows_the_total_or_every_heads_axes(heads, rotvec_arcsec, threshold, within):
    true = Rotation.from_euler("zyx", [40, -10, 75], degrees=True)
    est = Rotation.from_rotvec(np.array(rotvec_arcsec) * ARCSEC) * true
    step = StepFrame(est, attitude_error(est, true, heads), threshold)
    assert step.within is within
    assert not StepFrame(None, {}, threshold).within


def test_summary_takes_median_and_p95_over_steps_with_a_value():
    records = [{"frame": i, "x": float(i), "y": None if i % 2 else 1.0} for i in range(101)]
    out = summarize(records)
    assert out["x"]["median"] == 50.0 and out["x"]["p95"] == pytest.approx(95.0) and out["x"]["count"] == 101
    assert out["y"]["count"] == 51 and "frame" not in out
