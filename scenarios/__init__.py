"""The bundled scenario files (``*.toml``) and bench files (``benches/*.toml``).

This folder is installed as the package data of ``starenv.scenarios`` (``pyproject.toml`` maps it at build time), so
an installed starenv finds every bundled id from any working directory.  The files are data: nothing here is run.
"""
