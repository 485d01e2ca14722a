"""Wilson intervals and exact McNemar tests for paired success / failure outcomes."""
from __future__ import annotations

import math

import numpy as np
from scipy.stats import binomtest, norm

__all__ = ["mcnemar", "wilson"]


def wilson(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion (``(0, 1)`` for ``n == 0``)."""
    if n == 0:
        return 0.0, 1.0
    z = float(norm.ppf(0.5 + confidence / 2))
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return max(0.0, centre - half), min(1.0, centre + half)


def mcnemar(a, b) -> dict:
    """Exact two-sided McNemar test of paired 0/1 outcomes ``a`` vs ``b``.

    Only the discordant pairs count: ``a_only`` (a succeeded, b failed) and
    ``b_only``; under the null each discordant pair is a fair coin, so the
    p-value is the two-sided binomial test of ``a_only`` out of
    ``a_only + b_only`` (exact at every count, also when it is small).
    """
    a = np.asarray(a, dtype=bool)
    b = np.asarray(b, dtype=bool)
    if a.shape != b.shape:
        raise ValueError(f"paired outcomes must have the same shape, got {a.shape} and {b.shape}.")
    a_only, b_only = int((a & ~b).sum()), int((~a & b).sum())
    n = a_only + b_only
    p = 1.0 if n == 0 else float(binomtest(a_only, n, 0.5).pvalue)
    return {"a_only": a_only, "b_only": b_only, "diff": float(a.mean() - b.mean()) if a.size else 0.0, "p": p}
