"""Comparing rendered images against a reference (``bench_lowpoly.py``, ``profile_render.py``,
``bench_mjwarp.py``, ``bench_mjwarp_render.py``)."""

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


def ssim(first: np.ndarray, second: np.ndarray, window: int = 7) -> np.ndarray:
    """Mean SSIM per image of two ``uint8 [n, H, W, 3]`` stacks: Wang et al.'s index over every
    7x7 window (uniform weights, sample covariance, K1 0.01, K2 0.03, range 255), averaged over
    the windows and the channels."""
    x, y = (np.moveaxis(a.astype(np.float64), -1, 1) for a in (first, second))

    def mean(a: np.ndarray) -> np.ndarray:
        total = np.pad(a, [(0, 0)] * (a.ndim - 2) + [(1, 0), (1, 0)]).cumsum(-2).cumsum(-1)
        w = window
        return (total[..., w:, w:] - total[..., :-w, w:] - total[..., w:, :-w] + total[..., :-w, :-w]) / w**2

    correction = window**2 / (window**2 - 1)
    mx, my = mean(x), mean(y)
    vx, vy = (mean(x * x) - mx**2) * correction, (mean(y * y) - my**2) * correction
    cov = (mean(x * y) - mx * my) * correction
    c1, c2 = (0.01 * 255) ** 2, (0.03 * 255) ** 2
    index = (2 * mx * my + c1) * (2 * cov + c2) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return index.mean(axis=(1, 2, 3))
