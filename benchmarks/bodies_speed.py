"""Cost of the solar-system sky on a 1024 x 1024 frame: paper 002's head (5 deg/s) pointed 2 deg from the Moon (its
lit disk in the field, its stray light) with and without ``[sky] bodies`` and ``[sky] aberration``, each frame
simulated whole (render, bodies, read-out) by the sensor, timed in the same run (only the ratios mean anything on a
shared machine).  Goal (issue 32): the sky's effects within 2x of the same frames without them; frames of scenarios
that ask for neither run the same code as before (the effects are skipped, not computed and discarded).

    python benchmarks/bodies_speed.py [--frames N] [--repeats N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from starenv import scenario as scenario_mod
from starenv.sim import ephemeris
from starenv.sim.conventions import unit_to_radec
from starenv.sim.sensor import StarSensor


def frame_time(overrides: dict, frames: int, repeats: int) -> float:
    """Median over ``repeats`` of the mean time (s) of ``frames`` frames of paper_002 with ``overrides``."""
    sensor = StarSensor(scenario_mod.load("paper_002", overrides))
    sensor.next_frame()  # caches warm
    times = []
    for _ in range(repeats):
        sensor.reset(0)
        t0 = time.perf_counter()
        for _ in range(frames):
            sensor.next_frame()
        times.append((time.perf_counter() - t0) / frames)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    moon = ephemeris.body_geocentric("moon", ephemeris.julian_centuries(2026.0, 0.0))
    ra, dec = (np.degrees(x) for x in unit_to_radec(moon / np.linalg.norm(moon)))
    pointing = {"epoch": 2026.0, "motion.initial_ra_deg": float(ra) + 2.0, "motion.initial_dec_deg": float(dec)}
    cases = {
        "plain": {},
        "aberration": {"sky.aberration": True},
        "bodies": {"sky.bodies": True},
        "bodies + aberration": {"sky.bodies": True, "sky.aberration": True},
    }
    times = {name: frame_time(pointing | extra, args.frames, args.repeats) for name, extra in cases.items()}
    print(f"paper_002 frame (1024 x 1024, Moon in the field), median of {args.repeats} x {args.frames} frames")
    for name, seconds in times.items():
        print(f"  {name:20s} {seconds * 1e3:8.1f} ms   {seconds / times['plain']:.2f}x plain")


if __name__ == "__main__":
    main()
