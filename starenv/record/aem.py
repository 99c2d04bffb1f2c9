"""A recording's attitudes as CCSDS Attitude Ephemeris Messages (``starenv export RECORDING --format aem``).

Two files: the estimate (``--out FILE``), one segment per unbroken run of steps with an estimate (so that no reader
interpolates across a step without one), and the truth beside it (``FILE`` with ``.truth`` before its suffix), one
segment over every step.  Each record is a step's mid-exposure time on the recording's time origin (the scenario's
epoch, Unix time: ``TIME_SYSTEM = UTC`` with leap seconds not counted) and its attitude, written by the ``ccsds-ndm``
library as AEM 1.0 (:func:`starenv.sim.attitude_files.aem_text`: ICRF -> SC_BODY_1 quaternions, scalar last), KVN or,
for a name ending in ``.xml``, XML.  Either file reads back through :func:`starenv.sim.attitude_files.read_aem`; the
truth spans the steps' mid-exposure times, from the first to the last.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.sim.attitude_files import AemSegment, aem_text


def truth_path(out: str | os.PathLike) -> Path:
    """Where the truth goes beside the estimate ``out``: ``run.aem`` -> ``run.truth.aem``."""
    out = Path(out)
    return out.with_name(f"{out.stem}.truth{out.suffix or '.aem'}")


def recording_aems(recording: str | os.PathLike, form: str = "kvn") -> tuple[str, str, int, int]:
    """The estimate's and the truth's AEM text of a finished recording, with the number of steps with an estimate
    and of steps in all; ``form`` ``"kvn"`` or ``"xml"``.  A recording without any estimate is a ValueError."""
    from starenv.record.mcap import read_metadata, read_steps, run_info

    info = run_info(read_metadata(recording), recording)
    name = f"{info['name']} seed {info['seed']}"
    times, truth, estimate = [], [], []
    for step in read_steps(recording):
        if step.attitude_true is None:  # the message of an error that stopped the run: no step
            continue
        times.append(info["origin_ns"] + step.time_ns)
        truth.append(step.attitude_true)
        estimate.append(step.attitude_estimate)
    if not times:
        raise ValueError(f"{recording}: no steps to export")
    unix_ns = np.array(times, dtype=np.int64)
    runs, start = [], None
    for k, q in enumerate([*estimate, None]):
        if q is not None and start is None:
            start = k
        elif q is None and start is not None:
            runs.append((start, k))
            start = None
    if not runs:
        raise ValueError(f"{recording}: no step has an estimate (the run's pipeline gave no attitude): nothing to "
                         f"export as the estimate")
    segments = [AemSegment(unix_ns[a:b], Rotation.from_quat(np.array(estimate[a:b])), name,
                           f"starenv estimate, steps {a} to {b - 1} (a new segment after each step without one)")
                for a, b in runs]
    truth_segment = AemSegment(unix_ns, Rotation.from_quat(np.array(truth)), name,
                               "starenv truth at every step's mid-exposure time")
    count = sum(b - a for a, b in runs)
    return aem_text(segments, form), aem_text([truth_segment], form), count, len(times)
