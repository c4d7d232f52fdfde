"""Expert (context-collection) policies: a task-conditioned SAC per family."""

from bati.experts.base import Expert
from bati.experts.zoo import ExpertPolicy, load, register_expert

__all__ = ["Expert", "ExpertPolicy", "load", "register_expert"]
