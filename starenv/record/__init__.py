"""Recordings of episodes: MCAP in Foxglove's well-known protobuf schemas (``mcap``), Rerun review (``rerun``).

Both go through one per-step record (``step.StepData``) so the MCAP file and the Rerun recording say the same thing.
"""
