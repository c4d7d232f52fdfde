"""The paper's experiments as re-runnable specs."""
