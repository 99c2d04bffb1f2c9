"""Real frames: read a camera's image files (:mod:`~starenv.real.read`) and solve them lost in space
(:mod:`~starenv.real.solve`), the spot size measured where the camera's is not calibrated."""

from starenv.real.read import FrameFileError, read_frame
from starenv.real.solve import FrameSolution, FrameSolver, IdentifiedStar, camera_from_fov, radec_roll, solve_frame

__all__ = ["FrameFileError", "FrameSolution", "FrameSolver", "IdentifiedStar", "camera_from_fov", "radec_roll",
           "read_frame", "solve_frame"]
