"""Attitude from matched vector pairs (Wahba's problem): QUEST, Davenport's q-method and Markley's SVD method.

Each solver takes ``body`` (n, 3) and ``inertial`` (n, 3) direction vectors (row i of each is the same star) and
optional positive ``weights`` (n,), and returns the rotation ``A`` (inertial -> body, ``b = A.apply(r)``, see
:mod:`starenv.sim.conventions`) minimising Wahba's loss ``sum_i w_i |b_i - A r_i|^2``.  Vectors need not be unit
length (they are normalised); weights default to equal and only their ratios matter.

Internally quaternions are Shuster's ``[q1, q2, q3, q4]`` (vector part, then scalar) of the attitude matrix
``A(q) = (q4^2 - |q|^2) I + 2 q q^T - 2 q4 [q x]``, which is scipy's quaternion of ``A^-1``: ``[-q1, -q2, -q3, q4]``
is scipy's (scalar-last) quaternion of ``A``.  With the attitude profile matrix ``B = sum_i w_i b_i r_i^T``, the gain
``tr(A B^T) = sum w - loss / 2`` equals ``q^T K q`` for Davenport's symmetric 4 x 4 matrix
``K = [[S - sigma I, z], [z^T, sigma]]``, ``S = B + B^T``, ``sigma = tr B``, ``z = [B23 - B32, B31 - B13, B12 - B21]``;
the optimal quaternion is the eigenvector of K's largest eigenvalue ``lambda_max``.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.agents.blocks import wahba_svd
from starenv.checks import choice, finite

# Smallest sine of the angle between two of the vectors (in each set) for the attitude to count as observable: below
# it (0.2 arcsec) every rotation about the common direction fits almost equally well.
MIN_SEPARATION_SIN = 1e-6
# QUEST's Newton iteration on the characteristic polynomial (weights normalised to sum 1, so lambda_max <= 1): it
# stops when a step falls below NEWTON_TOLERANCE and gives up (q-method instead) after NEWTON_MAX_STEPS.
NEWTON_TOLERANCE = 1e-12
NEWTON_MAX_STEPS = 50
EPS = float(np.finfo(np.float64).eps)
POLY_ROUNDING = 16.0 * EPS  # relative rounding error of the quartic's value, coefficients included
# 180 deg rotations about x, y, z (diagonal matrices) for the method of sequential rotations.
HALF_TURNS = (np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0]))


def _unit_rows(name: str, vectors) -> np.ndarray:
    """``vectors`` as an (n, 3) float array of unit rows; refuses NaN/inf, other shapes and zero rows."""
    v = finite(name, vectors)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got shape {v.shape}")
    largest = np.max(np.abs(v), axis=1, initial=0.0)
    if np.any(largest == 0.0):
        raise ValueError(f"{name} must not contain zero vectors (rows {np.flatnonzero(largest == 0.0).tolist()})")
    v = v / largest[:, None]  # scaled first so that tiny or huge components neither underflow nor overflow
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _refuse_parallel(name: str, unit: np.ndarray) -> None:
    """Raise unless two of the unit rows are at least MIN_SEPARATION_SIN apart (parallel or antiparallel)."""
    if np.max(np.linalg.norm(np.cross(unit[0], unit), axis=1)) < MIN_SEPARATION_SIN:
        raise ValueError(f"{name} vectors are (nearly) parallel: attitude is unobservable")


def wahba_inputs(body, inertial, weights=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Checked solver inputs: unit body (n, 3), unit inertial (n, 3) and weights (n,) scaled to sum 1.

    Raises ``ValueError`` naming the parameter for NaN/inf, wrong shapes, fewer than 2 vectors, zero vectors,
    non-positive weights and (nearly) parallel vectors.
    """
    b = _unit_rows("body", body)
    r = _unit_rows("inertial", inertial)
    n = len(b)
    if n < 2:
        raise ValueError(f"body and inertial need at least 2 vectors, got {n}")
    if r.shape != b.shape:
        raise ValueError(f"inertial must have the same shape as body {b.shape}, got shape {r.shape}")
    if weights is None:
        w = np.ones(n)
    else:
        w = finite("weights", weights, shape=(n,))
        if np.any(w <= 0.0):
            raise ValueError(f"weights must be positive, got {w.tolist()}")
    _refuse_parallel("body", b)
    _refuse_parallel("inertial", r)
    return b, r, w / np.sum(w)


