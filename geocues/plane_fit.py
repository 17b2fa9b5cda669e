"""Plane estimation primitives of the plane-like cues: RANSAC fits, ray-plane intersection, snapping.

Planes are ``n·x + d = 0`` with ``‖n‖ = 1``, in whatever frame the points are given (the plane
stage works in each camera's frame).
"""

from __future__ import annotations

import numpy as np


def fit_plane_ransac(points: np.ndarray, dist: float, seed: int = 0, iters: int = 500,
                     max_points: int = 3000) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane n·x + d = 0 (‖n‖ = 1) through ``points`` [N, 3], N >= 3, fitted on at most
    ``max_points`` random points (speed) and refined by least squares on its inliers; inliers are
    then counted on all points. Returns (n [3], d, inlier mask [N]).

    The same seed gives the same plane: Open3D's ``segment_plane`` scores its hypotheses on several
    threads and, seeded or not, returned a different plane on 4 of 20 identical calls (Open3D
    0.20), which made ``geocues extract`` give different PLANE cue counts run to run. This is the
    same RANSAC, vectorised in numpy with one seeded generator (:func:`fit_plane_groups` with
    equal weights)."""
    pts = np.asarray(points, np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 3:
        raise ValueError(f"need [N >= 3, 3] points, got shape {pts.shape}")
    rng = np.random.default_rng(seed)
    sub = pts
    if len(pts) > max_points:
        sub = pts[rng.choice(len(pts), size=max_points, replace=False)]
    n, d, _, _ = fit_plane_groups(sub, np.arange(len(sub)), dist, rng, iters=iters)
    if not (np.all(np.isfinite(n)) and np.isfinite(d)):
        return np.array([0.0, 0.0, 1.0]), 0.0, np.zeros(len(pts), bool)
    return n, float(d), np.abs(pts @ n + d) < dist


def group_weights(groups: np.ndarray) -> np.ndarray:
    """w_i = 1 / |group(i)|: every line (all its samples together) weighs as much as one SfM point."""
    _, inv, cnt = np.unique(groups, return_inverse=True, return_counts=True)
    return 1.0 / cnt[inv.ravel()]


def fit_plane_groups(points: np.ndarray, groups: np.ndarray, dist: float, rng: np.random.Generator,
                     iters: int = 300) -> tuple[np.ndarray, float, np.ndarray, float]:
    """Group-weighted RANSAC plane through cue points (prior-free plane cues, paper §4.1).

        π* = argmax_π Σ_i w_i [|n·p_i + d| < τ],   w_i = 1 / |group(i)|

    so a line sampled every centimetre counts once, like one SfM point, and a plane is not chosen
    just because it contains one long line. Minimal samples are drawn with probability ∝ w; the
    winner is refined by weighted least squares on its inliers. points: [P, 3], groups: [P].
    Returns (n [3], d, inlier mask [P], inlier weight / total weight)."""
    P = len(points)
    if P < 3:
        return np.array([0.0, 0.0, 1.0]), 0.0, np.zeros(P, bool), 0.0
    w = group_weights(groups)
    idx = rng.choice(P, size=(iters, 3), p=w / w.sum())
    a, b, c = points[idx[:, 0]], points[idx[:, 1]], points[idx[:, 2]]
    n = np.cross(b - a, c - a)  # [iters, 3]
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    if not ok.any():
        return np.array([0.0, 0.0, 1.0]), 0.0, np.zeros(P, bool), 0.0
    n = n[ok] / norm[ok, None]
    d = -np.sum(n * a[ok], axis=1)
    score = (np.abs(points @ n.T + d) < dist).T.astype(np.float64) @ w  # [iters]
    best = int(np.argmax(score))
    n_b, d_b = n[best], float(d[best])
    for _ in range(2):  # weighted least-squares refinement on the inliers
        inl = np.abs(points @ n_b + d_b) < dist
        if inl.sum() < 3:
            break
        wi = w[inl]
        mu = wi @ points[inl] / wi.sum()
        cov = (points[inl] - mu).T @ ((points[inl] - mu) * wi[:, None])
        n_new = np.linalg.eigh(cov)[1][:, 0]
        n_b = n_new if n_new @ n_b >= 0 else -n_new
        d_b = -float(n_b @ mu)
    inl = np.abs(points @ n_b + d_b) < dist
    return n_b, d_b, inl, float(w[inl].sum() / w.sum())


def ray_plane_depth(rays: np.ndarray, n_cam: np.ndarray, d_cam: float) -> np.ndarray:
    """Intersect camera rays with a plane (prior-free plane cues, paper §4.1).

        x(z) = z · r  (r = (x, y, 1): z-depth parametrisation),   n·x + d = 0  ⇒  z = −d / (n·r)

    rays: [N, 3] camera-frame directions with r_z = 1; n_cam, d_cam: the plane in the camera frame.
    Returns z [N] (inf where the ray is parallel to the plane, negative behind the camera).
    """
    denom = rays @ n_cam
    with np.errstate(divide="ignore", invalid="ignore"):
        z = -d_cam / denom
    return np.where(np.abs(denom) > 1e-12, z, np.inf)


class AnchoredPlane:
    """A plane fitted to cue anchors, with its uncertainty (plane-like cues, paper §4.1).

    In a frame (o; e1, e2, n0) around an initial plane, the plane is h = α u + β v + γ, where u, v
    are in-plane coordinates and h the offset along n0. Each anchor group (one line, or one SfM
    point) is one observation of standard deviation ``sigma`` spread over its samples (weights w
    summing to 1 per group); a prior normal n0 adds the pseudo-observations α, β ~ N(0, tan² σ_n):

        θ = (Mᵀ W M / σ² + Λ)⁻¹ Mᵀ W h / σ²,   M = [u v 1],   Λ = diag(1/tan² σ_n, 1/tan² σ_n, 0)

    (Λ = 0 without a prior normal). The covariance (Mᵀ W M / σ² + Λ)⁻¹ gives the standard
    deviation of the plane's offset anywhere: std(X) = sqrt(m Σ mᵀ), m = [u(X), v(X), 1], which grows
    with the distance from the anchors -- fast when they are few or lie along one line.
    """

    def __init__(self, anchors: np.ndarray, w: np.ndarray, n0: np.ndarray, sigma: float,
                 prior_normal_std_rad: float | None = None, huber: float | None = None):
        a = np.asarray(anchors, np.float64).reshape(-1, 3)
        w = np.asarray(w, np.float64).reshape(len(a))
        n0 = np.asarray(n0, np.float64) / np.linalg.norm(n0)
        self.o = w @ a / max(w.sum(), 1e-12)
        helper = np.array([1.0, 0.0, 0.0]) if abs(n0[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        self.e1 = np.cross(n0, helper)
        self.e1 /= np.linalg.norm(self.e1)
        self.e2 = np.cross(n0, self.e1)
        self.n0 = n0
        q = a - self.o
        M = np.stack([q @ self.e1, q @ self.e2, np.ones(len(a))], axis=1)  # [A, 3]
        h = q @ n0
        lam = np.zeros(3)
        if prior_normal_std_rad is not None:
            lam[:2] = 1.0 / np.tan(prior_normal_std_rad) ** 2
        wr = w.copy()
        for _ in range(5 if huber else 1):  # Huber IRLS against anchors off the surface
            Nmat = M.T @ (M * wr[:, None]) / sigma ** 2 + np.diag(lam)
            # ridge relative to the matrix's scale: an absolute 1e-12 vanished next to 1 / sigma^2 and
            # collinear anchors without a prior normal raised LinAlgError (fuzz finding,
            # tests/test_fuzz_geometry.py); now the free direction gets a huge std instead
            Nmat = Nmat + 1e-12 * max(float(np.trace(Nmat)), 1.0) * np.eye(3)
            self.cov = np.linalg.inv(Nmat)
            self.theta = self.cov @ (M.T @ (wr * h)) / sigma ** 2
            self.residual = M @ self.theta - h  # [A] signed, metres
            if huber:
                wr = w * np.minimum(1.0, huber / np.maximum(np.abs(self.residual), 1e-12))
        al, be, ga = self.theta
        n = n0 - al * self.e1 - be * self.e2
        self.n = n / np.linalg.norm(n)
        self.d = -float(self.n @ (self.o + ga * n0))

    def std_at(self, X: np.ndarray) -> np.ndarray:
        """Standard deviation (metres) of the plane's offset at points X [N, 3]."""
        q = np.asarray(X, np.float64) - self.o
        m = np.stack([q @ self.e1, q @ self.e2, np.ones(len(q))], axis=1)
        return np.sqrt(np.maximum(np.einsum("ni,ij,nj->n", m, self.cov, m), 0.0))


def weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    """Median of x [N] with weights w [N] (the smallest x holding half the weight)."""
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][min(np.searchsorted(cw, 0.5 * cw[-1]), len(x) - 1)])


def loo_group_residuals(points: np.ndarray, groups: np.ndarray, n0: np.ndarray, sigma: float,
                        max_std: float) -> tuple[np.ndarray, np.ndarray]:
    """Leave-one-group-out test of a plane's anchors (prior-free plane cues, our addition).

    For every anchor group g (a line, or an SfM point), fit the plane to the *other* groups
    (:class:`AnchoredPlane`) and measure how far it passes from g:

        r_g = | mean_{i ∈ g} (n₋g · p_i + d₋g) |

    A fitted plane passes close to every anchor it was fitted to, the more so the fewer the anchors
    (each one pulls the plane towards itself): in-sample residuals cannot tell a plane from a
    surface that bends, or from anchors on two surfaces (a wall and the edge of a chair in front
    of it). The held-out residual can. Where the other groups do not pin the plane down at g
    (offset std there > ``max_std``, the bound the plane stage keeps pixels under), g is needed to
    fix the plane and cannot be tested: r_g is NaN, as it is for every group when there are fewer
    than three. points: [A, 3], groups: [A], n0: [3] start normal. Returns (unique groups [G],
    r [G] in metres)."""
    ug, gi = np.unique(groups, return_inverse=True)
    gi = gi.ravel()
    r = np.full(len(ug), np.nan)
    if len(ug) < 3:
        return ug, r
    for k in range(len(ug)):
        held = gi == k
        ap = AnchoredPlane(points[~held], group_weights(groups[~held]), n0, sigma)
        if np.mean(ap.std_at(points[held])) <= max_std:
            r[k] = abs(float(np.mean(points[held] @ ap.n + ap.d)))
    return ug, r
