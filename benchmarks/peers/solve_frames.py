"""cedar-solve on whole frames for ``benchmarks/real_frames.py``: centroid extraction and solution from the image, as
its ``solve_from_image`` does; runs in the peers' virtual environment (numpy < 2), so it imports nothing of starenv.

    python solve_frames.py FRAMES.npz RESULT.json

FRAMES.npz holds ``image{k}`` (2-D grey frames, as starenv reads them) and ``fov_deg`` (k,) (the field across the
columns each is solved with).  RESULT.json gets per frame cedar-solve's RA, Dec, Roll, FOV (deg), RMSE (arcsec),
matches, its own extraction and solution times (ms) and the wall time of the whole call (s); the default database
(10-30 deg fields) is loaded once, before.
"""

from __future__ import annotations

import json
import logging
import sys
import time

import numpy as np


def main() -> None:
    logging.getLogger("tetra3.Tetra3").addHandler(logging.NullHandler())
    import tetra3
    from PIL import Image

    frames = np.load(sys.argv[1])
    solver = tetra3.Tetra3("default_database")
    fovs = frames["fov_deg"]
    out = []
    images = [Image.fromarray(frames[f"image{k}"]) for k in range(len(fovs))]  # its input type, made untimed
    solver.solve_from_image(images[0], fov_estimate=float(fovs[0]))  # untimed: first-call costs
    for image, fov in zip(images, fovs, strict=True):
        start = time.perf_counter()
        result = solver.solve_from_image(image, fov_estimate=float(fov), fov_max_error=0.1 * float(fov))
        wall = time.perf_counter() - start
        keys = ("RA", "Dec", "Roll", "FOV", "RMSE", "Matches", "T_solve", "T_extract")
        out.append({**{key: None if result.get(key) is None else float(result[key]) for key in keys}, "wall_s": wall})
    with open(sys.argv[2], "w") as f:
        json.dump(out, f)


if __name__ == "__main__":
    main()
