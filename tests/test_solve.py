"""Tests of the Wahba solvers (starenv.agents.solve): exact recovery, agreement of QUEST, the q-method and the SVD
method on hard noisy cases (180 deg rotations, two or three stars, unequal weights, narrow fields), optimality, the
two-vector closed form and argument checks."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from starenv.agents.base import AttitudeSolver
from starenv.agents.solve import solvers as solve
from starenv.sim.conventions import ARCSEC, DEG, angle_between

SOLVERS = [solve.QuestSolver(), solve.DavenportSolver(), solve.SvdSolver()]
SOLVER_IDS = ["quest", "davenport", "svd"]
NOISE = 10 * ARCSEC  # rad, per axis
AXES = {"x": [1.0, 0.0, 0.0], "y": [0.0, 1.0, 0.0], "z": [0.0, 0.0, 1.0], "random": [0.36, -0.48, 0.8]}


def random_units(rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, 3) unit vectors uniform on the sphere."""
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def cone_units(rng: np.random.Generator, n: int, half_angle: float) -> np.ndarray:
    """(n, 3) unit vectors uniform within ``half_angle`` (rad) of a random direction: one tracker's field of view."""
    off_axis = np.arccos(1.0 - rng.uniform(size=n) * (1.0 - np.cos(half_angle)))
    azimuth = rng.uniform(0.0, 2 * np.pi, n)
    local = np.stack([np.sin(off_axis) * np.cos(azimuth), np.sin(off_axis) * np.sin(azimuth), np.cos(off_axis)], 1)
    return Rotation.random(random_state=rng).apply(local)


def with_noise(rng: np.random.Generator, unit: np.ndarray, sigma: float) -> np.ndarray:
    """Unit vectors perturbed by Gaussian noise of ``sigma`` rad per axis."""
    v = unit + rng.normal(scale=sigma, size=unit.shape)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def loss(attitude: Rotation, body: np.ndarray, inertial: np.ndarray, weights: np.ndarray) -> float:
    """Wahba's loss sum w |b - A r|^2 for unit vectors (independent of the module's own)."""
    return float(np.sum(weights * np.sum((body - attitude.apply(inertial)) ** 2, axis=1)))


def near_half_turn(rng: np.random.Generator, axis: str, offset: float) -> Rotation:
    """A rotation ``offset`` rad (in a random direction) away from 180 deg about ``axis``."""
    half_turn = Rotation.from_rotvec(np.pi * np.array(AXES[axis]) / np.linalg.norm(AXES[axis]))
    return Rotation.from_rotvec(offset * random_units(rng, 1)[0]) * half_turn


def case(rng, n, attitude=None, weights=None, inertial=None):
    """(body with NOISE, inertial, weights, true attitude) with n random stars unless ``inertial`` is given."""
    attitude = Rotation.random(random_state=rng) if attitude is None else attitude
    inertial = random_units(rng, n) if inertial is None else inertial
    weights = np.ones(n) if weights is None else weights
    return with_noise(rng, attitude.apply(inertial), NOISE), inertial, weights, attitude


def shuffled_log_weights(rng, n, decades):
    """Weights spread evenly in log over ``decades`` (1e-decades/2 .. 1e+decades/2), shuffled."""
    return rng.permutation(np.logspace(-decades / 2, decades / 2, n))


