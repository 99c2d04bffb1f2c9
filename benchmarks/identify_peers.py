"""Peer comparison of star identification on identical centroid sets: starenv's lost-in-space and tracking
identifiers beside cedar-solve 0.5.1 and tetra3rs 0.14.0.

Goals: lost-in-space per-star ID rate >= cedar-solve's and tetra3rs's, no false id; median lost-in-space latency
<= 1x tetra3rs's; tracking <= 1 ms for 30 stars.

Sets: random attitudes (uniform on the sky, uniform roll) of one camera (default paper 002's 1024 x 1024 px, f 58.5 mm,
12 um, 12 deg field; ``--fov 20`` a 20 deg one with the same sensor), the stars of the Hipparcos-2 catalogue down to
``--mag-limit`` (default 6.5 at 12 deg, as paper 002's scenario, and 5.5 at 20 deg; the run prints the stars a set)
at epoch 2025.0, projected by the ideal pinhole; a star within ``BLEND_PX`` of a brighter one is dropped (the sensor
sees one spot), 0.3 px Gaussian noise (``--noise``) is added to each coordinate, stars off the sensor are dropped,
the rest are ordered brightest first.  Every method solves the same sets; the peers run in their own virtual environment
(``.peers-venv`` in the repository root, made on the first run; they pin numpy < 2) through
``benchmarks/peers/run_peers.py``, which also checks their pixel conventions on noise-free copies of the first sets.

Scores, over all sets: per-star ID rate = correctly labelled centroids / all centroids; false-ID rate = wrongly
labelled centroids / all centroids.  starenv's labels are HIP numbers, right when they are the true star's; a peer's
label (its own catalogue) is right when the matched catalogue direction is within ``ID_TOLERANCE_ARCSEC`` of the
true star's at the epoch of that catalogue's positions (``PEER_EPOCHS``: cedar-solve's default database is propagated
to 2024.0; tetra3rs's bundled positions stay close to Gaia's 2016.0 whatever epoch its database is built for, so
fast stars would otherwise count as wrong).  A set is solved by starenv with >= 3 correct labels and none wrong; by a
peer when its attitude puts the boresight within ``SOLVED_ARCSEC`` of the truth and its roll error moves the sensor's
corners by no more than that.  Latency is the wall time of one call (median, 95th percentile), databases built or
loaded before.  starenv's and tetra3rs's lost-in-space calls take turns (cedar-solve, far slower, runs before them):
starenv times ``--lockstep`` sets, then tetra3rs the same sets, and so on, so that both see the machine in the same
state (the speed of a shared machine drifts within seconds).  The turn's length sets how warm the caches are: a
star tracker identifies once a frame between other work, so each call starts colder than in a long run of calls;
``--lockstep 2`` is close to that, ``--lockstep 50`` close to a run of calls.  Tracking gets a prior 0.05 deg off
the truth (random axis) on the sets with at least 30 stars, cut to their 30 brightest.

    python benchmarks/identify_peers.py [--sets N] [--fov {12,20}] [--mag-limit MAG] [--seed S] [--repeats R]
                                        [--noise PX] [--blend-px PX] [--lockstep N] [--json PATH]

Each of the ``--repeats`` runs (default 3) draws its own sets, from seeds ``--seed``, ``--seed`` + 1, ... (default
3400: no test draws from these), and times every method on them; the run prints each run's table and then every
ratio's median and range over the runs.  ``--blend-px 0`` keeps the stars a brighter one would blend with (pairs
the sensor could not split, each a detection of its own).

The tracking sweep (wrong ids with priors up to the gate's reach, 10 000 sets a case) is
``benchmarks/tracking_robustness.py``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from unittest import mock

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from starenv.agents.base import StarMeasurements
from starenv.agents.identify.lost_in_space import LostInSpaceIdentifier
from starenv.agents.identify.tracking import TrackingIdentifier
from starenv.sim.conventions import DEG, pointing
from starenv.sim.optics import Camera
from starenv.sim.sky import load_catalog

REPO = Path(__file__).resolve().parent.parent
VENV = REPO / ".peers-venv"
PEERS = ("cedar-solve==0.5.1", "tetra3rs==0.14.0")
RUNNER = Path(__file__).resolve().parent / "peers" / "run_peers.py"
EPOCH = 2025.0
NOISE_PX = 0.3
BLEND_PX = 3.0
PRIOR_ERROR_DEG = 0.05
SEED = 3400  # default seed of the first repeat (no test draws from it)
TRACK_STARS = 30
CHECK_SETS = 10  # noise-free sets for the peers' convention check
LOCKSTEP_SETS = 10  # default turn: starenv and tetra3rs take turns timing this many lost-in-space sets
SOLVED_ARCSEC = 60.0
ID_TOLERANCE_ARCSEC = 10.0
PEER_EPOCHS = {"cedar": 2024.0, "tetra3rs": 2016.0}
MAG_LIMIT = {12: 6.5, 20: 5.5}


def make_camera(fov_deg: int) -> Camera:
    """Paper 002's head (12 deg) or the same sensor behind a 20 deg lens."""
    if fov_deg == 12:
        return Camera.from_focal_length(58.5e-3, 12e-6, 1024, 1024)
    return Camera.from_fov(float(fov_deg), 1024, 1024, 12e-6)


