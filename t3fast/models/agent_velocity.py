"""Moved to :mod:`t3fast.agents.tracker`; this name stays importable while callers move."""

from t3fast.agents.tracker import tracker_velocities

__all__ = ["tracker_velocities"]
