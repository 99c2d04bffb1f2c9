"""The false-match bound of the shared verification (:mod:`starenv.agents.identify.verify`): its chance of a pair
against Monte Carlo of random star fields, the two-pair hypothesis count against brute force, the bound as a bound
(wrong attitudes on random fields reach it no more often than it says), and wrong hypotheses of a rendered paper 002
frame (a flipped roll, a wrong main star) refused; the scatter of directions predicted by a fitted attitude against
Monte Carlo, and the heads whose matches a loose roll leaves to chance."""

import itertools
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from starenv.agents.blocks import wahba_svd
from starenv.agents.identify.verify import (
    anchor_head,
    false_match_probability,
    pair_hypotheses,
    predicted_scatter,
    unconfirmed_heads,
    verify,
    verify_any_search,
)
from starenv.sim.conventions import pointing
from starenv.sim.optics import Camera
from starenv.sim.sky import StarCatalog

CAM = Camera.from_fov(12.0, 128, 128, 96e-6)  # paper 002's field on the 128 px sensor of the shipped weights
PIXEL = 1.0 / CAM.fx  # rad/px


def _random_sky(rng, stars_per_field: float) -> StarCatalog:
    """A Poisson field of stars, uniform on the sphere's cap of 15 deg about +Z (beyond the field's corners), with
    ``stars_per_field`` stars on average in the 128 x 128 px frame."""
    cap = math.radians(15.0)
    frame_sr = CAM.width * CAM.height * PIXEL**2
    count = rng.poisson(stars_per_field / frame_sr * 2.0 * math.pi * (1.0 - math.cos(cap)))
    z = 1.0 - rng.uniform(size=count) * (1.0 - math.cos(cap))
    a = rng.uniform(0.0, 2.0 * math.pi, count)
    s = np.sqrt(1.0 - z**2)
    unit = np.column_stack([s * np.cos(a), s * np.sin(a), z])
    return StarCatalog(hip=np.arange(1, count + 1), magnitude=np.full(count, 5.0), unit=unit, epoch=2026.0)


def _random_detections(rng, n: int, margin_px: float) -> np.ndarray:
    """Body vectors of ``n`` detections uniform on the frame, ``margin_px`` from its edges (a disc of that radius
    about each lies on the frame)."""
    xy = rng.uniform(margin_px - 0.5, CAM.width - 0.5 - margin_px, (n, 2))
    return CAM.unproject(xy)


def test_chance_pairs_of_a_wrong_attitude_follow_the_binomial_of_the_field_density():
    # A wrong attitude looks at a patch of sky unrelated to the detections: the number of detections it pairs within
    # r is Binomial(n, p), p the field's stars times pi r^2 over the frame's area (verify's p, per field).  The
    # closed form, averaged over the fields drawn, against the fraction of fields with k or more pairs.
    rng = np.random.default_rng(29)
    attitude = pointing(0.0, math.pi / 2.0, 0.0)  # boresight +Z
    n, radius, trials = 30, 2.0, 4000
    heads = np.zeros(n, dtype=np.int64)
    hits, expected = np.zeros((trials,), dtype=np.int64), {k: 0.0 for k in (1, 2, 3, 4)}
    for t in range(trials):
        sky = _random_sky(rng, 40.0)
        v = verify(attitude, _random_detections(rng, n, radius), heads, [CAM], sky, radius, refine=0)
        assert v.p_match == pytest.approx(len(v.field) * math.pi * radius**2 / (CAM.width * CAM.height))
        hits[t] = v.matched
        for k in expected:
            expected[k] += false_match_probability(n, k, v.p_match) / trials
    for k, tail in expected.items():
        assert abs(np.mean(hits >= k) - tail) <= 4.0 * math.sqrt(tail * (1.0 - tail) / trials) + 0.01 * tail