HARD_CASES = {
    "2 stars": lambda rng: case(rng, 2),
    "3 stars": lambda rng: case(rng, 3),
    **{
        f"180 deg about {axis} {offset:g} rad off, {n} stars": (
            lambda rng, axis=axis, offset=offset, n=n: case(rng, n, attitude=near_half_turn(rng, axis, offset))
        )
        for axis in AXES
        for offset in (1e-3, 1e-6, 0.0)
        for n in (2, 3, 10)
    },
    "weights over 12 decades": lambda rng: case(rng, 10, weights=shuffled_log_weights(rng, 10, 12)),
    "one weight 1e4 times the next": lambda rng: case(rng, 3, weights=rng.permutation([1e4, 1.0, 1e-4])),
    **{
        f"{n} stars in a 6 deg cone": lambda rng, n=n: case(rng, n, inertial=cone_units(rng, n, 3 * DEG))
        for n in (2, 3, 5, 20)
    },
}


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(3, 30),
    quaternion=st.tuples(*[st.floats(-1.0, 1.0)] * 4),
)
def test_noise_free_attitude_is_recovered(solver, seed, n, quaternion):
    """Exact vectors give back the attitude to 1e-12 rad, 180 deg rotations (zero scalar part) included."""
    assume(np.linalg.norm(quaternion) > 0.1)
    truth = Rotation.from_quat(quaternion)
    inertial = random_units(np.random.default_rng(seed), n)
    assert angle_between(solver.solve(truth.apply(inertial), inertial), truth) < 1e-12


@pytest.mark.parametrize("name", list(HARD_CASES))
def test_solvers_agree_on_hard_noisy_cases(name):
    """QUEST, the q-method and the SVD method give the same attitude to 1e-9 rad on 20 noisy draws per case."""
    rng = np.random.default_rng(list(HARD_CASES).index(name))
    for _ in range(20):
        body, inertial, weights, truth = HARD_CASES[name](rng)
        quest, davenport, svd = (s.solve(body, inertial, weights) for s in SOLVERS)
        assert angle_between(quest, svd) < 1e-9
        assert angle_between(davenport, svd) < 1e-9
        assert angle_between(quest, davenport) < 1e-9
        if name.startswith("180 deg"):
            # The hard case is really there: the solution's Gibbs vector |tan(angle / 2)| exceeds 1e3, where
            # QUEST's matrix (lambda + sigma) I - S is nearly singular (see test_plain_gibbs_quest_fails_at_180_deg).
            assert np.tan(svd.magnitude() / 2) > 1e3


def plain_gibbs_quest(body: np.ndarray, inertial: np.ndarray) -> Rotation:
    """QUEST without sequential rotations, equal weights, exact lambda_max: Gibbs vector y from
    ((lambda + sigma) I - S) y = z, quaternion [y, 1] (Shuster's, so scipy's is [-y, 1])."""
    profile = body.T @ inertial / len(body)
    s, sigma = profile + profile.T, np.trace(profile)
    z = np.array([profile[1, 2] - profile[2, 1], profile[2, 0] - profile[0, 2], profile[0, 1] - profile[1, 0]])
    k = np.block([[s - sigma * np.eye(3), z[:, None]], [z[None, :], np.array([[sigma]])]])
    lam = np.linalg.eigvalsh(k)[-1]
    gibbs = np.linalg.solve((lam + sigma) * np.eye(3) - s, z)
    return Rotation.from_quat(np.append(-gibbs, 1.0))


@pytest.mark.parametrize("axis", list(AXES))
def test_plain_gibbs_quest_fails_at_180_deg(axis):
    """Without sequential rotations QUEST loses the attitude at 180 deg; QuestSolver does not.

    The Gibbs vector's error grows like eps |y| = 2 eps / offset: ~4e-14 rad at 1e-2 rad from 180 deg, inside the
    1e-11 bound, while exactly at 180 deg |y| is infinite and what is left is rounding luck, up to radians.
    """
    rng = np.random.default_rng(7)
    for offset, plain_error_range in ((1e-2, (0.0, 1e-11)), (0.0, (0.1, np.pi))):
        plain_errors = []
        for _ in range(5):
            truth = near_half_turn(rng, axis, offset)
            inertial = random_units(rng, 5)
            body = truth.apply(inertial)
            assert angle_between(solve.QuestSolver().solve(body, inertial), truth) < 1e-12
            plain_errors.append(angle_between(plain_gibbs_quest(body, inertial), truth))
        # Away from 180 deg the reference formula is right; at 180 deg its error is rounding luck, up to radians.
        assert plain_error_range[0] <= max(plain_errors) <= plain_error_range[1]


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
@pytest.mark.parametrize("name", ["3 stars", "weights over 12 decades", "5 stars in a 6 deg cone"])
def test_solution_minimises_wahba_loss(solver, name):
    """The loss at the solution is below the truth's and below that of small rotations of the solution."""
    rng = np.random.default_rng(11)
    for _ in range(10):
        body, inertial, weights, truth = HARD_CASES[name](rng)
        attitude = solver.solve(body, inertial, weights)
        best = loss(attitude, body, inertial, weights)
        assert solve.wahba_loss(attitude, body, inertial, weights) == pytest.approx(best, rel=1e-12)
        assert best <= loss(truth, body, inertial, weights)
        for size in (1e-7, 1e-4):
            for direction in np.vstack([np.eye(3), -np.eye(3), random_units(rng, 6)]):
                nudged = Rotation.from_rotvec(size * direction) * attitude
                assert best <= loss(nudged, body, inertial, weights)


