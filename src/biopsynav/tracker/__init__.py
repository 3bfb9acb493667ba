"""Real-time lesion tracking from the tracked probe pose (network or FE engine)."""

from .core import Tracker, contact_indices, pose_problem
from .result import LesionResult, TrackingResult

__all__ = ["LesionResult", "Tracker", "TrackingResult", "contact_indices", "pose_problem"]
