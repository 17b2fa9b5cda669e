"""EWA projection of 3D Gaussians to the image, with RaDe-GS depth planes and normals (torch).

Everything here is differentiable and device-agnostic. Per Gaussian it computes the 2D mean,
conic (inverse 2D covariance after the 0.3 px low-pass), pixel radius, view-space depth, opacity,
SH colour, and (paper §3.2, after RaDe-GS) a depth plane ``d(pixel) = z + p . (pixel - mean2d)``
and a camera-frame normal facing the camera.

Numerical care (every case below has a test in tests/test_render_hard_cases.py):
- positions are moved to the camera centre before rotating (float32 far from the origin);
- quaternions are normalised with an epsilon (zero-norm gives the identity rotation, no NaN);
- the 2D covariance is ``M M^T`` with ``M = J R_cam S`` and its determinant is the sum of squared
  2x2 minors of M (Cauchy-Binet), so needles and discs never give a negative determinant;
- culled Gaussians (behind the near plane, outside the image) get safe stand-in values before any
  division so that their (unused) branches produce no Inf/NaN gradients.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from splat.camera import Camera
from splat.contracts import Projected, ProjectionConfig  # noqa: F401  (re-exported)
from splat.composite import cpu_backend_available
from splat.sh import num_sh_bases, sh_degree_of, sh_to_rgb

PARAM_KEYS = ("means", "quats", "scales", "opacities", "sh0", "shN")
FLAT_VARIANCE = 1e-8  # RaDe-GS: smallest variance (m^2) below which a Gaussian is treated as flat
MAX_RADIUS = 1e8  # pixel radii are capped here (int32 safety); such Gaussians cover any image


def check_params(params: dict[str, Tensor]) -> int:
    """Raise ValueError unless ``params`` holds the Gaussian tensors of the contract; return N."""
    missing = [k for k in PARAM_KEYS if k not in params]
    if missing:
        raise ValueError(f"Gaussian params miss {missing}; expected keys {list(PARAM_KEYS)}")
    for key in PARAM_KEYS:
        if not isinstance(params[key], Tensor):
            raise TypeError(f"params[{key!r}] must be a torch.Tensor, got {type(params[key]).__name__}")
    n = params["means"].shape[0]
    shapes = {"means": (n, 3), "quats": (n, 4), "scales": (n, 3), "opacities": (n,), "sh0": (n, 1, 3)}
    for key, shape in shapes.items():
        if tuple(params[key].shape) != shape:
            raise ValueError(f"params[{key!r}] must have shape {shape}, got {tuple(params[key].shape)}")
    shn = params["shN"]
    if shn.dim() != 3 or shn.shape[0] != n or shn.shape[2] != 3:
        raise ValueError(f"params['shN'] must have shape ({n}, (d+1)^2-1, 3), got {tuple(shn.shape)}")
    sh_degree_of(shn)
    dtype, device = params["means"].dtype, params["means"].device
    for key in PARAM_KEYS:
        if params[key].dtype != dtype or params[key].device != device:
            raise ValueError(f"params[{key!r}] is {params[key].dtype} on {params[key].device}, params['means'] "
                             f"{dtype} on {device}: every Gaussian tensor must share one dtype and device")
    return n


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] from wxyz quaternions [N, 4], normalised with an epsilon.

    R(q) for unit q = (w, x, y, z); a zero quaternion gives the identity (not NaN).
    """
    q = quats * torch.rsqrt(torch.clamp((quats * quats).sum(-1, keepdim=True), min=1e-12))
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], -1).reshape(-1, 3, 3)


def world_to_camera(means: Tensor, camera: Camera) -> Tensor:
    """x_cam = R (x_world - C)  [N, 3]: centre first, then rotate (float32 far from the origin)."""
    return (means - camera.center.to(means)) @ camera.R.to(means).T