def test_pair_hypotheses_count_the_agreeing_pairs_one_by_one():
    rng = np.random.default_rng(7)
    body = _random_detections(rng, 9, 0.0)
    reference = Rotation.from_rotvec([0.01, -0.02, 0.3]).apply(_random_detections(rng, 12, 0.0))
    tolerance = 3.0 * PIXEL
    brute = sum(abs(_angle(body[i], body[j]) - _angle(reference[a], reference[b])) <= tolerance
                for i, j in itertools.combinations(range(len(body)), 2)
                for a, b in itertools.permutations(range(len(reference)), 2))
    assert brute > 0
    assert pair_hypotheses(body, reference, tolerance) == brute
    assert pair_hypotheses(body[:1], reference, tolerance) == 0


ALPHAS = (0.01, 0.05, 0.2)


def test_verification_of_wrong_attitudes_reaches_the_bound_no_more_often_than_it_says():
    # Random detections against random fields: every attitude is wrong.  A valid bound is a p-value: it falls to
    # alpha or below in at most a fraction alpha of the fields (plus Monte Carlo error), refinement included.
    rng = np.random.default_rng(2029)
    n, trials = 12, 400
    heads = np.zeros(n, dtype=np.int64)
    bounded = []
    for _ in range(trials):
        sky = _random_sky(rng, 150.0)  # dense: refinement finds chance pairs to grow from
        attitude = pointing(0.0, math.pi / 2.0, rng.uniform(0.0, 2.0 * math.pi))
        v = verify_any_search(attitude, _random_detections(rng, n, 0.0), heads, [CAM], sky, 2.0, 1.0)
        bounded.append(v.p_false)
    for alpha in ALPHAS:
        assert np.mean(np.array(bounded) <= alpha) <= alpha + 3.0 * math.sqrt(alpha * (1.0 - alpha) / trials)


def test_the_two_pair_bound_holds_against_the_best_of_every_two_pair_hypothesis():
    # "Whatever the search": every attitude fixed by two (detection, star) pairs whose separations agree within 2 r
    # is tried on random fields, and the one pairing most detections (within r of a star, one star each) kept.  The
    # bound H_2 P(X >= m - 2), X ~ Binomial(n - 2, p), of that best one falls to alpha in at most a fraction alpha of
    # the fields; scored as one hypothesis (H = 1) it does so far more often: the count is what makes it a bound.
    rng = np.random.default_rng(292)
    n, radius, trials = 10, 1.0, 150
    area = CAM.width * CAM.height
    bounded, single = [], []
    for _ in range(trials):
        sky = _random_sky(rng, 40.0)
        xy, front = CAM.project(sky.unit)
        field = sky.unit[front & CAM.in_frame(xy)]
        det_xy = rng.uniform(-0.5, CAM.width - 0.5, (n, 2))
        body = CAM.unproject(det_xy)
        p = len(field) * math.pi * radius**2 / area
        i, j = np.triu_indices(n, 1)
        a, b = (x.ravel() for x in np.meshgrid(np.arange(len(field)), np.arange(len(field)), indexing="ij"))
        a, b = a[a != b], b[a != b]
        gap = np.abs(_angles(body[i], body[j])[:, None] - _angles(field[a], field[b])[None, :])
        pair, star_pair = np.nonzero(gap <= 2.0 * radius * PIXEL)
        turns = wahba_svd(np.stack([body[i[pair]], body[j[pair]]], axis=1),
                          np.stack([field[a[star_pair]], field[b[star_pair]]], axis=1))  # (k, 3, 3)
        star_xy, ahead = CAM.project((field @ turns.transpose(0, 2, 1)).reshape(-1, 3))
        star_xy = np.where(ahead[:, None], star_xy, np.inf).reshape(len(turns), len(field), 2)
        # Detections with a star within r: at least the one-star-each pairs, so the best is not undercounted.
        near = np.linalg.norm(det_xy[None, :, None] - star_xy[:, None], axis=3) <= radius
        best = int(near.any(axis=2).sum(axis=1).max(initial=0))
        hypotheses = pair_hypotheses(body, field, 2.0 * radius * PIXEL)
        bounded.append(false_match_probability(n, best, p, 2, max(hypotheses, 1)))
        single.append(false_match_probability(n, best, p, 2))
    bounded, single = np.array(bounded), np.array(single)
    for alpha in ALPHAS:
        assert np.mean(bounded <= alpha) <= alpha + 3.0 * math.sqrt(alpha * (1.0 - alpha) / trials)
    assert np.mean(single <= ALPHAS[0]) > 20 * ALPHAS[0]


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * math.asin(min(1.0, float(np.linalg.norm(a - b)) / 2.0))


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return 2.0 * np.arcsin(np.minimum(1.0, np.linalg.norm(a - b, axis=1) / 2.0))


