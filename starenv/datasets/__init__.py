"""Samples drawn from the simulator for learning (numpy only, no torch): each reproducible alone from its scenario
and seed.  ``smear``: smeared frames with their sharp, noise-free reference (deblurring)."""