def ewa_covariance_2d(axes_cam: Tensor, scales: Tensor, p_cam: Tensor, camera: Camera
                      ) -> tuple[Tensor, Tensor]:
    """EWA 2D covariance  Sigma' = J W Sigma W^T J^T  (3DGS eq. 5; Zwicker et al. 2002, eq. 31).

    axes_cam [N, 3, 3]: the Gaussian's rotation in the camera frame (W R), scales [N, 3] metres,
    p_cam [N, 3] camera-frame means with z > 0. J is the Jacobian of (fx x/z + cx, fy y/z + cy)
    evaluated at the mean with x/z, y/z clamped to 1.3x the field of view (gsplat's asymmetric
    limits for off-centre principal points). Returns (cov2d [N, 3] as (a, b, c), det [N]) where
    det = det(Sigma') is the sum of the squared 2x2 minors of M = J W R S (Cauchy-Binet), never < 0.
    """
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    tan_x, tan_y = 0.5 * camera.width / fx, 0.5 * camera.height / fy
    x, y, z = p_cam.unbind(-1)
    tx = z * torch.clamp(x / z, -(cx / fx + 0.3 * tan_x), (camera.width - cx) / fx + 0.3 * tan_x)
    ty = z * torch.clamp(y / z, -(cy / fy + 0.3 * tan_y), (camera.height - cy) / fy + 0.3 * tan_y)
    # J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]], applied row by row (no tiny bmm)
    rs = axes_cam * scales[:, None, :]  # [N, 3, 3] = W R S
    inv_z = 1.0 / z
    m = torch.stack([(fx * inv_z)[:, None] * rs[:, 0] - (fx * tx * inv_z * inv_z)[:, None] * rs[:, 2],
                     (fy * inv_z)[:, None] * rs[:, 1] - (fy * ty * inv_z * inv_z)[:, None] * rs[:, 2]],
                    1)  # [N, 2, 3] = J W R S
    m = torch.clamp(m, -1e9, 1e9)  # keeps squared minors below float32 overflow
    a = (m[:, 0] * m[:, 0]).sum(-1)
    b = (m[:, 0] * m[:, 1]).sum(-1)
    c = (m[:, 1] * m[:, 1]).sum(-1)
    minors = torch.stack([m[:, 0, 0] * m[:, 1, 1] - m[:, 0, 1] * m[:, 1, 0],
                          m[:, 0, 0] * m[:, 1, 2] - m[:, 0, 2] * m[:, 1, 0],
                          m[:, 0, 1] * m[:, 1, 2] - m[:, 0, 2] * m[:, 1, 1]], -1)
    return torch.stack([a, b, c], -1), (minors * minors).sum(-1)


class _DivideRows(torch.autograd.Function):
    """``num [N, K] / den [N]`` with d/d den = -(g . out) / den, as the C++ projection computes it:
    autograd's -g num / den^2 underflows den^2 in float32 for a Gaussian under 1e-7 px^2 with
    eps2d = 0 (a 1e-8 m Gaussian 2 m away: NaN gradients where the C++ backend gave 0)."""

    @staticmethod
    def forward(ctx, num: Tensor, den: Tensor) -> Tensor:
        out = num / den[:, None]
        ctx.save_for_backward(out, den)
        return out

    @staticmethod
    def backward(ctx, g: Tensor):
        out, den = ctx.saved_tensors
        return g / den[:, None], -(g * out).sum(-1) / den


def low_pass_conic(cov2d: Tensor, det: Tensor, eps2d: float) -> tuple[Tensor, Tensor, Tensor]:
    """Conic of the low-passed covariance Sigma' + eps2d I, its det, and 3DGS's largest eigenvalue.

    det(Sigma' + e I) = det(Sigma') + e (a + c) + e^2;  conic = [[c, -b], [-b, a]] / det (+ e on a, c).
    lambda_max = mid + sqrt(max(0.1, ((a - c) / 2)^2 + b^2)) with mid = (a + c) / 2 (3DGS radius rule).
    """
    a, b, c = (cov2d + torch.tensor([eps2d, 0.0, eps2d], dtype=cov2d.dtype, device=cov2d.device)).unbind(-1)
    det_lp = det + eps2d * (cov2d[:, 0] + cov2d[:, 2]) + eps2d * eps2d
    conics = _DivideRows.apply(torch.stack([c, -b, a], -1), det_lp)
    half_diff = 0.5 * (a - c)
    lam = 0.5 * (a + c) + torch.sqrt(torch.clamp(half_diff * half_diff + b * b, min=0.1))
    return conics, det_lp, lam


