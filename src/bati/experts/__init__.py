"""Expert (context-collection) policies: a task-conditioned SAC per family."""

from bati.experts.zoo import Expert, ExpertPolicy, load

__all__ = ["Expert", "ExpertPolicy", "load"]
