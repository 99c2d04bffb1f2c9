"""Motion profiles against closed forms, finite differences of the kinematics and conservation laws."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from starenv.sim.conventions import DEG, angle_between
from starenv.sim.motion import (
    ConstantRate,
    LeoNadir,
    Motion,
    Oscillation,
    Sequence,
    Slew,
    Superposed,
    TorqueFree,
    Trajectory,
)

STEP = 1e-5  # s, central-difference half step


def finite_difference_rate(motion: Motion, t: float, h: float = STEP) -> np.ndarray:
    """Body rate from dA/dt = -[w x] A: delta(t + h) delta(t - h)^-1 = exp(-2 h [w x]) + O(h^3)."""
    return -(motion.delta(t + h) * motion.delta(t - h).inv()).as_rotvec() / (2.0 * h)


def assert_rate_matches_delta(motion: Motion, t: float, rel: float = 1e-7) -> None:
    """Relative to the rate scale, plus a 1e-10 rad/s floor for the rounding of a difference over 2e-5 s."""
    scale = motion.max_rate(t - 1.0, t + 1.0)
    err = np.linalg.norm(finite_difference_rate(motion, t) - motion.body_rate(t))
    assert err <= rel * scale + 1e-10, (err, scale)


ASYMMETRIC_INERTIA = np.array([[10.0, 1.0, 0.5], [1.0, 15.0, -0.8], [0.5, -0.8, 20.0]])

vectors = st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=3).map(np.array)
rates = vectors.map(lambda v: 0.5 * v)
times = st.floats(0.0, 50.0)
oscillations = st.builds(
    Oscillation,
    amplitude=st.lists(st.floats(0.0, 0.05), min_size=3, max_size=3),
    frequency=st.lists(st.floats(0.0, 5.0), min_size=3, max_size=3),
    phase=st.lists(st.floats(-np.pi, np.pi), min_size=3, max_size=3),
)
nonzero_axes = vectors.filter(lambda v: np.linalg.norm(v) > 0.1)
slews = st.builds(
    Slew,
    axis=nonzero_axes,
    angle=st.floats(-np.pi, np.pi),
    max_rate=st.floats(0.01, 0.1),
    max_accel=st.floats(0.001, 0.05),
    start=st.floats(0.0, 5.0),
)


def away_from(t: float, instants, margin: float = 3 * STEP) -> bool:
    return bool(np.all(np.abs(np.asarray(instants) - t) > margin))


# --- constant rate -----------------------------------------------------------------------------------------------


def test_constant_rate_attitude_is_exponential_and_product_of_small_steps():
    w = np.array([0.02, -0.05, 0.03])
    a0 = Rotation.from_euler("zyx", [40, -20, 70], degrees=True)
    trajectory = Trajectory(ConstantRate(w), a0)
    duration, steps = 20.0, 2000
    expected = Rotation.from_rotvec(-w * duration) * a0
    assert angle_between(trajectory.attitude(duration), expected) < 1e-12
    stepped = a0
    step = Rotation.from_rotvec(-w * duration / steps)
    for _ in range(steps):
        stepped = step * stepped
    assert angle_between(trajectory.attitude(duration), stepped) < 1e-11


def test_constant_rate_star_vector_obeys_body_kinematics():
    w = np.array([0.1, 0.2, -0.15])
    trajectory = Trajectory(ConstantRate(w), Rotation.from_rotvec([0.3, -0.2, 1.1]))
    star = np.array([0.48, -0.6, 0.64])
    h = 1e-5
    for t in (0.0, 3.7, 12.0):
        seen = trajectory.attitude(t).apply(star)
        derivative = (trajectory.attitude(t + h).apply(star) - trajectory.attitude(t - h).apply(star)) / (2 * h)
        np.testing.assert_allclose(derivative, -np.cross(w, seen), atol=1e-10)


def test_vectorised_and_scalar_evaluation_agree():
    motion = Superposed(ConstantRate([0.01, 0.0, -0.02]), Oscillation([1e-3, 2e-3, 0.0], [2.0, 3.0, 0.0]))
    ts = np.array([0.0, 0.3, 1.7])
    many = motion.delta(ts)
    assert len(many) == 3 and motion.body_rate(ts).shape == (3, 3)
    for i, t in enumerate(ts):
        assert motion.delta(t).single and motion.body_rate(t).shape == (3,)
        assert angle_between(many[i], motion.delta(t)) < 1e-15
        np.testing.assert_allclose(motion.body_rate(ts)[i], motion.body_rate(t))
    assert motion.delta(0.0).magnitude() == 0.0
    empty = np.array([])
    for each in (motion, Slew([0, 0, 1], 1, 1, 1), TorqueFree(np.eye(3), [0, 0, 1]), Sequence([(motion, 1.0)])):
        assert len(each.delta(empty)) == 0 and each.body_rate(empty).shape == (0, 3)


@settings(max_examples=40, deadline=None)
@given(w=rates, t=times)
def test_constant_rate_matches_finite_difference(w, t):
    assert_rate_matches_delta(ConstantRate(w), t)


# --- slew --------------------------------------------------------------------------------------------------------


def test_slew_between_reaches_target_exactly():
    a0 = Rotation.from_euler("zyx", [10, 20, 30], degrees=True)
    a1 = Rotation.from_euler("zyx", [-100, 5, 60], degrees=True)
    slew = Slew.between(a0, a1, max_rate=2 * DEG, max_accel=0.2 * DEG, start=3.0)
    assert angle_between(slew.delta(slew.duration) * a0, a1) < 1e-12
    assert angle_between(slew.delta(slew.duration + 100.0) * a0, a1) < 1e-12
    assert angle_between(slew.delta(np.array([0.0, 2.9]))[1] * a0, a0) < 1e-15


def test_slew_trapezoid_duration_limits_and_rest_ends():
    angle, max_rate, max_accel = 60 * DEG, 2 * DEG, 0.25 * DEG
    slew = Slew([0, 1, 1], angle, max_rate, max_accel)
    assert slew.duration == pytest.approx(angle / max_rate + max_rate / max_accel, rel=1e-14)
    ts = np.linspace(-5.0, slew.duration + 5.0, 20001)
    speed = np.linalg.norm(slew.body_rate(ts), axis=1)
    assert speed.max() == pytest.approx(max_rate, rel=1e-12)
    assert speed.max() <= max_rate * (1 + 1e-12)
    assert np.all(np.abs(np.diff(speed)) / np.diff(ts) <= max_accel * (1 + 1e-9))
    np.testing.assert_array_equal(slew.body_rate(np.array([0.0, slew.duration])), 0.0)
    assert slew.delta(slew.duration).magnitude() == pytest.approx(angle, abs=1e-14)
    np.testing.assert_allclose(slew.body_rate(10.0), max_rate * np.array([0, 1, 1]) / np.sqrt(2), rtol=1e-14)
    assert slew.max_rate(0.0, 2.0) == pytest.approx(2.0 * max_accel)
    assert slew.max_rate(-10.0, slew.duration + 10.0) == pytest.approx(max_rate)


def test_slew_triangular_when_rate_limit_not_reached():
    angle, max_rate, max_accel = 1 * DEG, 2 * DEG, 0.25 * DEG
    slew = Slew([1, 0, 0], angle, max_rate, max_accel)
    peak = np.sqrt(angle * max_accel)
    assert peak < max_rate
    assert slew.duration == pytest.approx(2.0 * np.sqrt(angle / max_accel), rel=1e-14)
    ts = np.linspace(0.0, slew.duration, 10001)
    assert np.linalg.norm(slew.body_rate(ts), axis=1).max() == pytest.approx(peak, rel=1e-6)
    assert slew.delta(slew.duration).magnitude() == pytest.approx(angle, abs=1e-15)


@settings(max_examples=40, deadline=None)
@given(slew=slews, fraction=st.floats(-0.1, 1.1))
def test_slew_matches_finite_difference(slew, fraction):
    t = slew.start + fraction * (slew.duration - slew.start)
    assume(away_from(t, slew.phase_times))
    assert_rate_matches_delta(slew, t)
    assert np.linalg.norm(slew.body_rate(t)) <= slew.rate_limit * (1 + 1e-12)


# --- torque-free rigid body --------------------------------------------------------------------------------------


def test_torque_free_conserves_momentum_and_energy():
    w0 = np.array([20.0, -15.0, 15.0]) * DEG  # |w0| ~ 29 deg/s
    body = TorqueFree(ASYMMETRIC_INERTIA, w0)
    a0 = Rotation.from_rotvec([0.4, -1.0, 0.2])
    ts = np.linspace(0.0, 100.0, 401)
    attitude = Trajectory(body, a0).attitude(ts)
    w = body.body_rate(ts)
    momentum = attitude.inv().apply(w @ ASYMMETRIC_INERTIA)  # h_inertial = A^T I w
    energy = 0.5 * np.einsum("ni,ij,nj->n", w, ASYMMETRIC_INERTIA, w)
    h0 = a0.inv().apply(ASYMMETRIC_INERTIA @ w0)
    assert np.max(np.linalg.norm(momentum - h0, axis=1)) <= 1e-9 * np.linalg.norm(h0)
    assert np.max(np.abs(np.linalg.norm(momentum, axis=1) - np.linalg.norm(h0))) <= 1e-9 * np.linalg.norm(h0)
    assert np.max(np.abs(energy - energy[0])) <= 1e-9 * energy[0]
    assert np.ptp(w, axis=0).max() > 0.1  # really tumbling
    assert np.all(np.linalg.norm(w, axis=1) <= body.max_rate(0.0, 100.0))


def test_torque_free_extends_lazily_and_consistently():
    w0 = np.array([0.3, 0.1, -0.4])
    lazy = TorqueFree(ASYMMETRIC_INERTIA, w0)
    early = lazy.delta(5.0)
    late = lazy.delta(250.0)
    eager = TorqueFree(ASYMMETRIC_INERTIA, w0)
    both = eager.delta(np.array([250.0, 5.0]))
    assert angle_between(late, both[0]) < 1e-9
    assert angle_between(early, both[1]) < 1e-12
    for t in (0.5, 120.0, 240.0):
        assert_rate_matches_delta(lazy, t)


def test_torque_free_principal_spin_equals_constant_rate():
    spin = np.array([0.0, 0.0, 0.5])
    body = TorqueFree(np.diag([10.0, 15.0, 20.0]), spin)
    ts = np.linspace(0.0, 60.0, 121)
    assert np.max(angle_between(body.delta(ts), ConstantRate(spin).delta(ts))) < 1e-10
    np.testing.assert_allclose(body.body_rate(ts), np.tile(spin, (ts.size, 1)), atol=1e-13)


def test_torque_free_axisymmetric_precession_closed_form():
    i1, i3 = 10.0, 16.0
    w0, w3 = 0.2, 0.4
    body = TorqueFree(np.diag([i1, i1, i3]), [w0, 0.0, w3])
    rate = (i3 - i1) / i1 * w3
    ts = np.linspace(0.0, 100.0, 501)
    expected = np.stack([w0 * np.cos(rate * ts), w0 * np.sin(rate * ts), np.full_like(ts, w3)], axis=1)
    np.testing.assert_allclose(body.body_rate(ts), expected, atol=1e-10)


def test_quaternion_kinematics_sign_matches_constant_rate():
    # A rate held constant in the body frame (spherical body) must reproduce exp(-[w x] t) exactly.
    w = np.array([0.3, -0.7, 0.2])
    body = TorqueFree(np.eye(3) * 4.0, w)
    ts = np.linspace(0.0, 30.0, 61)
    assert np.max(angle_between(body.delta(ts), ConstantRate(w).delta(ts))) < 1e-10


def test_torque_free_rejects_negative_time():
    with pytest.raises(ValueError, match="t must be >= 0"):
        TorqueFree(np.eye(3), [0.1, 0.0, 0.0]).delta(-1.0)


# --- oscillation -------------------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(motion=oscillations, t=times)
def test_oscillation_matches_finite_difference(motion, t):
    assert_rate_matches_delta(motion, t)


def test_large_oscillation_matches_finite_difference():
    motion = Oscillation([1.0, 0.5, 0.7], [0.3, 0.2, 0.1], [0.1, 0.2, 0.3])
    for t in (0.0, 0.9, 3.3, 7.1):
        assert_rate_matches_delta(motion, t)


def test_coning_rate_and_cone():
    half_angle, frequency = 2 * DEG, 1.5
    coning = Oscillation.coning(half_angle, frequency)
    ts = np.linspace(0.0, 2.0, 401)
    z_axis_inertial = coning.delta(ts).inv().apply([0.0, 0.0, 1.0])  # A0 = identity
    tilt = np.arccos(np.clip(z_axis_inertial[:, 2], -1.0, 1.0))
    assert np.all(tilt <= half_angle + 1e-9)
    np.testing.assert_allclose(tilt, half_angle, atol=1e-7)  # centred on A0, already on the cone at t = 0
    for t in (0.0, 0.123, 0.77):
        assert_rate_matches_delta(coning, t)
    speed = np.linalg.norm(coning.body_rate(ts), axis=1)
    assert np.all(speed <= coning.max_rate(0.0, 2.0) * (1 + 1e-12))


# --- superposition and sequences ---------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(base_rate=rates, jitter=oscillations, t=times)
def test_superposed_matches_finite_difference(base_rate, jitter, t):
    motion = Superposed(ConstantRate(base_rate), jitter)
    assert_rate_matches_delta(motion, t)
    assert np.linalg.norm(motion.body_rate(t)) <= motion.max_rate(t, t) * (1 + 1e-12)


@settings(max_examples=20, deadline=None)
@given(slew=slews, jitter=oscillations, t=st.floats(0.0, 60.0))
def test_superposed_slew_matches_finite_difference(slew, jitter, t):
    assume(away_from(t, slew.phase_times))
    assert_rate_matches_delta(Superposed(slew, jitter), t)


@settings(max_examples=30, deadline=None)
@given(
    first=rates,
    second=oscillations,
    third=rates,
    durations=st.lists(st.floats(0.0, 10.0), min_size=3, max_size=3),
    t=st.floats(0.0, 40.0),
)
def test_sequence_matches_finite_difference(first, second, third, durations, t):
    segments = [(ConstantRate(first), durations[0]), (second, durations[1]), (ConstantRate(third), durations[2])]
    sequence = Sequence(segments)
    assume(away_from(t, np.cumsum(durations)))
    assert_rate_matches_delta(sequence, t)


def test_sequence_continuity_and_segment_rates():
    slew = Slew([1.0, 0.0, 0.0], 10 * DEG, 1 * DEG, 0.5 * DEG)
    spin = ConstantRate([0.0, 0.01, 0.0])
    jitter = Oscillation.coning(1e-3, 2.0)
    durations = [slew.duration, 7.0, 5.0]
    sequence = Sequence([(slew, durations[0]), (spin, durations[1]), (jitter, durations[2])])
    boundaries = np.cumsum(durations)
    eps = 1e-9
    for boundary in boundaries:
        assert angle_between(sequence.delta(boundary - eps), sequence.delta(boundary + eps)) < 1e-10
    # After the slew the sequence holds the slew's final attitude, then spins, then cones from there.
    assert angle_between(sequence.delta(boundaries[0]), slew.delta(slew.duration)) < 1e-15
    t_spin = boundaries[0] + 3.0
    expected = spin.delta(3.0) * slew.delta(slew.duration)
    assert angle_between(sequence.delta(t_spin), expected) < 1e-14
    ts = np.array([1.0, t_spin, boundaries[1] + 0.4, boundaries[2] + 2.0])
    expected_rates = [slew.body_rate(1.0), spin.body_rate(3.0), jitter.body_rate(0.4), jitter.body_rate(7.0)]
    np.testing.assert_allclose(sequence.body_rate(ts), np.array(expected_rates), atol=1e-15)
    assert sequence.max_rate(boundaries[0] + 1, boundaries[1] - 1) == pytest.approx(0.01)
    assert sequence.max_rate(0.0, 100.0) == pytest.approx(max(1 * DEG, 0.01, jitter.max_rate(0, 1)))


# --- LEO nadir pointing ------------------------------------------------------------------------------------------


def lvlh_from_state(r: np.ndarray, v: np.ndarray) -> Rotation:
    z = -r / np.linalg.norm(r)
    h = np.cross(r, v)
    y = -h / np.linalg.norm(h)
    return Rotation.from_matrix(np.stack([np.cross(y, z), y, z]))


def test_leo_nadir_attitude_follows_orbit():
    orbit = LeoNadir(550e3, 97.6 * DEG, 0.7, 1.2)
    trajectory = orbit.trajectory()
    for t in (0.0, 123.4, 1500.0, 5000.0):
        built = lvlh_from_state(orbit.position(t), orbit.velocity(t))
        assert angle_between(built, trajectory.attitude(t)) < 1e-12
    np.testing.assert_allclose(orbit.body_rate(10.0), [0.0, -orbit.mean_motion, 0.0])
    # Position: circular, at the right height, normal at the right inclination, velocity = d r / dt, +x along v.
    ts = np.linspace(0.0, orbit.period, 7)
    r, v = orbit.position(ts), orbit.velocity(ts)
    np.testing.assert_allclose(np.linalg.norm(r, axis=1), 6378137.0 + 550e3, rtol=1e-14)
    np.testing.assert_allclose(r[0], r[-1], atol=1e-6)
    normal = np.cross(r[0], v[0]) / np.linalg.norm(np.cross(r[0], v[0]))
    assert normal[2] == pytest.approx(np.cos(97.6 * DEG), abs=1e-14)
    h = 1e-3
    velocity_fd = (orbit.position(3.0 + h) - orbit.position(3.0 - h)) / (2 * h)
    np.testing.assert_allclose(velocity_fd, orbit.velocity(3.0), atol=1e-5)
    x_axis = trajectory.attitude(3.0).inv().apply([1.0, 0.0, 0.0])
    np.testing.assert_allclose(x_axis, orbit.velocity(3.0) / np.linalg.norm(orbit.velocity(3.0)), atol=1e-12)


def test_leo_period_550km():
    a = 6378137.0 + 550e3
    period = 2 * np.pi * np.sqrt(a**3 / 3.986004418e14)
    orbit = LeoNadir(550e3, 0.0, 0.0, 0.0)
    assert orbit.period == pytest.approx(period, rel=1e-14)
    assert 5700.0 < orbit.period < 5780.0


# --- bad input ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("build", "name"),
    [
        (lambda: ConstantRate([np.nan, 0.0, 0.0]), "rate"),
        (lambda: ConstantRate([0.0, 1.0]), "rate"),
        (lambda: Slew([0, 0, 1], 1.0, -0.1, 0.01), "max_rate"),
        (lambda: Slew([0, 0, 1], 1.0, 0.1, 0.0), "max_accel"),
        (lambda: Slew([0, 0, 0], 1.0, 0.1, 0.01), "axis"),
        (lambda: Slew([0, 0, 1], np.nan, 0.1, 0.01), "angle"),
        (lambda: TorqueFree(np.diag([1.0, -2.0, 3.0]), [0.1, 0.0, 0.0]), "inertia"),
        (lambda: TorqueFree([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.1, 0.0, 0.0]), "inertia"),
        (lambda: TorqueFree(np.diag([1.0, 1.0, 3.0]), [0.1, 0.0, 0.0]), "inertia"),
        (lambda: TorqueFree(np.eye(3), [0.1, np.inf, 0.0]), "rate0"),
        (lambda: Oscillation([0.1, -0.1, 0.0], [1.0, 1.0, 1.0]), "amplitude"),
        (lambda: Oscillation([0.1, 0.1, 0.0], [1.0, np.nan, 1.0]), "frequency"),
        (lambda: Oscillation.coning(0.01, -1.0), "frequency"),
        (lambda: Sequence([(ConstantRate([0, 0, 1]), 5.0), (ConstantRate([0, 1, 0]), -1)]), r"segments\[1\] duration"),
        (lambda: Sequence([]), "segments"),
        (lambda: Sequence([(object(), 1.0)]), r"segments\[0\]"),
        (lambda: Superposed(ConstantRate([0, 0, 1]), None), "perturbation"),
        (lambda: LeoNadir(-5.0, 0.0), "altitude"),
        (lambda: LeoNadir(500e3, 4.0), "inclination"),
        (lambda: Trajectory(ConstantRate([0, 0, 1]), Rotation.random(2, rng=1)), "initial"),
        (lambda: ConstantRate([0, 0, 1]).delta(np.nan), "t"),
        (lambda: ConstantRate([0, 0, 1]).max_rate(2.0, 1.0), "t1"),
    ],
)
def test_bad_input_names_the_parameter(build, name):
    with pytest.raises(ValueError, match=f"^{name}"):
        build()
