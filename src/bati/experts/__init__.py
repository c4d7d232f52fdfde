"""Expert (context-collection) policies: a task-conditioned SAC per family."""

from bati.experts.zoo import ExpertPolicy, load

__all__ = ["ExpertPolicy", "load"]