def make_sets(
    camera: Camera, mag_limit: float, count: int, rng: np.random.Generator, noise_px: float = NOISE_PX,
    blend_px: float = BLEND_PX,
) -> dict:
    """``count`` centroid sets with their truth, as flat arrays (see the module docstring and run_peers.py), with
    ``noise_px`` Gaussian noise on each coordinate; a star within ``blend_px`` of a brighter one is dropped."""
    catalog = load_catalog(mag_limit, EPOCH)
    peer_units = {peer: load_catalog(mag_limit, epoch).unit for peer, epoch in PEER_EPOCHS.items()}  # same rows
    sizes, xy, clean, flux, unit, hip, attitudes = [], [], [], [], [], [], []
    for _ in range(count):
        ra, dec, roll = rng.uniform(0.0, 2 * np.pi), np.arcsin(rng.uniform(-1.0, 1.0)), rng.uniform(0.0, 2 * np.pi)
        attitude = pointing(ra, dec, roll).as_matrix()  # inertial -> camera
        rows = catalog.cone(attitude[2], camera.half_diagonal)
        rows = rows[np.argsort(catalog.magnitude[rows], kind="stable")]
        true_xy, front = camera.project(catalog.unit[rows] @ attitude.T)
        rows, true_xy = rows[front], true_xy[front]
        blended = {j for _, j in cKDTree(true_xy).query_pairs(blend_px)} if len(rows) > 1 and blend_px > 0 else set()
        keep = np.setdiff1d(np.arange(len(rows)), list(blended))
        rows, true_xy = rows[keep], true_xy[keep]
        noisy = true_xy + rng.normal(0.0, noise_px, true_xy.shape)
        inside = camera.in_frame(noisy)
        sizes.append(int(inside.sum()))
        xy.append(noisy[inside])
        clean.append(true_xy[inside])
        flux.append(10.0 ** (-0.4 * catalog.magnitude[rows[inside]]))
        unit.append({peer: units[rows[inside]] for peer, units in peer_units.items()})
        hip.append(catalog.hip[rows[inside]])
        attitudes.append(attitude)
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    priors = Rotation.from_rotvec(axes * PRIOR_ERROR_DEG * DEG) * Rotation.from_matrix(np.array(attitudes))
    return {
        "width": camera.width, "height": camera.height, "fov_deg": np.degrees(camera.fov[0]),
        "half_diagonal": camera.half_diagonal, "sizes": np.array(sizes), "xy": np.concatenate(xy),
        "xy_clean": np.concatenate(clean), "flux": np.concatenate(flux),
        "hip": np.concatenate(hip), "attitude": np.array(attitudes), "prior": priors.as_matrix(),
        "prior_error_deg": PRIOR_ERROR_DEG,
        "track": np.flatnonzero(np.array(sizes) >= TRACK_STARS), "track_stars": TRACK_STARS,
        "check": np.arange(min(CHECK_SETS, count)), "solved_arcsec": SOLVED_ARCSEC,
        "id_tolerance_arcsec": ID_TOLERANCE_ARCSEC,
        **{f"unit_{peer}": np.concatenate([u[peer] for u in unit]) for peer in PEER_EPOCHS},
    }


