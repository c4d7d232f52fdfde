"""How tables write methods and returns (shared by `bati report` and the experiment reports)."""

from __future__ import annotations

import numpy as np

# How a method is named in tables (its `--method` name otherwise).
METHOD_LABELS = {"oracle": "oracle (IQL, true task)"}


def return_digits(*values: float) -> int:
    """Decimals for returns: 3 when every |return| is below 5 (KuhnPoker's returns per hand), else 1."""
    finite = [abs(float(v)) for v in values if v is not None and np.isfinite(v)]
    return 3 if finite and max(finite) < 5 else 1