def _tangent_noise(rng, vectors: np.ndarray, sigma: float) -> np.ndarray:
    """``vectors`` (n, 3) moved by Gaussian noise of ``sigma`` rad on each of the two axes across them, renormalised."""
    noisy = vectors + rng.normal(0.0, sigma, vectors.shape)
    noisy -= np.sum(noisy * vectors, axis=1, keepdims=True) * vectors - vectors  # (drop the radial part)
    return noisy / np.linalg.norm(noisy, axis=1, keepdims=True)


def _cluster(rng, axis: np.ndarray, count: int, radius_deg: float) -> np.ndarray:
    """``count`` unit vectors uniform within ``radius_deg`` of ``axis``."""
    rotation = Rotation.align_vectors([axis], [[0.0, 0.0, 1.0]])[0]
    r = math.radians(radius_deg) * np.sqrt(rng.uniform(size=count))
    a = rng.uniform(0.0, 2.0 * math.pi, count)
    return rotation.apply(np.column_stack([np.sin(r) * np.cos(a), np.sin(r) * np.sin(a), np.cos(r)]))


@pytest.mark.parametrize("spread_deg, seed", [(3.0, 1), (40.0, 2)])
def test_predicted_scatter_is_that_of_the_fitted_attitude_over_noisy_fits(spread_deg, seed):
    # A small cluster leaves the roll about it loose (a far direction's scatter many times its own noise), a wide one
    # does not.  The covariance sigma^2 (sum (I - b b'))^-1 is the first-order one of Wahba's problem with
    # equal weights; over 4000 noisy fits the mean squared displacement of each direction matches it within 10 %
    # (a mean of 4000 draws of a squared Gaussian has a relative sigma of sqrt(2 / 4000), about 2 %).
    rng = np.random.default_rng(seed)
    sigma = 1e-4
    basis = _cluster(rng, np.array([0.0, 0.0, 1.0]), 6, spread_deg)
    directions = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, math.sqrt(0.5), math.sqrt(0.5)]])
    predicted = np.array(predicted_scatter(basis, sigma**-2, directions))
    displaced = np.zeros(len(directions))
    for _ in range(4000):
        fitted = wahba_svd(_tangent_noise(rng, basis, sigma), basis)  # the attitude fitted on noisy detections
        displaced += np.sum((directions @ fitted.T - directions) ** 2, axis=1)
    np.testing.assert_allclose(displaced / 4000, predicted, rtol=0.1)
    weights = np.full(len(basis), sigma**-2)  # the per-vector form gives the same
    np.testing.assert_allclose(predicted_scatter(basis, weights, directions), predicted, rtol=1e-12)


def _two_heads(rng, anchor_spread_deg: float, far_count: int):
    """An anchor head of 5 detections within ``anchor_spread_deg`` of +Z and a far head of ``far_count`` about +X."""
    body = np.vstack([_cluster(rng, np.array([0.0, 0.0, 1.0]), 5, anchor_spread_deg),
                      _cluster(rng, np.array([1.0, 0.0, 0.0]), far_count, 3.0)])
    return body, np.repeat([0, 1], [5, far_count])


SIGMA, RADIUS, CHANCE, THRESHOLD = 1e-4, 6e-4, 5e-4, 1e-5  # rad (0.5 px, 3 px at 42"/px), p per detection, bound


