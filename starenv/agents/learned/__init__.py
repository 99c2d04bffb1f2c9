"""Learned (torch) agents: their networks, the agents that run them in the pipeline, and their training.  torch is
imported only inside this package, so the simulator and the classical agents load without it."""
