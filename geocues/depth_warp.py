"""Smooth warp correction of an aligned depth prior (our addition; docs/geocues.md, depth alignment):
a low-order 2D polynomial of the ratio between the anchors' depths and the affine-aligned prior."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from geocues.depth_align import DepthAlignConfig


def norm_uv(uv: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates -> isotropic coordinates centred on the image, x in [-1, 1]."""
    half = width / 2.0
    return (uv[:, 0] - half) / half, (uv[:, 1] - height / 2.0) / half


def monomials(x: np.ndarray, y: np.ndarray, degree: int) -> np.ndarray:
    """[N, T] monomials x^a y^b with 1 <= a + b <= degree (no constant: the affine fit has it)."""
    cols = [x ** a * y ** (k - a) for k in range(1, degree + 1) for a in range(k, -1, -1)]
    return np.stack(cols, axis=1) if cols else np.zeros((len(x), 0))


def fit_warp(x: np.ndarray, y: np.ndarray, ratio: np.ndarray, degree: int, cfg: DepthAlignConfig
             ) -> np.ndarray:
    """Smooth warp correction of an aligned prior (our addition for low-frequency prior errors).

        z_i / (s·d_i + b) − 1 ≈ w(x_i, y_i) = Σ_{1 ≤ a+b ≤ D} c_ab x_i^a y_i^b

    fitted by Huber IRLS (δ = huber_rel) with a ridge penalty ``warp_ridge`` · N · ‖c‖². x, y: [N]
    normalised image coordinates of the anchors, ratio: [N] z / (s d + b). Returns c [T]."""
    A = monomials(x, y, degree)
    e = ratio - 1.0
    c = np.zeros(A.shape[1])
    lam = cfg.warp_ridge * len(e)
    for _ in range(10):
        r = A @ c - e
        w = np.minimum(1.0, cfg.huber_rel / np.maximum(np.abs(r), 1e-12))
        Aw = A * w[:, None]
        c_new = np.linalg.solve(A.T @ Aw + lam * np.eye(A.shape[1]), Aw.T @ e)
        if np.max(np.abs(c_new - c)) < 1e-7:
            c = c_new
            break
        c = c_new
    return c
