"""Comparing rendered images against a reference (``bench_lowpoly.py``, ``profile_render.py``)."""

from __future__ import annotations

import numpy as np


def quality(reference: np.ndarray, images: np.ndarray) -> dict[str, list[float]]:
    """Return per image the PSNR (dB; None when equal) and mean absolute difference to ``reference``."""
    error = images.astype(np.float64) - reference.astype(np.float64)
    mse = (error**2).mean(axis=(1, 2, 3))
    return {
        "psnr_db": [round(float(10 * np.log10(255.0**2 / m)), 2) if m > 0 else None for m in mse],
        "mean_abs_diff": [round(float(v), 3) for v in np.abs(error).mean(axis=(1, 2, 3))],
    }
