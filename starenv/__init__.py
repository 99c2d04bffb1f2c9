"""starenv: a Gymnasium-style simulator of spacecraft star sensors under dynamic conditions."""

__version__ = "0.1.0"
