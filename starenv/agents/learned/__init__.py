"""Learned agents: torch models, their agents and training.  The only package of the project that imports torch."""
