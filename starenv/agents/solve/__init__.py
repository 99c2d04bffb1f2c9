"""Attitude solution: identified stars in, one attitude out (:class:`~starenv.agents.base.AttitudeSolver`).

``solve(body, inertial, weights=None) -> Rotation``: ``body`` (n, 3) unit vectors in the body frame, ``inertial``
(n, 3) their catalogue directions in ICRS, optional weights; the result is the rotation ICRS -> body minimising
Wahba's loss.

* :class:`QuestSolver` (with sequential rotations), :class:`DavenportSolver` (q-method), :class:`SvdSolver` (Markley's
  SVD solution, through :func:`starenv.agents.blocks.wahba_svd`).

To add a solver, write a class with that ``solve`` method in a module here and name it in ``__all__``.
"""

from starenv.agents.solve.solvers import DavenportSolver, QuestSolver, SvdSolver

__all__ = ["DavenportSolver", "QuestSolver", "SvdSolver"]
