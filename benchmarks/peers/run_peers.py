"""cedar-solve and tetra3rs on the centroid sets of ``benchmarks/identify_peers.py``; runs in the peers' own virtual
environment (numpy < 2), so it imports nothing of starenv.

    python run_peers.py SETS.npz RESULT.json [--sync READ_FD WRITE_FD CHUNK]

SETS.npz holds flat per-centroid arrays ``xy`` (px, (0, 0) the centre of the top-left pixel, +x right, +y down),
``xy_clean`` (the same without noise), ``flux`` and ``unit_cedar``, ``unit_tetra3rs`` (the true stars' ICRS unit
vectors at the epoch of each peer's catalogue), cut into sets by ``sizes``; per set the true and the prior attitude
(``attitude``, ``prior``: inertial -> camera matrices, camera +x along columns, +y along rows, +z the boresight) and
the prior's error ``prior_error_deg``; the sensor (``width``, ``height``, ``fov_deg`` across columns,
``half_diagonal`` rad); the tracking sets ``track`` (cut to their ``track_stars`` brightest), the noise-free
convention-check sets ``check`` and the scoring tolerances.  RESULT.json gets, per peer, its database, build or load
time, the convention check and per-set rows [centroids, correct, wrong, solved, latency s] for lost in space (all
sets) and tracking (tetra3rs only; its hint uncertainty is the prior's error).

With ``--sync`` tetra3rs's lost-in-space timing goes in lockstep with starenv's (``identify_peers.py``): once
everything before it is done the run writes a byte to WRITE_FD; then, for every CHUNK sets, it waits for a byte on
READ_FD, times those sets and writes a byte back (none after a last chunk of fewer sets).

Conventions (checked on the noise-free sets every run): cedar-solve takes (y, x) from the top-left corner of the
image (pixel centres at +0.5) and returns RA, Dec and roll of a frame with +x the boresight, +y image left, +z image
up; tetra3rs takes (x, y) from the image centre and returns an inertial -> camera matrix with starenv's axes.
"""

from __future__ import annotations

import json
import logging
import os
import sys
import time

import numpy as np
from scipy.spatial import cKDTree

ARCSEC = np.pi / 180.0 / 3600.0


def unit_vectors(ra_deg, dec_deg) -> np.ndarray:
    """ICRS unit vectors (n, 3) of RA and Dec in degrees."""
    ra, dec = np.radians(ra_deg), np.radians(dec_deg)
    return np.stack([np.cos(dec) * np.cos(ra), np.cos(dec) * np.sin(ra), np.sin(dec)], axis=-1).reshape(-1, 3)


def cedar_matrix(ra_deg: float, dec_deg: float, roll_deg: float) -> np.ndarray:
    """Inertial -> camera matrix (starenv's camera axes) of cedar-solve's RA, Dec and roll (its Euler angles)."""
    ra, dec, roll = np.radians([ra_deg, dec_deg, roll_deg])
    about_z = np.array([[np.cos(ra), np.sin(ra), 0.0], [-np.sin(ra), np.cos(ra), 0.0], [0.0, 0.0, 1.0]])
    about_y = np.array([[np.cos(dec), 0.0, np.sin(dec)], [0.0, 1.0, 0.0], [-np.sin(dec), 0.0, np.cos(dec)]])
    about_x = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(roll), np.sin(roll)], [0.0, -np.sin(roll), np.cos(roll)]])
    boresight, left, up = about_x @ about_y @ about_z
    return np.stack([-left, -up, boresight])


