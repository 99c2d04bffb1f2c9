"""Wahba's problem by the singular value decomposition: the attitude that best maps reference vectors onto measured
ones."""

from __future__ import annotations

import numpy as np
from scipy.linalg import lapack


def wahba_svd(body: np.ndarray, inertial: np.ndarray, weights: np.ndarray | None = None) -> np.ndarray:
    """Attitude matrix minimising Wahba's loss, by the SVD of the attitude profile matrix.

    Parameters
    ----------
    body : (..., n, 3) ndarray
        Measured directions, unit vectors in the body frame; row ``i`` is the same star as row ``i`` of
        ``inertial``.  Leading axes hold independent problems, solved as one batch.
    inertial : (..., n, 3) ndarray
        Reference (catalogue) directions, unit vectors in ICRS.
    weights : (..., n) ndarray, optional
        Positive weight of each pair (only their ratios matter); equal weights if None.

    Returns
    -------
    attitude : (..., 3, 3) ndarray
        The rotation matrix ``A``, ICRS -> body (``b = A r``, :mod:`starenv.sim.conventions`), minimising
        ``sum_i w_i |b_i - A r_i|^2``.  ``scipy.spatial.transform.Rotation.from_matrix`` turns it into a rotation.

    Notes
    -----
    With the attitude profile matrix ``B = sum_i w_i b_i r_i^T = U S V^T``, the optimal attitude is
    ``A = U diag(1, 1, d) V^T``, ``d = det(U V^T) = +-1``: the orthogonal matrix nearest ``B``, kept a proper rotation
    (``d = -1`` flips the axis of the smallest singular value instead of reflecting) [1]_; ``d`` is exactly +-1, the
    sign of the computed determinant.  A single problem calls LAPACK's ``dgesdd`` directly (the routine
    ``numpy.linalg.svd`` calls, without its wrapper's cost, most of the time for one 3 x 3 matrix); a batch goes
    through ``numpy.linalg.svd``.  A problem gives the same bits alone as in a batch (``tests/test_blocks.py``).
    The inputs are not checked: this is the inner loop of the identifiers and verifiers;
    :class:`starenv.agents.solve.SvdSolver` checks them (shapes, unit length, observability) and calls this.  Fewer
    than two non-parallel pairs leave the rotation about the common direction undetermined, and the result is one of
    the minimisers.

    References
    ----------
    .. [1] F. L. Markley, "Attitude determination using vector observations and the singular value decomposition",
       Journal of the Astronautical Sciences 36(3), 245-258, 1988.
    .. [2] G. Wahba, "A least squares estimate of satellite attitude", SIAM Review 7(3), 409, 1965.
    """
    if weights is not None:
        body = body * weights[..., None]
    if body.ndim == 2 and inertial.ndim == 2:
        u, _, vt, _ = lapack.dgesdd(body.T @ inertial)
        attitude = u @ vt
        (a, b, c), (d, e, f), (g, h, i) = attitude.tolist()
        if a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) < 0.0:
            u[:, 2] = -u[:, 2]
            attitude = u @ vt
        return attitude
    profile = np.swapaxes(body, -1, -2) @ inertial
    u, _, vt = np.linalg.svd(profile)
    u[..., :, 2] *= np.where(np.linalg.det(u @ vt) < 0.0, -1.0, 1.0)[..., None]
    return u @ vt
