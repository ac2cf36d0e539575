"""The one PSNR of bcf: reports, training progress, baselines, benchmarks and `bcf bc6h encode --verify` use it."""

from __future__ import annotations

import math

__all__ = ["MAX_PSNR_DB", "psnr_from_mse"]

MAX_PSNR_DB = 100.0  # what an exact match scores: a finite number, so reports stay valid JSON


def psnr_from_mse(mse: float, peak: float = 1.0) -> float:
    """PSNR in dB of a mean squared error against `peak` (1 for values in [0, 1]). An exact match (mse at most
    1e-10 of peak squared) gives MAX_PSNR_DB."""
    return MAX_PSNR_DB if mse <= 1e-10 * peak * peak else 10.0 * math.log10(peak * peak / mse)
