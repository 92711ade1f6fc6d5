"""Moved to :mod:`t3fast.agents.boxes`; this name stays importable while callers move."""

from t3fast.agents.boxes import fit_agent_boxes

__all__ = ["fit_agent_boxes"]
