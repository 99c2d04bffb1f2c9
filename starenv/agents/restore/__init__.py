"""Restoration of smeared frames: blur kernels from the gyro (``kernels``), the algorithms (``algorithms``:
Richardson-Lucy, Wiener, the curvature filter, resharpening) and the deblurrers built on them -- full frame
(``frame``), region of interest (``roi``), seed 001's curvature + RL (``curvature``) and seed 000's RL with a learned
iteration count (``iteration``).  No deblurrer imports another."""
