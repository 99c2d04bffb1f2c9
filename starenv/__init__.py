"""starenv: a Gymnasium-style simulator of spacecraft star sensors under dynamic conditions.

Importing the package registers one Gymnasium id per bundled scenario (``StarEnv/Paper000-v0``, ...) and
``StarEnv/Scenario-v0``, which takes ``scenario=`` (bundled name or path) and ``overrides=`` (dotted key paths).
"""

from starenv.registration import register_envs

__version__ = "0.1.0"

register_envs()
