"""Average consensus on the fleet: a user algorithm outside the core (see consensus.py)."""

from examples.average_consensus.consensus import Average, NaiveAverage

__all__ = ["Average", "NaiveAverage"]