def wahba_loss(attitude: Rotation, body, inertial, weights=None) -> float:
    """Wahba's loss ``sum_i w_i |b_i - A r_i|^2`` of ``attitude`` (inertial -> body) for unit-normalised vectors.

    Weights are used as given (default 1 each), not scaled to sum 1.
    """
    b = _unit_rows("body", body)
    r = _unit_rows("inertial", inertial)
    w = np.ones(len(b)) if weights is None else finite("weights", weights, shape=(len(b),))
    return float(np.sum(w * np.sum((b - attitude.apply(r)) ** 2, axis=1)))


def _profile(b: np.ndarray, r: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Attitude profile matrix ``B = sum_i w_i b_i r_i^T`` (3, 3)."""
    return (w[:, None] * b).T @ r


def _davenport_parts(profile: np.ndarray) -> tuple[np.ndarray, float, np.ndarray]:
    """``S = B + B^T`` (3, 3), ``sigma = tr B`` and ``z`` (3,) of Davenport's K for the profile matrix B."""
    z = np.array([profile[1, 2] - profile[2, 1], profile[2, 0] - profile[0, 2], profile[0, 1] - profile[1, 0]])
    return profile + profile.T, float(np.trace(profile)), z


def _adjugate_trace(s: np.ndarray) -> float:
    """Trace of the adjugate of a 3 x 3 matrix: the sum of its principal 2 x 2 minors."""
    return 0.5 * (np.trace(s) ** 2 - np.trace(s @ s))


def _davenport_matrix(profile: np.ndarray) -> np.ndarray:
    """Davenport's symmetric K (4, 4) for the profile matrix B: ``q^T K q = tr(A(q) B^T)``."""
    s, sigma, z = _davenport_parts(profile)
    k = np.empty((4, 4))
    k[:3, :3] = s - sigma * np.eye(3)
    k[:3, 3] = k[3, :3] = z
    k[3, 3] = sigma
    return k


def _rotation(shuster_q: np.ndarray) -> Rotation:
    """Attitude (inertial -> body) of a Shuster quaternion ``[q1, q2, q3, q4]`` (any non-zero length)."""
    return Rotation.from_quat([-shuster_q[0], -shuster_q[1], -shuster_q[2], shuster_q[3]])


def _q_method(profile: np.ndarray) -> np.ndarray:
    """Shuster quaternion of the optimal attitude: K's eigenvector for its largest eigenvalue."""
    _, vectors = np.linalg.eigh(_davenport_matrix(profile))
    return vectors[:, -1]


def _lambda_max_newton(profile: np.ndarray) -> float | None:
    """Largest root of K's characteristic polynomial by Newton's method from ``sum w = 1``; None if not resolved.

    For lambda >= lambda_max the quartic is increasing and convex, so from above Newton descends monotonically onto
    lambda_max.  Rounding in the coefficients and the evaluation (``POLY_ROUNDING`` times the terms' magnitudes)
    moves the computed root by about that much over the slope ``p'(lambda_max)``, the product of the distances to
    the other eigenvalues (each <= 2, so the gap to the next one is >= p' / 4).  The root is refused (None) unless
    this error e satisfies ``e^2 <= eps p' / 4``, so that QUEST's Rayleigh-quotient refinement (error e^2 / gap)
    reaches rounding level; also when the slope turns non-positive or no step falls below NEWTON_TOLERANCE.
    """
    s, sigma, z = _davenport_parts(profile)
    kappa = _adjugate_trace(s)
    a = sigma**2 - kappa
    b = sigma**2 + z @ z
    c = np.linalg.det(s) + z @ s @ z
    d = z @ s @ s @ z
    lam = 1.0
    for _ in range(NEWTON_MAX_STEPS):
        slope = 4.0 * lam**3 - 2.0 * (a + b) * lam - c
        if slope <= 0.0:
            return None
        step = ((lam**2 - a) * (lam**2 - b) - c * lam + c * sigma - d) / slope
        lam -= step
        if abs(step) <= NEWTON_TOLERANCE:
            break
    else:
        return None
    terms = lam**4 + abs(a + b) * lam**2 + abs(c) * lam + abs(a * b) + abs(c * sigma) + abs(d)
    root_error = POLY_ROUNDING * terms / slope
    return float(lam) if root_error**2 <= EPS * slope / 4.0 else None


def _quest_vector(profile: np.ndarray, lam: float) -> tuple[np.ndarray, float]:
    """Shuster's unnormalised optimal quaternion ``[X, gamma]`` for eigenvalue ``lam``.

    ``gamma = det((lam + sigma) I - S)`` and ``X = adj((lam + sigma) I - S) z``, so that the Gibbs vector is
    ``X / gamma``; both vanish when the rotation is 180 deg (the Gibbs vector is infinite there).
    """
    s, sigma, z = _davenport_parts(profile)
    kappa = _adjugate_trace(s)
    alpha = lam**2 - sigma**2 + kappa
    beta = lam - sigma
    gamma = (lam + sigma) * alpha - np.linalg.det(s)
    x = (alpha * np.eye(3) + beta * s + s @ s) @ z
    return x, float(gamma)


class QuestSolver:
    """Shuster's QUEST with the method of sequential rotations (Shuster & Oh 1981), guarded by the q-method.

    1. ``lambda_max``: Newton's method on K's characteristic polynomial from ``sum w`` (weights scaled to sum 1).
    2. Sequential rotations: the Gibbs vector ``X / gamma`` is infinite at 180 deg, where X and gamma both vanish
       and their ratio is lost in rounding (a plain Gibbs-vector QUEST is off by about 2 eps / (pi - angle) rad, and
       by radians at 180 deg).  Rotating the inertial frame by 180 deg about x, y or z (``B -> B R``) swaps the
       quaternion's scalar part with one of its vector components; since ``gamma = C q4^2`` with C > 0 the same in
       every frame, gamma is computed in the original frame and the three rotated ones, the frame with the largest
       gamma (|q4| >= 1/2 there) is used and the rotation is composed back afterwards.
    3. One Rayleigh-quotient refinement: ``lambda = q^T K q`` of that quaternion, then ``[X, gamma]`` again.  Rounding
       in the quartic's coefficients moves the Newton root by about eps / p', where the slope
       ``p' = prod_j (lambda_max - lambda_j) <= 4 gap`` (gap: lambda_max minus the next eigenvalue, small for two or
       three stars close together, a narrow field, or weights that leave one star nearly alone); the quaternion
       inherits that error over the gap (eps / gap^2 in all), and the refinement brings it down to order eps / gap,
       as for the q-method.
    4. Fallback to the q-method (``numpy.linalg.eigh``) when the quartic cannot resolve lambda_max: Newton's slope
       turns non-positive, no step falls below NEWTON_TOLERANCE within NEWTON_MAX_STEPS, or the root's rounding
       error is too large for step 3 (see :func:`_lambda_max_newton`).  The step size alone does not reveal this:
       with three stars weighted 1 : 1e-10 : 3e-10 (gap ~5e-10), Newton stops with steps below 1e-12 on a root that
       rounding has moved by more than the gap, and the attitude from it can be off by radians.
    """

    def solve(self, body: np.ndarray, inertial: np.ndarray, weights: np.ndarray | None = None) -> Rotation:
        """Attitude (inertial -> body) minimising Wahba's loss; see :func:`wahba_inputs` for the checks."""
        b, r, w = wahba_inputs(body, inertial, weights)
        profile = _profile(b, r, w)
        lam = _lambda_max_newton(profile)
        if lam is None:
            return _rotation(_q_method(profile))
        frames = [np.eye(3), *HALF_TURNS]
        candidates = [_quest_vector(profile @ turn, lam) for turn in frames]
        best = int(np.argmax([gamma for _, gamma in candidates]))
        turned = profile @ frames[best]
        q = np.append(*candidates[best])
        q /= np.linalg.norm(q)
        lam = float(q @ _davenport_matrix(turned) @ q)
        q = np.append(*_quest_vector(turned, lam))
        return _rotation(q) * Rotation.from_matrix(frames[best])


class DavenportSolver:
    """Davenport's q-method: the eigenvector of K for its largest eigenvalue (``numpy.linalg.eigh``)."""

    def solve(self, body: np.ndarray, inertial: np.ndarray, weights: np.ndarray | None = None) -> Rotation:
        """Attitude (inertial -> body) minimising Wahba's loss; see :func:`wahba_inputs` for the checks."""
        return _rotation(_q_method(_profile(*wahba_inputs(body, inertial, weights))))


class SvdSolver:
    """Markley's SVD method: with ``B = U diag(s) V^T``, ``A = U diag(1, 1, det(U V^T)) V^T``
    (:func:`starenv.agents.blocks.wahba_svd`)."""

    def solve(self, body: np.ndarray, inertial: np.ndarray, weights: np.ndarray | None = None) -> Rotation:
        """Attitude (inertial -> body) minimising Wahba's loss; see :func:`wahba_inputs` for the checks."""
        return Rotation.from_matrix(wahba_svd(*wahba_inputs(body, inertial, weights)))


SOLVERS = {"quest": QuestSolver, "davenport": DavenportSolver, "svd": SvdSolver}


def solver_by_name(name: str) -> QuestSolver | DavenportSolver | SvdSolver:
    """A new solver: ``"quest"``, ``"davenport"`` or ``"svd"``."""
    return SOLVERS[choice("name", name, sorted(SOLVERS))]()