def attitude_errors(estimate: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """Boresight direction error and roll error about it (rad) of an inertial -> camera matrix (tetra3rs's is
    orthonormal to about 1e-7 only, so no arccos of a dot product)."""
    boresight = np.arctan2(np.linalg.norm(np.cross(estimate[2], truth[2])), estimate[2] @ truth[2])
    error = estimate @ truth.T
    return float(boresight), float(abs(np.arctan2(error[0, 1] - error[1, 0], error[0, 0] + error[1, 1])))


class Sets:
    """The centroid sets and their truth for one peer (``unit_<peer>`` are the true star directions)."""

    def __init__(self, path: str, peer: str):
        data = np.load(path)
        self.data = data
        cuts = np.cumsum(data["sizes"])[:-1]
        self.xy, self.clean = np.split(data["xy"], cuts), np.split(data["xy_clean"], cuts)
        self.flux, self.unit = np.split(data["flux"], cuts), np.split(data[f"unit_{peer}"], cuts)
        self.size = (int(data["height"]), int(data["width"]))
        self.fov_deg = float(data["fov_deg"])
        self.corner_sine = float(np.sin(data["half_diagonal"]))
        self.solved_rad = float(data["solved_arcsec"]) * ARCSEC
        self.id_rad = float(data["id_tolerance_arcsec"]) * ARCSEC

    def row(self, index: int, stars: int, matches, estimate, latency: float) -> list:
        """[centroids, correct, wrong, solved, latency s]; ``matches`` (centroid rows, catalogue unit vectors)."""
        rows, catalog = matches
        close = np.linalg.norm(self.unit[index][rows] - catalog, axis=1) <= 2.0 * np.sin(self.id_rad / 2.0)
        solved = False
        if estimate is not None:
            boresight, roll = attitude_errors(estimate, self.data["attitude"][index])
            solved = boresight <= self.solved_rad and roll * self.corner_sine <= self.solved_rad
        return [stars, int(close.sum()), int((~close).sum()), bool(solved), latency]

    def check(self, solve, read) -> str:
        """Median and largest boresight and roll errors of a peer on the noise-free sets."""
        errors = []
        for i in self.data["check"]:
            estimate, _ = read(solve(self.clean[i], self.flux[i]), self.clean[i])
            if estimate is not None:
                errors.append(attitude_errors(estimate, self.data["attitude"][i]))
        if not errors:
            return "no noise-free set solved"
        e = np.array(errors) / ARCSEC
        return (f"{len(e)}/{len(self.data['check'])} solved, boresight error median {np.median(e[:, 0]):.2f}\" "
                f"max {e[:, 0].max():.2f}\", roll error median {np.median(e[:, 1]):.1f}\" max {e[:, 1].max():.1f}\"")

    def rows(self, solve, read, indices, stars=None, priors=None, lockstep=None) -> list[list]:
        """Per-set rows of a peer: ``solve(xy, flux[, prior])`` is the timed call (one untimed call first),
        ``read(result, xy) -> (estimate, matches)`` its answer; ``lockstep`` (:class:`Lockstep`), if given, paces
        the timing."""
        priors = [()] * len(indices) if priors is None else [(p,) for p in priors]
        cut = slice(stars)
        solve(self.xy[indices[0]][cut], self.flux[indices[0]][cut], *priors[0])
        if lockstep is not None:
            lockstep.ready()
        out = []
        for k, (i, prior) in enumerate(zip(indices, priors, strict=True)):
            if lockstep is not None:
                lockstep.before(k)
            xy = self.xy[i][cut]
            start = time.perf_counter()
            result = solve(xy, self.flux[i][cut], *prior)
            latency = time.perf_counter() - start
            estimate, matches = read(result, xy)
            out.append(self.row(i, len(xy), matches, estimate, latency))
        if lockstep is not None:
            lockstep.end(len(indices))
        return out


NO_MATCHES = (np.zeros(0, dtype=int), np.zeros((0, 3)))


class Lockstep:
    """Takes turns with the caller over two pipes (see the module docstring): a byte out when ready and after each
    whole chunk, a byte in before each chunk."""

    def __init__(self, read_fd: int, write_fd: int, chunk: int):
        self.read, self.write, self.chunk = os.fdopen(read_fd, "rb", buffering=0), os.fdopen(write_fd, "wb",
                                                                                             buffering=0), chunk

    def ready(self) -> None:
        self.write.write(b"d")

    def before(self, k: int) -> None:
        """Before set ``k``: at a chunk's end say so, at a chunk's start wait for the go."""
        if k and k % self.chunk == 0:
            self.write.write(b"d")
        if k % self.chunk == 0 and self.read.read(1) != b"g":
            raise RuntimeError("the caller of the lockstep went away")

    def end(self, count: int) -> None:
        """After the last set: a whole last chunk is answered."""
        if count % self.chunk == 0:
            self.write.write(b"d")


def cedar(sets: Sets) -> dict:
    """cedar-solve with its default database (it builds others only from catalogue files it would download)."""
    logging.getLogger("tetra3.Tetra3").addHandler(logging.NullHandler())  # keeps its constructor's chatter off
    import tetra3

    start = time.perf_counter()
    solver = tetra3.Tetra3("default_database")
    load_s = time.perf_counter() - start
    props = solver.database_properties

    def solve(xy, flux):
        return solver.solve_from_centroids(xy[:, ::-1] + 0.5, sets.size, fov_estimate=sets.fov_deg,
                                           return_matches=True)

    def read(result, xy):
        if result["RA"] is None:
            return None, NO_MATCHES
        _, rows = cKDTree(xy[:, ::-1] + 0.5).query(np.asarray(result["matched_centroids"]).reshape(-1, 2))
        stars = np.asarray(result["matched_stars"]).reshape(-1, 3)
        return cedar_matrix(result["RA"], result["Dec"], result["Roll"]), (rows, unit_vectors(stars[:, 0], stars[:, 1]))

    return {
        "database": (f"default database: {props['num_patterns']} patterns, {len(solver.star_table)} stars "
                     f"({props['star_catalog']}, mag <= {props['star_max_magnitude']:.2f}, epoch "
                     f"{props['epoch_proper_motion']:g}), fields "
                     f"{props['min_fov']:g}-{props['max_fov']:g} deg"),
        "build": "loaded",
        "build_s": load_s,
        "check": sets.check(solve, read),
        "lis": sets.rows(solve, read, np.arange(len(sets.xy))),
    }


def tetra3rs_peer(sets: Sets, lockstep: Lockstep | None = None) -> dict:
    """tetra3rs with a database built for the sets' field from its bundled Gaia + Hipparcos catalogue; its
    lost-in-space timing paced by ``lockstep`` if given."""
    import tetra3rs

    start = time.perf_counter()
    db = tetra3rs.SolverDatabase.generate_from_gaia(max_fov_deg=sets.fov_deg)
    build_s = time.perf_counter() - start
    params = db.parameters
    height, width = sets.size
    centre = np.array([(width - 1) / 2.0, (height - 1) / 2.0])
    prior_error_deg = float(sets.data["prior_error_deg"])

    def solve(xy, flux, prior=None):
        hint = {} if prior is None else {"attitude_hint": prior, "hint_uncertainty_deg": prior_error_deg}
        return db.solve_from_centroids(np.column_stack([xy - centre, flux]), fov_estimate_deg=sets.fov_deg,
                                       image_width=width, image_height=height, **hint)

    def read(result, xy):
        if not result:
            return None, NO_MATCHES
        stars = [db.get_star_by_id(int(i)) for i in result.matched_catalog_ids]
        catalog = unit_vectors([s.ra_deg for s in stars], [s.dec_deg for s in stars])
        return result.rotation_matrix_icrs_to_camera, (result.matched_centroids.astype(int), catalog)

    lis = sets.rows(solve, read, np.arange(len(sets.xy)), lockstep=lockstep)
    track, tracking = sets.data["track"], []
    if len(track):
        tracking = sets.rows(solve, read, track, int(sets.data["track_stars"]), sets.data["prior"][track])
    return {
        "database": (f"{params['num_patterns']} patterns, {params['num_stars']} stars (Gaia G <= "
                     f"{params['star_max_magnitude']:.2f}), field {params['max_fov_deg']:.2f} deg"),
        "build": "built",
        "build_s": build_s,
        "check": sets.check(solve, read),
        "lis": lis,
        "tracking": tracking,
    }


def main() -> None:
    path = sys.argv[1]
    lockstep = None
    if len(sys.argv) > 3 and sys.argv[3] == "--sync":
        lockstep = Lockstep(int(sys.argv[4]), int(sys.argv[5]), int(sys.argv[6]))
    result = {"cedar-solve": cedar(Sets(path, "cedar")), "tetra3rs": tetra3rs_peer(Sets(path, "tetra3rs"), lockstep)}
    with open(sys.argv[2], "w") as out:
        json.dump(result, out)


if __name__ == "__main__":
    main()
