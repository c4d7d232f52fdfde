"""Expert (context-collection) policies: a task-conditioned SAC per family, or one SAC per training task.

The names below load on first use (PEP 562), so `bati.experts.kinds` (what reports read) imports no JAX."""

__all__ = ["Expert", "ExpertPolicy", "load", "register_expert"]


def __getattr__(name: str):
    if name == "Expert":
        from bati.experts.base import Expert

        return Expert
    if name in ("ExpertPolicy", "load", "register_expert"):
        from bati.experts import zoo

        return getattr(zoo, name)
    raise AttributeError(f"module 'bati.experts' has no attribute {name!r}")