def split(sets: dict, name: str) -> list[np.ndarray]:
    """A flat per-centroid array of ``sets`` cut into its sets."""
    return np.split(sets[name], np.cumsum(sets["sizes"])[:-1])


def timed_rows(identifier, camera: Camera, stars: list[StarMeasurements], hips: list[np.ndarray], priors,
               after_chunk=None, chunk: int = LOCKSTEP_SETS) -> list[list]:
    """Per set [centroids, correct, wrong, solved, latency s] of ``identifier`` (one untimed call first);
    ``after_chunk()``, if given, is called after every ``chunk`` sets (untimed)."""
    identifier.identify([stars[0]], [camera], priors[0])
    rows = []
    for k, (s, hip, prior) in enumerate(zip(stars, hips, priors, strict=True)):
        start = time.perf_counter()
        ids = identifier.identify([s], [camera], prior)[0].catalog_id
        latency = time.perf_counter() - start
        correct, wrong = int(np.sum(ids == hip)), int(np.sum((ids >= 0) & (ids != hip)))
        rows.append([len(s), correct, wrong, correct >= 3 and wrong == 0, latency])
        if after_chunk is not None and (k + 1) % chunk == 0:
            after_chunk()
    return rows


def run_starenv(camera: Camera, sets: dict, mag_limit: float, chunk: int = LOCKSTEP_SETS) -> dict:
    """starenv's lost-in-space rows on all sets, ``chunk`` sets at a time in turn with tetra3rs's (:class:`PeerRun`),
    then its tracking rows on the 30-star sets once the peers are done; the database build time; the peers' results."""
    catalog = load_catalog(mag_limit, EPOCH)
    lis = LostInSpaceIdentifier()
    tracker = TrackingIdentifier(fallback=lis)
    with tempfile.TemporaryDirectory() as cache, mock.patch.dict(os.environ, {"STARENV_CACHE_DIR": cache}):
        start = time.perf_counter()
        lis.reset([camera], catalog)  # a cold build: the user's cache is neither read nor written
        build_s = time.perf_counter() - start
        tracker.reset([camera], catalog)
    stars = [StarMeasurements(xy, f) for xy, f in zip(split(sets, "xy"), split(sets, "flux"), strict=True)]
    hips = split(sets, "hip")
    track = sets["track"]
    n = sets["track_stars"]
    priors = [Rotation.from_matrix(sets["prior"][i]) for i in track]
    with PeerRun(sets, chunk) as peers:
        peers.ready()
        lis_rows = timed_rows(lis, camera, stars, hips, [None] * len(stars), after_chunk=peers.chunk, chunk=chunk)
        peer_results = peers.results()
    return {
        "build_s": build_s,
        "database": f"{len(lis.database)} patterns of {len(lis.database.hip)} stars (Hp <= {mag_limit})",
        "lis": lis_rows,
        "tracking": timed_rows(tracker, camera, [StarMeasurements(stars[i].xy[:n], stars[i].flux[:n]) for i in track],
                               [hips[i][:n] for i in track], priors),
        "peers": peer_results,
    }


def peers_python() -> Path:
    """The peers' virtual environment's python, creating the environment and installing the peers if needed."""
    python = VENV / "bin" / "python"
    if not python.exists():
        subprocess.run([sys.executable, "-m", "venv", str(VENV)], check=True)
    probe = "import importlib.metadata as m; [m.version(p) for p in ('cedar-solve', 'tetra3rs')]"
    if subprocess.run([str(python), "-c", probe], capture_output=True).returncode != 0:
        subprocess.run([str(python), "-m", "pip", "install", "--quiet", *PEERS], check=True)
    return python


