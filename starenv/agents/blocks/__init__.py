"""Pure building blocks the agents share (numpy / scipy functions, no state)."""
__all__: list[str] = []
