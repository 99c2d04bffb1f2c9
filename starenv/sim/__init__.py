"""The simulator: sky, motion, gyro, optics, photometry, rendering, the image sensor's noise, drops, and the sensor
that steps them frame by frame.  It knows nothing above it (scenarios, agents, the env): see ``tests/test_layers.py``.
"""