class PeerRun:
    """The peers' run (see run_peers.py), a subprocess in their environment, in lockstep with starenv's timing:
    :meth:`ready` waits until the peers have built their databases and run everything but tetra3rs's lost-in-space
    timing; then each :meth:`chunk` (called after starenv has timed ``chunk`` sets) lets tetra3rs time the same
    sets and waits for it, so that both see the machine in the same state; :meth:`results` gives the rows."""

    def __init__(self, sets: dict, chunk: int = LOCKSTEP_SETS, runner: list[str] | None = None):
        """``runner``: the command that runs the peers (default: run_peers.py in their environment); it gets the sets'
        file, the result's file and ``--sync READ_FD WRITE_FD CHUNK``."""
        self._folder = tempfile.TemporaryDirectory()
        folder = Path(self._folder.name)
        np.savez(folder / "sets.npz", **sets)
        self._result = folder / "peers.json"
        self._partial = len(sets["sizes"]) % chunk > 0  # a last chunk of fewer sets
        to_peer, self._go = os.pipe()
        self._done, from_peer = os.pipe()
        runner = [str(peers_python()), str(RUNNER)] if runner is None else runner
        self._process = subprocess.Popen(
            [*runner, str(folder / "sets.npz"), str(self._result), "--sync", str(to_peer), str(from_peer), str(chunk)],
            pass_fds=(to_peer, from_peer))
        os.close(to_peer)
        os.close(from_peer)
        self._to, self._from = os.fdopen(self._go, "wb", buffering=0), os.fdopen(self._done, "rb", buffering=0)

    def __enter__(self) -> PeerRun:
        return self

    def __exit__(self, *exc) -> None:
        self._to.close()
        self._from.close()
        if self._process.poll() is None:
            self._process.kill()
        self._process.wait()
        self._folder.cleanup()

    def _wait(self) -> None:
        if self._from.read(1) != b"d":
            raise RuntimeError(f"the peers' run ended early (exit status {self._process.wait()})")

    def ready(self) -> None:
        self._wait()

    def chunk(self) -> None:
        self._to.write(b"g")
        self._wait()

    def results(self) -> dict:
        if self._partial:
            self._to.write(b"g")
        if self._process.wait() != 0:
            raise RuntimeError(f"the peers' run failed (exit status {self._process.returncode})")
        return json.loads(self._result.read_text())


