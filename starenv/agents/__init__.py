"""Processing agents of a star-sensor pipeline: the role protocols and their implementations."""
