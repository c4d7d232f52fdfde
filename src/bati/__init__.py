"""bati: Behavior-agnostic Task Inference for robust offline in-context RL."""

__version__ = "0.1.0"