def depth_plane_and_normal(axes_cam: Tensor, log_scales: Tensor, p_cam: Tensor, camera: Camera,
                           min_cos: float) -> tuple[Tensor, Tensor]:
    """RaDe-GS per-Gaussian depth plane and normal (IndoorGS §3.2: d = z' + p . (dx, dy)).

    The Gaussian's surface is the plane through its mean with normal n = Sigma_cam^-1 r0, where
    r0 = (x/z, y/z, 1) is the ray to the mean: along rays near r0 the density
    peaks on that plane. Sigma_cam^-1 = W R diag(1/s^2) R^T W^T is scaled by s_min^2 (the plane
    only needs n's direction), so the weights w_i = (s_min / s_i)^2 lie in (0, 1] and flat Gaussians
    stay finite; RaDe-GS's guard for flat Gaussians (smallest variance below 1e-8 m^2: use only the
    smallest eigen-axis, n = e_min e_min^T r0) zeroes the other weights. The z-depth of the
    ray-plane intersection, to first order in the normalised pixel offset (du, dv), is
    z(du, dv) = z - z (n_x du + n_y dv) / (r0 . n), so the slope per pixel is
    p = -z n_xy / (r0 . n) / (fx, fy), with r0 . n clamped to min_cos |r0| |n| (edge-on planes).
    The normal is -n / |n| (facing the camera, n . ray < 0), zero where n vanishes.
    Returns (slopes [N, 2] metres per pixel, normals [N, 3]).
    """
    fx, fy = camera.K[0, 0], camera.K[1, 1]
    ls_min = log_scales.min(-1, keepdim=True).values  # [N, 1]
    weights = torch.exp(2.0 * (ls_min - log_scales))  # [N, 3] (s_min / s_i)^2
    is_min = torch.zeros_like(log_scales, dtype=torch.bool).scatter_(1, log_scales.argmin(-1, keepdim=True), True)
    flat = 2.0 * ls_min < math.log(FLAT_VARIANCE)  # [N, 1]
    weights = torch.where(flat & ~is_min, torch.zeros_like(weights), weights)
    x, y, z = p_cam.unbind(-1)
    r0 = torch.stack([x / z, y / z, torch.ones_like(z)], -1)  # [N, 3]
    local = (axes_cam * r0[:, :, None]).sum(1)  # [N, 3] r0 in Gaussian axes (A^T r0)
    n = (axes_cam * (weights * local)[:, None, :]).sum(2)  # [N, 3] A (w * local)
    # n / max(|n|, 1e-15), not n * rsqrt(max(|n|^2, 1e-30)): rsqrt's backward -x^-1.5 / 2 overflows
    # float32 for |n|^2 < 2e-26 (the ray perpendicular to the smallest axis, the other axes far
    # larger: n ~ 1e-13) and gave NaN gradients (fuzz finding, tests/test_fuzz_render.py)
    n_hat = n / torch.clamp(torch.linalg.vector_norm(n, dim=-1, keepdim=True), min=1e-15)
    r0n = (r0 * n_hat).sum(-1)  # >= 0 in exact arithmetic
    r0_norm = torch.linalg.vector_norm(r0, dim=-1)
    denom = torch.maximum(r0n.abs(), min_cos * r0_norm) * torch.where(r0n < 0, -1.0, 1.0).to(r0n)
    slopes = -z[:, None] * n_hat[:, :2] / denom[:, None]
    slopes = slopes / torch.stack([fx, fy]).to(slopes)
    normals = torch.where((r0n < 0)[:, None], n_hat, -n_hat)  # flip so that n . ray < 0
    return slopes, normals


def _ewa_stage(means: Tensor, quats: Tensor, log_scales: Tensor, cam: Camera, cfg: ProjectionConfig):
    """Camera-frame means, axes, 2D covariance, conic and 2D means of a set of Gaussians.

    Gaussians not strictly between the near and far planes get a stand-in point 1 m straight ahead
    so that no branch divides by ~0 (their results are discarded by the caller).
    """
    rel = means - cam.center  # [N, 3] camera centre -> mean, world frame
    p_cam = rel @ cam.R.T  # [N, 3]
    z_raw = p_cam[:, 2]
    in_depth = (z_raw > cfg.near) & (z_raw < cfg.far) & torch.isfinite(p_cam).all(-1)
    p_safe = torch.where(in_depth[:, None], p_cam, torch.tensor([0.0, 0.0, 1.0], dtype=means.dtype,
                                                                device=means.device))
    rot = quat_to_rotmat(quats)  # [N, 3, 3]
    # Gaussian axes in the camera frame, W R, as one [3N, 3] x [3, 3] product (no tiny bmm)
    axes_cam = (rot.transpose(1, 2).reshape(-1, 3) @ cam.R.T).reshape(-1, 3, 3).transpose(1, 2)
    cov2d, det = ewa_covariance_2d(axes_cam, torch.exp(log_scales), p_safe, cam)
    conics, det_lp, lam = low_pass_conic(cov2d, det, cfg.eps2d)
    fx, fy, cx, cy = cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]
    z = p_safe[:, 2]
    means2d = torch.stack([fx * p_safe[:, 0] / z + cx, fy * p_safe[:, 1] / z + cy], -1)  # [N, 2]
    return rel, p_safe, in_depth, axes_cam, det, conics, det_lp, lam, means2d


