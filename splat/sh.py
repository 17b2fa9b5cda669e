"""Real spherical harmonics up to degree 3 -> RGB, with 3DGS's constants, offset and clamp."""

from __future__ import annotations

import torch
from torch import Tensor

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_sh_bases(degree: int) -> int:
    """(degree + 1)^2 coefficients per channel."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be in 0..3, got {degree}")
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Real SH basis [N, (degree+1)^2] at unit directions dirs [N, 3] (3DGS ordering and signs)."""
    n = num_sh_bases(degree)
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2.0 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3.0 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4.0 * zz - xx - yy),
                SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), SH_C3[4] * x * (4.0 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3.0 * yy)]
    basis = torch.stack(out, 1)
    assert basis.shape[1] == n
    return basis


def sh_to_rgb(sh0: Tensor, shN: Tensor, dirs: Tensor, degree: int) -> Tensor:
    """colour = max(0, sum_k Y_k(dir) c_k + 0.5)  (3DGS), using the first (degree+1)^2 coefficients.

    sh0 [N, 1, 3], shN [N, K-1, 3] (may be [N, 0, 3]), dirs [N, 3] unit view directions
    (camera -> Gaussian, world frame). Returns [N, 3].
    """
    n = sh0.shape[0]
    if tuple(sh0.shape) != (n, 1, 3):
        raise ValueError(f"sh0 must be [N, 1, 3], got {tuple(sh0.shape)}")
    if shN.dim() != 3 or shN.shape[0] != n or shN.shape[2] != 3:
        raise ValueError(f"shN must be [{n}, K, 3], got {tuple(shN.shape)}")
    available = shN.shape[1] + 1
    if num_sh_bases(degree) > available:
        raise ValueError(f"SH degree {degree} needs {num_sh_bases(degree)} coefficients, have {available}")
    k = num_sh_bases(degree)
    coeffs = torch.cat([sh0, shN[:, : k - 1]], 1)  # [N, k, 3]
    basis = sh_basis(degree, dirs)  # [N, k]
    return torch.clamp((basis[:, :, None] * coeffs).sum(1) + 0.5, min=0.0)


def sh_degree_of(shN: Tensor) -> int:
    """Highest degree the coefficients [N, K-1, 3] support."""
    k = shN.shape[1] + 1
    degree = int(round(k ** 0.5)) - 1
    if (degree + 1) ** 2 != k or degree > 3:
        raise ValueError(f"shN must hold (d+1)^2-1 coefficients for d in 0..3, got {shN.shape[1]}")
    return degree
