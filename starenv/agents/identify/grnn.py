"""Paper 004's multi-stage identifier for multi-head sensors: a GRNN on each star's triangle feature, verification
against the library, and boresight-aided identification across heads (:class:`GrnnIdentifier`).

Library (:class:`TriangleLibrary`).  The navigation stars are the catalogue's down to ``nav_mag_limit`` (the paper's
6.5).  Each star's three sides d_i (deg: star-nearest, star-second-nearest, nearest-second-nearest, among navigation
stars) give its P value ``P_i = Omega . d_i``, ``Omega`` the leading eigenvector of ``W = mean(d_i d_i^T)`` (the
paper's Eqs. 1-3; Hipparcos to Hp 6.5 gives ``Omega = [0.399 0.578 0.712]``, the paper's SAO set
``[0.397 0.580 0.711]``).

Stage 1, per head.  The ``stage1_stars`` brightest detections (default: 1.5 times the navigation stars expected in
the head's field) form the image's triangles: each detection with its two nearest other detections.  Their feature
-- the three sides themselves (``feature="sides"``, ours, the default) or the scalar P (``feature="p"``, the
paper's, which does not identify: see :class:`GrnnIdentifier`) -- goes through a generalised regression network
(:class:`Grnn`: Gaussian kernel regression, MATLAB ``newgrnn``'s spread convention, ``a = exp(-(0.8326 d / rho)^2)``)
trained on ``draws`` noisy copies of every library star's feature (centroid noise rising 0 -> ``max_noise_px``,
:mod:`starenv.datasets.triangles`), whose output is the star number as 13 bits (thresholded at 0.5; 0 or a number
past the library: unidentified).

Stage 2, verification.  An identified detection's image sides must match its library star's within
``eta = sqrt(2) delta theta`` on each side (the paper's Eq. 4: ``delta`` the spot radius, ``spot_radius_px``,
default 2 sigma of the calibrated spot, the radius holding 86 % of its light; ``theta`` the head's pixel angle).
The network proposes the library star whose sides are nearest the image's, so a wrong triangle (a neighbour outside
the field, a missing or false star) often verifies too: the verified stars of all heads must then agree pairwise
(body-frame angle vs catalogue angle within ``eta``), the star with most disagreements dropped until all agree, and
fewer than four agreeing stars count as none (three stars of one image triangle agree with each other exactly when
their triangle verified: no new check).  This consensus is ours; the paper verifies triangles only.

Stage 3, across heads.  With two or more verified stars the attitude (SVD solution of Wahba's problem) gives each
head's boresight; library stars within ``R_FOV + xi`` of it (``R_FOV`` the head's half-diagonal, ``xi`` 3 deg, the
paper's) are candidates for each detection still unidentified, in any head: a candidate is taken when its catalogue
angles to every verified star match the detection's body-frame angles within ``eta`` and no other candidate does.
This labels heads with 1-2 stars and re-identifies heads whose stage-1 ids failed verification.

``last_stages`` holds, per head, the library rows after each stage (-1: none) and ``last_timing_ms`` each stage's
wall time.  Ids are HIP numbers.
"""

from __future__ import annotations

import math
import time

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from starenv import checks
from starenv.agents.base import StarMeasurements
from starenv.agents.blocks import wahba_svd
from starenv.agents.identify.geometry import chord
from starenv.datasets.triangles import nearest_two, noisy_three_sides, three_sides
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog

CODE_BITS = 13  # the paper's 13-bit star number (2^13 = 8192 >= its 6970 stars)
NEWGRNN_SCALE = 0.8326  # sqrt(-ln 0.5): MATLAB newgrnn's weight is 0.5 at a distance of one spread
MIN_CONSENSUS = 4  # verified stars that must agree pairwise before any is trusted
KERNEL_REACH = 3.0  # training samples farther than this many spreads are left out (weight < 2e-3)


class TriangleLibrary:
    """Navigation stars with their three sides (n, 3) deg, neighbours (n, 2), Omega (3,) and P values (n,)."""

    def __init__(self, catalog: StarCatalog, nav_mag_limit: float = 6.5):
        keep = catalog.magnitude <= nav_mag_limit
        if np.count_nonzero(keep) < 3:
            raise ValueError(f"nav_mag_limit {nav_mag_limit} leaves fewer than 3 catalogue stars")
        self.hip = catalog.hip[keep]
        self.unit = catalog.unit[keep]
        self.neighbours = nearest_two(self.unit)
        self.sides = three_sides(self.unit, self.unit[self.neighbours[:, 0]], self.unit[self.neighbours[:, 1]])
        self.omega = best_projection_axis(self.sides)
        self.p = self.sides @ self.omega
        self.tree = cKDTree(self.unit)

    def __len__(self) -> int:
        return len(self.hip)