def _scatter_rows(rows: Tensor, values: Tensor, n: int, fill: float = 0.0) -> Tensor:
    """[n, ...] tensor holding ``values`` at ``rows`` and ``fill`` elsewhere (differentiable)."""
    full = torch.full((n,) + tuple(values.shape[1:]), fill, dtype=values.dtype, device=values.device)
    return full.index_put((rows,), values)


def project_gaussians(params: dict[str, Tensor], camera: Camera, *, sh_degree: int | None = None,
                      config: ProjectionConfig | None = None, backend: str = "torch") -> Projected:
    """Project every Gaussian of ``params`` (gsplat naming, see docs/rasterizer.md) into ``camera``.

    Two stages: culling for all Gaussians without autograd (depth range, radius box on the image),
    then the differentiable projection, colour and depth plane for the visible ones only. Culled
    Gaussians get radius 0 and zeros elsewhere (depth 1.0), and no gradient.

    ``backend="cpu"`` runs the same computation fused in C++ (:mod:`splat.project_cpu`; CPU
    tensors, no camera gradients); it falls back to this torch code when the camera requires grad
    or the C++ extension cannot be built (the compositing dispatcher has logged why).
    """
    cfg = config or ProjectionConfig()
    n = check_params(params)
    means = params["means"]
    dtype, device = means.dtype, means.device
    if sh_degree is None:
        sh_degree = sh_degree_of(params["shN"])
    elif num_sh_bases(sh_degree) > params["shN"].shape[1] + 1:
        raise ValueError(f"SH degree {sh_degree} needs {num_sh_bases(sh_degree)} coefficients, "
                         f"have {params['shN'].shape[1] + 1}")
    if backend not in ("torch", "cpu"):
        raise ValueError(f"projection backend must be 'torch' or 'cpu', got {backend!r}")
    camera_grad = any(t is not None and t.requires_grad for t in (camera.K, camera.viewmat, camera.center))
    if backend == "cpu" and device.type == "cpu" and not camera_grad and cpu_backend_available():
        from splat.project_cpu import project_gaussians_cpu  # built with the compositing kernel

        return project_gaussians_cpu(params, camera, sh_degree, cfg)
    cam = Camera._derived(camera.K.to(device=device, dtype=dtype), camera.viewmat.to(device=device, dtype=dtype),
                          camera.width, camera.height, camera.center.to(device=device, dtype=dtype))
    with torch.no_grad():
        _, _, in_depth, _, _, conics, _, lam, means2d = _ewa_stage(
            means, params["quats"], params["scales"], cam, cfg)
        radius = torch.ceil(3.0 * torch.sqrt(lam)).clamp(max=MAX_RADIUS)
        mx, my = means2d[:, 0], means2d[:, 1]
        # the radius box must contain a pixel centre (j + 0.5, i + 0.5) of the image
        on_image = ((mx + radius >= 0.5) & (mx - radius <= camera.width - 0.5)
                    & (my + radius >= 0.5) & (my - radius <= camera.height - 0.5))
        visible = in_depth & on_image & torch.isfinite(means2d).all(-1) & torch.isfinite(conics).all(-1)
        radii = torch.where(visible, radius, torch.zeros_like(radius)).to(torch.int32)
        vis = torch.nonzero(visible).squeeze(1)
    log_scales = params["scales"][vis]
    rel, p_cam, _, axes_cam, det, conics, det_lp, _, means2d = _ewa_stage(
        means[vis], params["quats"][vis], log_scales, cam, cfg)
    opacities = torch.sigmoid(params["opacities"][vis])
    if cfg.antialiased:
        opacities = opacities * torch.sqrt(torch.clamp(det / det_lp, min=1e-12))
    dirs = rel * torch.rsqrt(torch.clamp((rel * rel).sum(-1, keepdim=True), min=1e-24))
    colors = sh_to_rgb(params["sh0"][vis], params["shN"][vis], dirs, sh_degree)
    slopes, normals = depth_plane_and_normal(axes_cam, log_scales, p_cam, cam, cfg.min_plane_cos)
    out = Projected(
        means2d=_scatter_rows(vis, means2d, n), conics=_scatter_rows(vis, conics, n),
        depths=_scatter_rows(vis, p_cam[:, 2], n, fill=1.0), radii=radii,
        opacities=_scatter_rows(vis, opacities, n), colors=_scatter_rows(vis, colors, n),
        depth_slopes=_scatter_rows(vis, slopes, n), normals=_scatter_rows(vis, normals, n))
    assert out.means2d.shape == (n, 2) and out.conics.shape == (n, 3)
    return out