@pytest.mark.parametrize("far_matched, held_back", [(1, True), (2, True), (3, False), (6, False)])
def test_a_far_head_under_a_loose_roll_is_held_back_unless_its_matches_are_too_many_for_chance(far_matched,
                                                                                               held_back):
    # Anchor of 5 within 3 deg: the roll about it is loose, the far head's 3 sigma reach about 7 match radii (about
    # 7 rolls searched).  Its k of 6 detections matching by chance at one of them: 7 P(X >= k), X ~ Binomial(6, 5e-4):
    # about 2e-2 for k = 1 and 2.7e-5 for k = 2 (over the 1e-5 bound), 2e-8 for k = 3: held back for 1 and 2.
    body, head = _two_heads(np.random.default_rng(3), 3.0, 6)
    matched = np.concatenate([np.arange(5), 5 + np.arange(far_matched)])
    radius2 = np.full(2, RADIUS**2)
    reach2 = 9.0 * max(predicted_scatter(body[:5], SIGMA**-2, body[5:]))
    assert reach2 > 25 * RADIUS**2  # (the trap: a search several radii wide)
    out = unconfirmed_heads(body, head, matched, 0, SIGMA**-2, radius2, np.full(2, CHANCE), THRESHOLD)
    assert out == ([1] if held_back else [])


def test_a_far_head_the_anchor_predicts_keeps_a_single_match_and_a_head_with_none_is_held_back_only_when_loose():
    # An anchor of 5 spread over 40 deg pins the roll: the far head's 3 sigma lies within the match radius, and its
    # one match (or none) is as good as the anchor's.  With the anchor in 3 deg, a head with no match is held back
    # too (its detections are not to be labelled through a radius wider than the search's).
    body, head = _two_heads(np.random.default_rng(4), 40.0, 6)
    radius2 = np.full(2, RADIUS**2)
    assert 9.0 * max(predicted_scatter(body[:5], SIGMA**-2, body[5:])) < RADIUS**2
    for matched in (np.arange(6), np.arange(5)):
        assert unconfirmed_heads(body, head, matched, 0, SIGMA**-2, radius2, np.full(2, CHANCE), THRESHOLD) == []
    body, head = _two_heads(np.random.default_rng(4), 3.0, 6)
    assert unconfirmed_heads(body, head, np.arange(5), 0, SIGMA**-2, radius2, np.full(2, CHANCE), THRESHOLD) == [1]


def test_two_far_heads_under_one_loose_roll_are_tested_together():
    # Heads about +X (2 of 6 matched) and +Y (1 of 6), about 7 rolls searched: each alone could be chance (7 P(X >= 2)
    # about 2.5e-5, 7 P(X >= 1) about 2e-2), but one roll moves both, and 3 matches among their 12 detections at one
    # of its rolls are not (about 2e-7).  With no match in the +Y head (2 of 12, about 1.1e-4) both are held back.
    rng = np.random.default_rng(5)
    body = np.vstack([_cluster(rng, np.array(axis), count, 3.0)
                      for axis, count in (([0.0, 0.0, 1.0], 5), ([1.0, 0.0, 0.0], 6), ([0.0, 1.0, 0.0], 6))])
    head = np.repeat([0, 1, 2], [5, 6, 6])
    args = (0, SIGMA**-2, np.full(3, RADIUS**2), np.full(3, CHANCE), THRESHOLD)
    assert unconfirmed_heads(body, head, np.array([0, 1, 2, 3, 4, 5, 6, 11]), *args) == []
    assert unconfirmed_heads(body, head, np.array([0, 1, 2, 3, 4, 5, 6]), *args) == [1, 2]


def test_the_anchor_is_the_head_with_most_matches_and_of_equals_the_one_with_fewest_detections():
    # Heads of 4, 22 and 25 detections.  A head needs three matches to fix the attitude alone.
    head = np.repeat([2, 1, 0], [4, 22, 25])[::-1].copy()  # (head 0 first: 25, then 22, then 4)
    first = {h: int(np.flatnonzero(head == h)[0]) for h in range(3)}
    matched = np.array([first[1] + k for k in range(4)] + [first[2] + k for k in range(4)] + [first[0]])
    assert anchor_head(head, np.sort(matched)) == 2  # 4 and 4: the head of 4 detections, not the first
    assert anchor_head(head, np.sort(np.append(matched, first[1] + 4))) == 1  # 5 against 4
    assert anchor_head(head, np.array([first[0], first[1], first[1] + 1, first[2]])) is None