def best_projection_axis(sides: np.ndarray) -> np.ndarray:
    """The paper's Omega: unit leading eigenvector of ``W = mean(d d^T)`` over rows ``d`` of ``sides``, signed so
    that its components sum positive."""
    w = sides.T @ sides / len(sides)
    _, vectors = np.linalg.eigh(w)
    axis = vectors[:, -1]
    return axis if axis.sum() >= 0 else -axis


def code_bits(codes: np.ndarray) -> np.ndarray:
    """The 13-bit binary form (n, 13) of integer star numbers (n,), least significant bit first."""
    return ((np.asarray(codes)[:, None] >> np.arange(CODE_BITS)) & 1).astype(np.float64)


class Grnn:
    """Generalised regression network: inputs (m, d) with integer targets (m,) coded as 13 bits; the output for ``x``
    is ``sum_j a_j t_j / sum_j a_j`` with ``a_j = exp(-(0.8326 |x - x_j| / spread)^2)`` over the training samples
    within ``3 spread`` (no sample there: NaN)."""

    def __init__(self, inputs: np.ndarray, targets: np.ndarray, spread: float):
        self.spread = checks.in_range("rho", spread, 0.0, 10.0, low_open=True, unit="deg")
        inputs = np.asarray(inputs, dtype=np.float64)
        inputs = inputs.reshape(len(inputs), -1)
        order = np.argsort(inputs[:, 0], kind="stable")  # 1-D inputs: a sorted array is the index
        self.inputs, self.bits = inputs[order], code_bits(np.asarray(targets)[order])
        self.tree = cKDTree(self.inputs) if inputs.shape[1] > 1 else None

    def outputs(self, x: np.ndarray) -> np.ndarray:
        """Network outputs (q, 13) for inputs ``x`` (q, d)."""
        x = np.asarray(x, dtype=np.float64).reshape(-1, self.inputs.shape[1])
        reach = KERNEL_REACH * self.spread
        if self.tree is None:
            lo = np.searchsorted(self.inputs[:, 0], x[:, 0] - reach)
            hi = np.searchsorted(self.inputs[:, 0], x[:, 0] + reach, side="right")
            near = [slice(a, b) for a, b in zip(lo, hi, strict=True)]
        else:
            near = self.tree.query_ball_point(x, reach)
        out = np.full((len(x), CODE_BITS), np.nan)
        for i, rows in enumerate(near):
            d = np.linalg.norm(self.inputs[rows] - x[i], axis=1)
            if len(d):
                a = np.exp(-((NEWGRNN_SCALE * d / self.spread) ** 2))
                out[i] = a @ self.bits[rows] / a.sum()
        return out

    def predict(self, x: np.ndarray) -> np.ndarray:
        """Star numbers (q,) decoded from the outputs thresholded at 0.5 (0 where there is no output)."""
        bits = self.outputs(x)
        codes = (np.nan_to_num(bits, nan=0.0) > 0.5).astype(np.int64) @ (1 << np.arange(CODE_BITS))
        return np.where(np.isnan(bits).any(axis=1), 0, codes)


def angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (deg) between unit vectors, pairwise: (n, 3) x (m, 3) -> (n, m)."""
    return np.degrees(np.arccos(np.clip(a @ b.T, -1.0, 1.0)))


class GrnnIdentifier:
    """Paper 004's three-stage identifier (module docstring) as an :class:`~starenv.agents.base.Identifier`.

    Options: ``feature`` ("sides", the default: the three sides; "p": the paper's scalar P, kept for comparison: it
    identifies almost no star, because thousands of navigation stars' P values share a few degrees and lie closer
    together than centroid noise moves one), ``rho`` (GRNN spread, deg; the paper's 0.01), ``nav_mag_limit`` (6.5),
    ``draws`` (noisy samples per star, 100) and ``max_noise_px`` (0.1), ``spot_radius_px`` (None: 2 sigma of each
    head's calibrated spot), ``xi_deg`` (3), ``stage1_stars`` (None: 1.5 times the expected navigation stars per
    head), ``seed`` (training noise).  Training happens at :meth:`reset`.
    """

    def __init__(self, feature: str = "sides", rho: float = 0.01, nav_mag_limit: float = 6.5, draws: int = 100,
                 max_noise_px: float = 0.1, spot_radius_px: float | None = None, xi_deg: float = 3.0,
                 stage1_stars: int | None = None, seed: int = 0):
        if feature not in ("p", "sides"):
            raise ValueError(f"feature must be 'p' or 'sides', got {feature!r}")
        self.feature = feature
        self.rho = checks.in_range("rho", rho, 0.0, 10.0, low_open=True, unit="deg")
        self.nav_mag_limit = checks.in_range("nav_mag_limit", nav_mag_limit, -2.0, 14.0, unit="mag")
        self.draws = checks.integer("draws", draws, 1, 10000)
        self.max_noise_px = checks.in_range("max_noise_px", max_noise_px, 0.0, 10.0, unit="px")
        self.spot_radius_px = None if spot_radius_px is None else checks.in_range(
            "spot_radius_px", spot_radius_px, 0.0, 100.0, low_open=True, unit="px")
        self.xi_deg = checks.in_range("xi_deg", xi_deg, 0.0, 90.0, unit="deg")
        self.stage1_stars = None if stage1_stars is None else checks.integer("stage1_stars", stage1_stars, 3, 10000)
        self.seed = checks.integer("seed", seed, 0, 2**63 - 1)
        self.library: TriangleLibrary | None = None
        self.network: Grnn | None = None
        self.last_stages: dict[str, list[np.ndarray]] = {}
        self.last_timing_ms: dict[str, float] = {}

    def reset(self, cameras: list[Camera], catalog: StarCatalog) -> None:
        """Build the library from ``catalog`` and train the network on noisy copies of its features."""
        self.library = lib = TriangleLibrary(catalog, self.nav_mag_limit)
        pixel_rad = 1.0 / min(min(cam.fx, cam.fy) for cam in cameras)
        sigmas = np.linspace(0.0, self.max_noise_px, self.draws)
        noisy = noisy_three_sides(lib.unit, lib.neighbours, pixel_rad, sigmas, self.seed)  # (n, draws, 3)
        codes = np.repeat(np.arange(1, len(lib) + 1), self.draws)
        if len(lib) >= 2**CODE_BITS:
            raise ValueError(f"{len(lib)} navigation stars do not fit {CODE_BITS}-bit star numbers")
        self.network = Grnn(self._features(noisy.reshape(-1, 3)), codes, self.rho)

    def _features(self, sides: np.ndarray) -> np.ndarray:
        return sides @ self.library.omega if self.feature == "p" else sides

    def _eta_deg(self, camera: Camera) -> float:
        """The verification threshold sqrt(2) delta theta (deg) of one head."""
        delta = 2.0 * camera.psf_sigma_px if self.spot_radius_px is None else self.spot_radius_px
        return math.degrees(math.sqrt(2.0) * delta / min(camera.fx, camera.fy))

    def _stage1_count(self, camera: Camera) -> int:
        if self.stage1_stars is not None:
            return self.stage1_stars
        area = camera.fov[0] * camera.fov[1]
        return max(3, math.ceil(1.5 * len(self.library) * area / (4.0 * math.pi)))

    def identify(self, stars: list[StarMeasurements], cameras: list[Camera], prior: Rotation | None = None,
                 images: list[np.ndarray | None] | None = None) -> list[StarMeasurements]:
        """HIP numbers for every head's detections (-1: unidentified); ``prior`` and ``images`` are not used."""
        if self.library is None:
            raise RuntimeError("call reset(cameras, catalog) before identify")
        if len(stars) != len(cameras):
            raise ValueError(f"stars must hold one StarMeasurements per camera ({len(cameras)}), got {len(stars)}")
        t0 = time.perf_counter()
        triangles = [self._triangles(s, cam) for s, cam in zip(stars, cameras, strict=True)]
        first = [self.stage1(tri) for tri in triangles]
        t1 = time.perf_counter()
        verified = self.verify(stars, cameras, triangles, first)
        t2 = time.perf_counter()
        final = self.correct(stars, cameras, verified)
        t3 = time.perf_counter()
        self.last_stages = {"stage1": first, "stage2": verified, "stage3": final}
        self.last_timing_ms = {"stage1": 1e3 * (t1 - t0), "stage2": 1e3 * (t2 - t1), "stage3": 1e3 * (t3 - t2)}
        return [StarMeasurements(s.xy.copy(), s.flux.copy(), np.where(rows >= 0, self.library.hip[rows], -1))
                for s, rows in zip(stars, final, strict=True)]

    def _triangles(self, stars: StarMeasurements, camera: Camera) -> tuple[np.ndarray, np.ndarray]:
        """The detections used in stage 1 (brightest first) and their image sides (k, 3) deg."""
        used = np.argsort(-stars.flux, kind="stable")[: self._stage1_count(camera)]
        if len(used) < 3:
            return used, np.zeros((len(used), 3))
        v = camera.unproject(stars.xy[used])
        sep = angles(v, v)
        np.fill_diagonal(sep, np.inf)
        near = np.argsort(sep, axis=1, kind="stable")[:, :2]
        return used, three_sides(v, v[near[:, 0]], v[near[:, 1]])

    def stage1(self, triangles: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """Library rows (k,) of the stage-1 detections from the network (-1: no valid star number)."""
        used, sides = triangles
        rows = np.full(len(used), -1)
        if len(used) >= 3:
            codes = self.network.predict(self._features(sides))
            ok = (codes >= 1) & (codes <= len(self.library))
            rows[ok] = codes[ok] - 1
        return rows

    def verify(self, stars, cameras, triangles, first) -> list[np.ndarray]:
        """Stage 2: per head, library rows (n,) of each detection that passed (-1 elsewhere): its triangle within
        eta of its library star's, then pairwise agreement of all heads' verified stars."""
        lib = self.library
        out = [np.full(len(s), -1) for s in stars]
        for h, ((used, sides), rows) in enumerate(zip(triangles, first, strict=True)):
            eta = self._eta_deg(cameras[h])
            ok = rows >= 0
            ok[ok] = np.all(np.abs(sides[ok] - lib.sides[rows[ok]]) <= eta, axis=1)
            out[h][used[ok]] = rows[ok]
        return self._consensus(stars, cameras, out)

    def _consensus(self, stars, cameras, rows_per_head) -> list[np.ndarray]:
        """Drop verified stars until every pair's body-frame angle matches its catalogue angle within eta (the
        larger of the two heads'), the star with most disagreements first; a library star claimed twice is kept once."""
        heads, dets, rows, body = [], [], [], []
        for h, (s, cam, r) in enumerate(zip(stars, cameras, rows_per_head, strict=True)):
            k = np.flatnonzero(r >= 0)
            heads += [h] * len(k)
            dets += k.tolist()
            rows += r[k].tolist()
            body.append(cam.mounting.inv().apply(cam.unproject(s.xy[k])) if len(k) else np.zeros((0, 3)))
        out = [np.full(len(s), -1) for s in stars]
        if not rows:
            return out
        rows_arr, body_arr = np.array(rows), np.concatenate(body)
        keep = np.ones(len(rows_arr), bool)
        _, first_claim = np.unique(rows_arr, return_index=True)
        keep[np.setdiff1d(np.arange(len(rows_arr)), first_claim)] = False
        eta = np.array([self._eta_deg(cameras[h]) for h in heads])
        tolerance = np.maximum(eta[:, None], eta[None, :])
        bad = np.abs(angles(body_arr, body_arr) - angles(self.library.unit[rows_arr], self.library.unit[rows_arr]))
        bad = bad > tolerance
        while True:
            counts = (bad & keep[None, :] & keep[:, None]).sum(axis=1)
            if counts.max(initial=0) == 0:
                break
            keep[np.argmax(counts)] = False
        if np.count_nonzero(keep) < MIN_CONSENSUS:
            return out
        for i in np.flatnonzero(keep):
            out[heads[i]][dets[i]] = rows_arr[i]
        return out

    def correct(self, stars, cameras, verified) -> list[np.ndarray]:
        """Stage 3: detections left unidentified in any head matched to library stars near their head's boresight
        by their angles to the verified stars (module docstring); needs two verified stars (the consensus of stage 2
        leaves four or none)."""
        lib = self.library
        out = [r.copy() for r in verified]
        ref_body = np.concatenate([cam.mounting.inv().apply(cam.unproject(s.xy[r >= 0]))
                                   for s, cam, r in zip(stars, cameras, verified, strict=True)])
        ref_rows = np.concatenate([r[r >= 0] for r in verified])
        if len(ref_rows) < 2:
            return out
        attitude = wahba_svd(ref_body, lib.unit[ref_rows])  # inertial -> body matrix
        used = set(ref_rows.tolist())
        for h, (s, cam) in enumerate(zip(stars, cameras, strict=True)):
            todo = np.flatnonzero(out[h] < 0)
            if not len(todo):
                continue
            boresight = attitude.T @ cam.mounting.inv().apply([0.0, 0.0, 1.0])
            reach = cam.half_diagonal + math.radians(self.xi_deg)
            candidates = np.array([c for c in lib.tree.query_ball_point(boresight, chord(reach)) if c not in used])
            if not len(candidates):
                continue
            eta = self._eta_deg(cam)
            catalogue = angles(lib.unit[candidates], lib.unit[ref_rows])  # (c, r)
            measured = angles(cam.mounting.inv().apply(cam.unproject(s.xy[todo])), ref_body)  # (k, r)
            fits = np.all(np.abs(measured[:, None, :] - catalogue[None, :, :]) <= eta, axis=2)  # (k, c)
            unique = fits.sum(axis=1) == 1
            chosen = candidates[np.argmax(fits, axis=1)]
            claimed, counts = np.unique(chosen[unique], return_counts=True)
            unique &= ~np.isin(chosen, claimed[counts > 1])  # two detections on one star: neither is taken
            out[h][todo[unique]] = chosen[unique]
            used.update(chosen[unique].tolist())
        return out
