"""Verifying an attitude hypothesis against the catalogue, for identifiers that first guess and then check, and the
false-match probability every verifier uses.

The false-match probability.  Take a wrong attitude: it puts each detection's direction on a patch of sky unrelated
to the star that made it.  The catalogue stars around that patch are modelled as a Poisson field of ``density``
stars per steradian (the stars counted in the field divided by its solid angle), so the chance that at least one
lies within ``r`` rad of the detection is ``p = 1 - exp(-density * pi * r**2)`` (:func:`chance_match`; ``~ density *
pi * r**2`` when small; the same with stars per px^2 and ``r`` in px).  Detections more than ``2 r`` apart look at
disjoint discs of a Poisson field, so these events are independent.  Of ``n`` detections, the ``g`` the hypothesis was
built from pair by construction; each of the other ``n - g`` pairs by chance with probability ``p``, so the number
``X`` that do is Binomial(n - g, p) and the probability that a wrong attitude pairs ``m`` detections or more is

    P_false(m) = P(X >= m - g) = sum_{j = m-g}^{n-g} C(n-g, j) p^j (1 - p)^(n-g-j)

(:func:`false_match_probability`, as tetra3 / cedar-solve verify).  A search that tried ``H`` hypotheses accepts a
wrong one with probability at most ``H * P_false(m)`` (union bound); each verifier states its ``g`` and ``H`` and
compares that bound with its threshold.  The model leaves out the edges of the field (fewer stars around a detection
near a corner: the bound stays an upper one) and clustering of stars (the galactic plane: ``density`` is measured in
each field, not over the sky).

:func:`verify`: for a hypothesis (inertial -> body), every head's catalogue stars in its field are projected, each
detection is paired with the nearest projected star within ``radius_px`` (one detection a star, closest pairs first),
the attitude is refined from the pairs (SVD solution of Wahba's problem) and the pairing repeated; ``p`` there is the
stars in the field times the disc area over the image area.

A bound whatever the search (:func:`verify_any_search`).  The count ``H`` above is only honest when the hypotheses
tried are fixed before the detections are compared with the catalogue; a search that picks its hypotheses from the
detections (votes, refinement) explores more attitudes than it tries.  Any attitude that pairs ``m >= 2``
detections within ``r`` is close to the attitude fixed by two of its pairs, and the separation of those two
detections then agrees with that of their two stars within ``2 r``.  So the attitudes any search can end on are
covered by the two-pair hypotheses: (detection pair, ordered star pair) combinations whose separations agree within
``2 r`` (:func:`pair_hypotheses`), each pairing its two detections by construction (``g = 2``).  With the stars of
the field under the verified attitude counted, times the ``regions`` of the sky the search could be in (a
lost-in-space identifier that only looks about ``k`` candidate directions: ``k``), the union bound gives

    P_wrong <= regions * H_2 * P(X >= m - 2),   X ~ Binomial(n - 2, p).

The radius is the one the final pairing uses: :func:`verify_any_search` refines a hypothesis at the search's
radius, then pairs and refines again at ``radius_px``, so that an attitude a few pixels off the truth (which the
search radius still pairs with most of the stars, and so with a few wrong ones) settles on the right stars or fails.
The covering is a model, not a theorem: the attitude fixed by two pairs puts the other pairs within a few ``r``
(more for pairs far from the two), not ``r``; the tests check the bound on random star fields against the best of
every two-pair hypothesis.

What that allows.  On paper 002's 128 px sensor (12 deg, Hp 6.5: about 40 stars in a field, ``p ~ 0.008`` at
1 px) a frame of 30 detections has 435 detection pairs and 1560 ordered star pairs, about one in 30 of them agreeing
within 2 px: ``H_2 ~ 2e4``; with three regions, 10 pairs give a bound of 2e-6, 9 pairs 1e-4 (refused at 1e-5).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.special import bdtrc

from starenv.agents.blocks import wahba_svd
from starenv.agents.identify.geometry import IDENTITY
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog


def chance_match(density: float | np.ndarray, radius: float | np.ndarray) -> float | np.ndarray:
    """Probability that a Poisson field of ``density`` stars per unit area has one within ``radius`` of a point
    (``density`` per sr with ``radius`` in rad, or per px^2 with px)."""
    return -np.expm1(-density * math.pi * np.square(radius))


def false_match_probability(n: int, m: int, p: float, given: int = 0, hypotheses: float = 1.0) -> float:
    """Bound on the probability that a wrong attitude, among ``hypotheses`` tried, pairs ``m`` of ``n`` detections
    when ``given`` of them pair by construction and each other one by chance with probability ``p``:
    ``min(1, hypotheses * P(X >= m - given))``, ``X ~ Binomial(n - given, p)`` (see the module docstring)."""
    if m <= given:
        return 1.0
    return min(1.0, float(hypotheses * bdtrc(m - given - 1, n - given, p)))


def predicted_scatter(basis: np.ndarray, weight: float | np.ndarray, directions: np.ndarray) -> list:
    """The variance (rad^2, the two axes across it summed) of each of the unit vectors ``directions`` (k, 3)
    predicted under an attitude fitted on the unit vectors ``basis`` (m, 3), from the attitude's covariance; ``weight``
    is the inverse centroid variance (rad^-2 per axis) of the basis vectors, a number or (m,).  In plain numbers (a
    3 x 3 inverse by cofactors)."""
    if isinstance(weight, float):
        information = weight * (len(basis) * IDENTITY - basis.T.dot(basis))
    else:
        information = weight.sum() * IDENTITY - (basis.T * weight) @ basis
    (a, d, e), (_, f, g), (_, _, h) = information.tolist()  # symmetric
    ca, cd, ce = f * h - g * g, e * g - d * h, d * g - e * f  # its cofactors
    cf, cg, ch = a * h - e * e, d * e - a * g, a * f - d * d
    scale = 1.0 / (a * ca + d * cd + e * ce)  # covariance = cofactors * scale (rad^2, about body axes)
    trace = ca + cf + ch
    return [  # E|rotation x direction|^2 = trace(C) - direction' C direction
        max(scale * (trace - (ca * x * x + cf * y * y + ch * z * z + 2.0 * (cd * x * y + ce * x * z + cg * y * z))),
            0.0)
        for x, y, z in directions.tolist()
    ]


def anchor_head(head: np.ndarray, matched: np.ndarray) -> int | None:
    """The head of ``head`` (pooled detections' heads) with most ``matched`` detections, three or more (None when
    none has three: no head fixes the attitude alone); of equals, the one with fewest detections (chance matches come
    with many)."""
    per_head = np.bincount(head[matched], minlength=int(head.max()) + 1) if len(matched) else np.zeros(1, dtype=int)
    if per_head.max() < 3:
        return None
    return int(np.lexsort((np.bincount(head, minlength=len(per_head)), -per_head))[0])


def unconfirmed_heads(body: np.ndarray, head: np.ndarray, matched: np.ndarray, anchor: int,
                      weight: float | np.ndarray, radius2: np.ndarray, chance: np.ndarray,
                      threshold: float) -> list:
    """The heads whose ``matched`` detections may be chance matches (or, with none, whose detections a labelling
    radius wider than the match radius may label by chance), ``anchor`` (a head whose matches fix the attitude alone)
    aside: pooled detections ``body`` (n, 3) of heads ``head`` (n,), their inverse centroid variance
    ``weight`` (rad^-2, a number or (n,)); per head its match radius squared ``radius2`` (rad^2) and the chance
    ``chance`` that a detection lands that close to a star under a wrong attitude; ``anchor`` as
    :func:`anchor_head` gives it.

    One small head's matches leave the roll about it loose: another head's stars move by several match radii, and a
    detection there can land within the radius of a wrong star; taken into a fit, that one match pins the roll to
    itself.  So a head is confirmed when the attitude fitted on the confirmed heads' matches (the anchor's at first)
    predicts its detections within their match radius (3 sigma, :func:`predicted_scatter`), or when its matches are
    too many for chance: the search over the loose roll covers about ``3 sigma / radius`` distinct rolls, and at each
    the head's ``n`` detections match ``k`` or more stars with probability ``P(X >= k)``, ``X ~ Binomial(n, chance)``;
    their product (:func:`false_match_probability`) must stay under ``threshold``.  Confirming repeats until no head
    is added.  The heads left are then tested together (one roll moves them all: coincidences in several heads at
    one roll multiply), with the most rolls and the largest chance of any of them, and are returned unless that
    passes."""
    found = np.bincount(head[matched], minlength=len(radius2))
    pending = [h for h in np.flatnonzero(np.bincount(head)).tolist() if h != anchor]
    confirmed = np.zeros(len(radius2), dtype=bool)
    confirmed[anchor] = True
    while pending:
        basis = matched[confirmed[head[matched]]]
        basis_weight = weight if isinstance(weight, float) else weight[basis]
        left, searched = [], []  # per head left: (detections, rolls)
        for h in pending:
            rows = (head == h).nonzero()[0]
            reach2 = 9.0 * max(predicted_scatter(body[basis], basis_weight, body[rows]))
            rolls = math.sqrt(reach2 / radius2[h])
            if reach2 > radius2[h] and false_match_probability(
                len(rows), int(found[h]), float(chance[h]), 0, rolls
            ) >= threshold:
                left.append(h)
                searched.append((len(rows), rolls))
            else:
                confirmed[h] = True
        if len(left) == len(pending):
            break
        pending = left
    if len(pending) > 1 and false_match_probability(
        sum(n for n, _ in searched), int(found[pending].sum()), float(chance[pending].max()), 0,
        max(rolls for _, rolls in searched)
    ) < threshold:
        return []
    return pending


def pair_hypotheses(body: np.ndarray, reference: np.ndarray, tolerance: float) -> int:
    """Attitudes fixed by two (detection, star) pairs: the (detection pair, ordered star pair) combinations of unit
    vectors ``body`` (n, 3) and ``reference`` (s, 3) whose angular separations agree within ``tolerance`` (rad)."""
    if len(body) < 2 or len(reference) < 2:
        return 0
    detection = _separations(body)
    star = np.sort(_separations(reference))
    agree = np.searchsorted(star, detection + tolerance, "right") - np.searchsorted(star, detection - tolerance, "left")
    return 2 * int(agree.sum())


def _separations(unit: np.ndarray) -> np.ndarray:
    """Angles (rad) between every two of the unit vectors ``unit`` (k, 3), each pair once."""
    i, j = np.triu_indices(len(unit), 1)
    return 2.0 * np.arcsin(np.minimum(np.linalg.norm(unit[i] - unit[j], axis=1) / 2.0, 1.0))


@dataclass
class Verdict:
    """A verified (or refuted) hypothesis: pooled ids (-1 none), pairs ``m`` of ``n`` detections, the false-match
    probability, the refined attitude, the catalogue rows in the heads' fields under it and the chance ``p`` that a
    detection pairs with one of them; ``hypotheses``: the ``H`` (or ``regions * H_2``) in ``p_false``."""

    ids: np.ndarray
    matched: int
    detections: int
    p_false: float
    attitude: Rotation
    field: np.ndarray
    p_match: float
    hypotheses: float = 1.0


def verify(attitude: Rotation, body: np.ndarray, heads: np.ndarray, cameras: list[Camera], catalog: StarCatalog,
           radius_px: float = 3.0, given: int = 0, refine: int = 2) -> Verdict:
    """Pair detections (pooled body vectors ``body`` of heads ``heads``) with the catalogue under ``attitude``, solve
    and re-pair up to ``refine`` times (fewer once the pairs stop changing); ``given``: detections the hypothesis was
    built from."""
    n = len(body)
    ids = np.full(n, -1, dtype=np.int64)
    for step in range(refine + 1):
        previous, ids = ids, np.full(n, -1, dtype=np.int64)
        pairs_b, pairs_r, field = [], [], []
        expected = 0.0
        for h, cam in enumerate(cameras):
            rows_det = np.flatnonzero(heads == h)
            cam_rot = cam.mounting * attitude
            axis = cam_rot.inv().apply([0.0, 0.0, 1.0])
            rows = catalog.cone(axis, min(math.pi, cam.half_diagonal + 0.01))
            xy, front = cam.project(cam_rot.apply(catalog.unit[rows]))
            inside = front & cam.in_frame(xy)
            rows, xy = rows[inside], xy[inside]
            field.append(rows)
            area = cam.width * cam.height
            expected += len(rows_det) * min(1.0, len(rows) * math.pi * radius_px**2 / area)
            if not len(rows_det) or not len(rows):
                continue
            det_xy, _ = cam.project(cam.mounting.apply(body[rows_det]))
            d = np.linalg.norm(det_xy[:, None, :] - xy[None, :, :], axis=2)
            order = np.argsort(d, axis=None)
            used_d, used_s = set(), set()
            for flat in order:
                i, j = divmod(int(flat), len(rows))
                if d[i, j] > radius_px:
                    break
                if i in used_d or j in used_s:
                    continue
                used_d.add(i)
                used_s.add(j)
                ids[rows_det[i]] = catalog.hip[rows[j]]
                pairs_b.append(body[rows_det[i]])
                pairs_r.append(catalog.unit[rows[j]])
        if len(pairs_b) < 2 or (step and np.array_equal(ids, previous)):
            break  # (the same pairs: the attitude is already their solution)
        attitude = Rotation.from_matrix(wahba_svd(np.array(pairs_b), np.array(pairs_r)))
    m = int((ids >= 0).sum())
    p = expected / n if n else 0.0
    p_false = false_match_probability(n, m, p, given)
    return Verdict(ids, m, n, p_false, attitude, np.unique(np.concatenate(field)), p)


def verify_any_search(attitude: Rotation, body: np.ndarray, heads: np.ndarray, cameras: list[Camera],
                      catalog: StarCatalog, search_px: float, radius_px: float, regions: int = 1,
                      refine: int = 10) -> Verdict:
    """A hypothesis refined at ``search_px``, then paired and refined at ``radius_px``, with ``p_false`` the bound
    ``regions * H_2 * P(X >= m - 2)`` that holds whatever search found it (see the module docstring)."""
    coarse = verify(attitude, body, heads, cameras, catalog, search_px, 2, refine)
    v = verify(coarse.attitude, body, heads, cameras, catalog, radius_px, 2, refine)
    pixel = max(1.0 / min(cam.fx, cam.fy) for cam in cameras)
    hypotheses = regions * pair_hypotheses(body, catalog.unit[v.field], 2.0 * radius_px * pixel)
    v.hypotheses = float(max(hypotheses, 1))
    v.p_false = false_match_probability(v.detections, v.matched, v.p_match, 2, v.hypotheses)
    return v
