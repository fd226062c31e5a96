"""Shipped DiT checkpoints, one per design space (``<space>.pt``); see README.md here for how
each was trained."""