def summary(rows: list[list]) -> dict:
    """Table entries of per-set rows [centroids, correct, wrong, solved, latency s]."""
    table = np.array(rows, dtype=np.float64).reshape(-1, 5)
    stars = table[:, 0].sum()
    return {
        "sets": len(table), "solved": int(table[:, 3].sum()), "id_rate": table[:, 1].sum() / stars,
        "false_id_rate": table[:, 2].sum() / stars, "median_ms": 1e3 * float(np.median(table[:, 4])),
        "p95_ms": 1e3 * float(np.percentile(table[:, 4], 95)),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sets", type=int, default=200)
    parser.add_argument("--fov", type=int, choices=sorted(MAG_LIMIT), default=12)
    parser.add_argument("--mag-limit", type=float, default=None, help="faintest star (Hp); default by --fov")
    parser.add_argument("--seed", type=int, default=SEED, help="repeat k draws its sets from seed + k")
    parser.add_argument("--repeats", type=int, default=3, help="independent runs (own sets, own timings)")
    parser.add_argument("--noise", type=float, default=NOISE_PX, help="centroid noise per axis (px)")
    parser.add_argument("--blend-px", type=float, default=BLEND_PX,
                        help="drop a star within this of a brighter one (0: keep every star)")
    parser.add_argument("--lockstep", type=int, default=LOCKSTEP_SETS,
                        help="lost-in-space sets starenv and tetra3rs each time in turn")
    parser.add_argument("--json", type=Path, default=None, help="also write the tables here")
    args = parser.parse_args()
    print(f"load average {os.getloadavg()[0]:.2f} (1 min) on {os.cpu_count()} cores")
    runs = [compare(args, args.seed + k) for k in range(args.repeats)]
    print(f"\nover {args.repeats} repeats (seeds {args.seed}-{args.seed + args.repeats - 1}): median [min, max]")
    for name, goal in (("per-star ID rate / cedar-solve's", "id_rate_vs_cedar"),
                       ("per-star ID rate / tetra3rs's", "id_rate_vs_tetra3rs"),
                       ("median LIS latency / tetra3rs's", "latency_vs_tetra3rs"),
                       ("median tracking latency, 30 stars (ms)", "tracking_median_ms"),
                       ("starenv LIS false ids", "false_ids")):
        values = np.array([run["goals"][goal] for run in runs])
        print(f"{name:40} {np.median(values):8.3f} [{values.min():.3f}, {values.max():.3f}]")
    if args.json is not None:
        args.json.write_text(json.dumps(runs, indent=2) + "\n")


def compare(args: argparse.Namespace, seed: int) -> dict:
    """One run: sets drawn from ``seed``, every method on them; its table and goals."""
    mag_limit = MAG_LIMIT[args.fov] if args.mag_limit is None else args.mag_limit
    camera = make_camera(args.fov)
    sets = make_sets(camera, mag_limit, args.sets, np.random.default_rng(seed), args.noise, args.blend_px)
    sizes = sets["sizes"]
    print(f"\nseed {seed}: {args.sets} sets, {np.degrees(camera.fov[0]):.2f} deg field, Hp <= {mag_limit}, "
          f"{args.noise} px noise: "
          f"{np.median(sizes):.0f} stars a set (5-95%: {np.percentile(sizes, 5):.0f}-{np.percentile(sizes, 95):.0f}); "
          f"tracking on {len(sets['track'])} sets cut to {TRACK_STARS} stars")
    ours = run_starenv(camera, sets, mag_limit, args.lockstep)
    peers = ours["peers"]
    databases = {"starenv": f"{ours['database']}, built (cold) in {ours['build_s']:.2f} s"}
    for name, peer in peers.items():
        databases[name] = f"{peer['database']}, {peer['build']} in {peer['build_s']:.2f} s"
    for name, text in databases.items():
        print(f"database {name}: {text}")
    for name, peer in peers.items():
        print(f"noise-free convention check {name}: {peer['check']}")
    methods = {
        "starenv lost-in-space": ours["lis"],
        **{f"{name} lost-in-space": peer["lis"] for name, peer in peers.items()},
        f"starenv tracking ({TRACK_STARS} stars)": ours["tracking"],
        **{f"{name} tracking ({TRACK_STARS} stars)": peer["tracking"] for name, peer in peers.items()
           if "tracking" in peer},
    }
    table = {name: summary(rows) for name, rows in methods.items()}
    print(f"\n{'method':34} | {'sets solved':>11} | {'per-star ID':>11} | {'false ID':>8} | {'median ms':>9} | "
          f"{'p95 ms':>8}")
    for name, row in table.items():
        print(f"{name:34} | {row['solved']:>5}/{row['sets']:<5} | {row['id_rate']:11.2%} | "
              f"{row['false_id_rate']:8.2%} | {row['median_ms']:9.3f} | {row['p95_ms']:8.3f}")
    ours_lis = table["starenv lost-in-space"]
    goals = {
        "id_rate_vs_cedar": ours_lis["id_rate"] / table["cedar-solve lost-in-space"]["id_rate"],
        "id_rate_vs_tetra3rs": ours_lis["id_rate"] / table["tetra3rs lost-in-space"]["id_rate"],
        "false_ids": float(np.array(ours["lis"], dtype=np.float64).reshape(-1, 5)[:, 2].sum()),
        "latency_vs_tetra3rs": ours_lis["median_ms"] / table["tetra3rs lost-in-space"]["median_ms"],
        "tracking_median_ms": table[f"starenv tracking ({TRACK_STARS} stars)"]["median_ms"],
    }
    print(f"\nper-star ID rate / cedar-solve's:       {goals['id_rate_vs_cedar']:7.3f}     (goal >= 1)")
    print(f"median LIS latency / tetra3rs's:        {goals['latency_vs_tetra3rs']:7.2f}     (goal <= 1)")
    print(f"median tracking latency, {TRACK_STARS} stars:     {goals['tracking_median_ms']:7.3f} ms  (goal <= 1 ms)")
    settings = {"sets": args.sets, "fov_deg": float(sets["fov_deg"]), "mag_limit": mag_limit, "seed": seed,
                "lockstep": args.lockstep,
                "noise_px": args.noise, "blend_px": args.blend_px, "tracking_sets": len(sets["track"])}
    return {"settings": settings, "databases": databases, "table": table, "goals": goals}

if __name__ == "__main__":
    main()
