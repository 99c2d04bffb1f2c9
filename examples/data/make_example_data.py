"""Writes the two example input files beside this script (run it again to regenerate them, byte for byte):

* ``orion_stars.csv``: the Hipparcos-2 stars (Hp <= 6.5) within 20 deg of Orion's belt, (RA, Dec) = (83.8, -5.4) deg,
  as a plain CSV catalogue (positions at J1991.25, the catalogue's own epoch: ``[catalog] epoch = 1991.25``);
* ``orion_pass.aem``: a CCSDS AEM 1.0 (KVN) of 20 s at 10 samples per second: the body turning about its +Z axis at
  0.5 deg/s while its +Z axis drifts at 0.2 deg/s, starting with the body +Z axis on Orion.
"""

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from starenv.sim.attitude_files import AemSegment, aem_text
from starenv.sim.conventions import DEG, pointing, radec_to_unit
from starenv.sim.sky import hipparcos_table

HERE = Path(__file__).parent
CENTRE_DEG = (83.8, -5.4)
J2026_UNIX_NS = 1767225600 * 10**9  # 2026-01-01T00:00:00 UTC


def write_catalogue() -> None:
    table = hipparcos_table()
    centre = radec_to_unit(np.radians(CENTRE_DEG[0]), np.radians(CENTRE_DEG[1]))
    near = radec_to_unit(table.ra, table.dec) @ centre >= np.cos(np.radians(20.0))
    rows = np.flatnonzero(near & (table.hp <= 6.5))
    lines = ["# Hipparcos-2 (van Leeuwen 2007) stars with Hp <= 6.5 within 20 deg of (83.8, -5.4) deg, J1991.25",
             "id,ra_deg,dec_deg,pmra_mas_yr,pmdec_mas_yr,mag,b_v"]
    for k in rows:
        b_v = "" if np.isnan(table.b_v[k]) else repr(float(table.b_v[k]))
        lines.append(",".join([str(table.hip[k]), repr(float(np.degrees(table.ra[k]))),
                               repr(float(np.degrees(table.dec[k]))), repr(float(table.pmra[k])),
                               repr(float(table.pmdec[k])), repr(float(table.hp[k])), b_v]))
    (HERE / "orion_stars.csv").write_text("\n".join(lines) + "\n")


def write_attitude() -> None:
    t = np.arange(201) * 0.1  # s
    start = pointing(CENTRE_DEG[0] * DEG, CENTRE_DEG[1] * DEG, 0.0)  # ICRS -> body (head 0 mounted along the body)
    rate = np.array([0.2, 0.0, 0.5]) * DEG  # rad/s, body frame
    attitude = Rotation.from_rotvec(-np.outer(t, rate)) * start
    segment = AemSegment(J2026_UNIX_NS + np.round(t * 1e9).astype(np.int64), attitude, "EXAMPLE SAT",
                         "a slow drift and roll across Orion, written by examples/data/make_example_data.py")
    (HERE / "orion_pass.aem").write_text(aem_text([segment], "kvn"))


if __name__ == "__main__":
    write_catalogue()
    write_attitude()
