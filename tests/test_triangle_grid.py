"""Triangle and grid identifiers (paper 002's comparators) and hypothesis verification, on projected catalogue stars."""

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from starenv.agents.base import StarMeasurements
from starenv.agents.identify.geometry import body_vectors
from starenv.agents.identify.grid import GridIdentifier, pattern_cells
from starenv.agents.identify.triangle import TriangleIdentifier
from starenv.agents.identify.verify import verify
from starenv.sim.conventions import pointing, radec_to_unit
from starenv.sim.optics import Camera
from starenv.sim.sky import load_catalog

CAM = Camera.from_fov(12.0, 128, 128, pixel_pitch_m=96e-6)


@pytest.fixture(scope="module")
def catalog():
    return load_catalog(6.5, 2026.0)


@pytest.fixture(scope="module")
def agents(catalog):
    out = {"triangle": TriangleIdentifier(), "grid": GridIdentifier()}
    for agent in out.values():
        agent.reset([CAM], catalog)
    return out


def _frame(catalog, attitude, mag=6.5, noise_px=0.1, seed=0):
    """The catalogue stars brighter than ``mag`` in the field, projected with Gaussian centroid noise."""
    cam_rot = CAM.mounting * attitude
    rows = catalog.cone(cam_rot.inv().apply([0, 0, 1]), CAM.half_diagonal)
    rows = rows[catalog.magnitude[rows] <= mag]
    xy, front = CAM.project(cam_rot.apply(catalog.unit[rows]))
    inside = front & CAM.in_frame(xy)
    rng = np.random.default_rng(seed)
    xy = xy[inside] + rng.normal(0, noise_px, (inside.sum(), 2))
    return StarMeasurements(xy, flux=10.0 ** (-0.4 * catalog.magnitude[rows[inside]])), catalog.hip[rows[inside]]


# Sparse fields away from the Milky Way (the grid algorithm's orientation star is unreliable in dense ones)
POINTINGS = [(30.0, 40.0, 10.0), (150.0, -20.0, 200.0), (200.0, 60.0, 95.0), (250.0, 10.0, 300.0)]


@pytest.mark.parametrize("name", ["triangle", "grid"])
@pytest.mark.parametrize("ra, dec, roll", POINTINGS)
def test_identifies_projected_catalogue_stars(agents, catalog, name, ra, dec, roll):
    attitude = pointing(math.radians(ra), math.radians(dec), math.radians(roll))
    stars, truth = _frame(catalog, attitude)
    ids = agents[name].identify([stars], [CAM], None)[0].catalog_id
    known = ids >= 0
    assert known.sum() >= 0.8 * len(ids)
    np.testing.assert_array_equal(ids[known], truth[known])


@pytest.mark.parametrize("name", ["triangle", "grid"])
def test_random_points_are_not_identified(agents, name):
    rng = np.random.default_rng(1)
    for _ in range(3):
        stars = StarMeasurements(rng.uniform(0, 127, (15, 2)), flux=rng.uniform(1, 10, 15))
        assert (agents[name].identify([stars], [CAM], None)[0].catalog_id == -1).all()


def test_verify_counts_pairs_and_false_match_probability(catalog):
    attitude = pointing(math.radians(30.0), math.radians(40.0), 0.3)
    stars, truth = _frame(catalog, attitude)
    body, heads = body_vectors([stars], [CAM])
    good = verify(attitude, body, heads, [CAM], catalog, radius_px=2.0)
    np.testing.assert_array_equal(good.ids, truth)
    assert good.matched == len(truth) and good.p_false < 1e-12
    assert (good.attitude * attitude.inv()).magnitude() < math.radians(0.05)  # 0.1 px noise, ~6 arcmin px
    far = verify(Rotation.from_rotvec([0, 0.2, 0]) * attitude, body, heads, [CAM], catalog, radius_px=2.0)
    assert far.matched <= 2 and far.p_false > 1e-3


def test_grid_pattern_is_roll_invariant():
    centre = radec_to_unit(np.radians(30.0), np.radians(40.0))
    rng = np.random.default_rng(2)
    neighbours = centre + rng.normal(0, 0.03, (12, 3))
    neighbours /= np.linalg.norm(neighbours, axis=1, keepdims=True)
    cells, k = pattern_cells(centre, neighbours, math.radians(6), math.radians(0.3), 20)
    turned = Rotation.from_rotvec(centre * 1.234)
    cells2, k2 = pattern_cells(centre, turned.apply(neighbours), math.radians(6), math.radians(0.3), 20)
    assert k == k2 and np.array_equal(cells, cells2) and len(cells) >= 8