def triad(body: np.ndarray, inertial: np.ndarray) -> Rotation:
    """TRIAD attitude: the first vector pair matched exactly, the second only in its plane."""

    def frame(first, second):
        across = np.cross(first, second)
        across /= np.linalg.norm(across)
        return np.stack([first, across, np.cross(first, across)], axis=1)

    return Rotation.from_matrix(frame(*body) @ frame(*inertial).T)


def two_vector_closed_form(body: np.ndarray, inertial: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Markley's optimal attitude matrix (inertial -> body) for two unit vector pairs and any weights."""
    w = weights / np.sum(weights)
    b3 = np.cross(*body) / np.linalg.norm(np.cross(*body))
    r3 = np.cross(*inertial) / np.linalg.norm(np.cross(*inertial))
    cosines = np.dot(*body) * np.dot(*inertial)
    sines = np.linalg.norm(np.cross(*body)) * np.linalg.norm(np.cross(*inertial))
    lam = np.sqrt(w[0] ** 2 + w[1] ** 2 + 2 * w[0] * w[1] * (cosines + sines))
    matrix = np.outer(b3, r3)
    for b, r, wi in zip(body, inertial, w, strict=True):
        matrix += wi / lam * (np.outer(b, r) + np.outer(np.cross(b, b3), np.cross(r, r3)))
    return matrix


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
def test_two_vectors_closed_form_and_triad_limit(solver):
    """Two pairs: exact attitude without noise; with noise Markley's closed form for any weights, and TRIAD (first
    pair exact) when the first weight dominates, which equal weights are not."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        truth = Rotation.random(random_state=rng)
        inertial = random_units(rng, 2)
        while np.linalg.norm(np.cross(*inertial)) < 0.5:  # 30 to 150 deg apart: the roll is well determined
            inertial = random_units(rng, 2)
        assert angle_between(solver.solve(truth.apply(inertial), inertial), truth) < 1e-12
        body = with_noise(rng, truth.apply(inertial), NOISE)
        weights = rng.uniform(0.1, 1.0, 2)
        expected = two_vector_closed_form(body, inertial, weights)
        np.testing.assert_allclose(solver.solve(body, inertial, weights).as_matrix(), expected, atol=1e-11)
        assert angle_between(solver.solve(body, inertial, [1.0, 1e-6]), triad(body, inertial)) < 1e-8
        assert angle_between(solver.solve(body, inertial), triad(body, inertial)) > 1e-7


def test_quest_falls_back_when_lambda_max_is_unresolved():
    """Three stars, two with weights 1e-10 of the first: lambda_max is within ~1e-10 of the next eigenvalue, below
    what the characteristic polynomial resolves in double precision (rounding moves its root by ~1e-9).  Taking
    Newton's root there can put QUEST radians off; with the q-method fallback it agrees with the SVD method to the
    problem's own sensitivity (eps / gap ~ 1e-6 rad)."""
    rng = np.random.default_rng(5)
    for _ in range(20):
        body, inertial, weights, _ = case(rng, 3, weights=np.array([1.0, 1e-10, 3e-10]))
        assert solve._lambda_max_newton(solve._profile(*solve.wahba_inputs(body, inertial, weights))) is None
        quest = solve.QuestSolver().solve(body, inertial, weights)
        assert angle_between(quest, solve.SvdSolver().solve(body, inertial, weights)) < 1e-4


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
def test_vector_lengths_and_weight_scale_do_not_matter(solver):
    """Rows are normalised (tiny and huge lengths too) and only weight ratios count."""
    rng = np.random.default_rng(13)
    body, inertial, weights, _ = case(rng, 6)
    reference = solver.solve(body, inertial, weights)
    lengths = np.array([1e-200, 1e-3, 1.0, 7.0, 1e3, 1e200])[:, None]
    scaled = solver.solve(body * lengths, inertial * lengths[::-1], weights * 1e100)
    assert angle_between(scaled, reference) < 1e-14


GOOD = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
BAD_INPUTS = {
    "NaN in body": ({"body": np.where(GOOD == 1.0, np.nan, GOOD)}, "body must be finite"),
    "inf in inertial": ({"inertial": np.where(GOOD == 1.0, np.inf, GOOD)}, "inertial must be finite"),
    "body rows of 2": ({"body": GOOD[:, :2]}, r"body must have shape \(n, 3\)"),
    "flat inertial": ({"inertial": GOOD.ravel()}, r"inertial must have shape \(n, 3\)"),
    "one vector": ({"body": GOOD[:1], "inertial": GOOD[:1]}, "at least 2 vectors"),
    "row counts differ": ({"inertial": GOOD[:2]}, "inertial must have the same shape as body"),
    "zero vector": ({"body": np.vstack([GOOD[:2], np.zeros(3)])}, "body must not contain zero vectors"),
    "parallel body": ({"body": [[0.0, 0.0, 1.0], [0.0, 1e-7, 2.0], [0.0, 0.0, -3.0]]}, "body vectors are .*parallel"),
    "parallel inertial": ({"inertial": [[1.0, 1.0, 0.0]] * 3}, "inertial vectors are .*parallel"),
    "negative weight": ({"weights": [1.0, -1.0, 1.0]}, "weights must be positive"),
    "zero weight": ({"weights": [1.0, 0.0, 1.0]}, "weights must be positive"),
    "NaN weight": ({"weights": [1.0, np.nan, 1.0]}, "weights must be finite"),
    "weights too few": ({"weights": [1.0, 1.0]}, r"weights must have shape \(3,\)"),
    "text weights": ({"weights": ["a", "b", "c"]}, "weights must be a real number"),
}


@pytest.mark.parametrize("solver", SOLVERS, ids=SOLVER_IDS)
@pytest.mark.parametrize("name", list(BAD_INPUTS))
def test_bad_input_is_refused(solver, name):
    """Each bad argument raises ValueError naming it (and, for parallel vectors, the unobservable attitude)."""
    change, message = BAD_INPUTS[name]
    arguments = {"body": GOOD, "inertial": GOOD, "weights": None} | change
    with pytest.raises(ValueError, match=message):
        solver.solve(**arguments)


def test_parallel_vectors_message_names_unobservable_attitude():
    """Two copies of one star leave the rotation about it free."""
    with pytest.raises(ValueError, match=r"vectors are \(nearly\) parallel: attitude is unobservable"):
        solve.QuestSolver().solve(GOOD[[0, 0]], GOOD[:2])


@pytest.mark.parametrize("name", SOLVER_IDS)
def test_solver_by_name(name):
    """Each name gives its solver class, which satisfies the AttitudeSolver protocol; other names are refused."""
    solver = solve.solver_by_name(name)
    assert isinstance(solver, AttitudeSolver)
    assert type(solver) is type(SOLVERS[SOLVER_IDS.index(name)])
    with pytest.raises(ValueError, match="name must be one of"):
        solve.solver_by_name("triad")
