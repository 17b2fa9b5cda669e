"""Hypothesis strategies for the property-based fuzz suite (tests/test_fuzz_*.py, docs/testing.md).

One strategy per domain object. Each draws a small, readable *spec* (a frozen dataclass: the
choices that matter -- regimes, special values, a numpy seed for the bulk) and ``build()`` turns it
into the arrays the library takes. Specs print well when a property fails and can be written
literally into ``@example(...)`` regression pins; the bulk values come from a seeded numpy
generator so that a 64-Gaussian scene costs a few dozen hypothesis choices, not thousands.

Domains and their hard cases:
- ``cameras``: focal 1e-1..1e5 px, fx != fy, principal points off the image, images from 1x1 to
  24x18 px, any rotation, centres up to 1e4 m from the origin;
- ``gaussians``: means behind the camera, straddling or exactly on the near plane, off-frustum,
  1e2..1e4 m away; log-scales from log(1e-8) to log(1e3) per axis, needles, discs, +-40; zero,
  tiny and huge quaternions; opacity logits up to +-50;
- ``splats2d``: already-projected Gaussians for the compositor (means far off the image, thin and
  huge covariances, radii 0 or 1e8, opacities at 0, 1/255, 0.99 and 1, depth ties);
- ``depth_maps`` / ``normal_maps``: holes (0), spikes, NaN and Inf regions;
- ``line_pairs``: two cameras and a 3D segment seen by both, incl. zero-length and
  parallel-to-epipolar (along the baseline) segments;
- ``point_sets``: noisy coplanar points with outliers, collinear and duplicate points.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from hypothesis import strategies as st

# ------------------------------------------------------------------------------------- helpers


def rotation_from_quat(q) -> np.ndarray:
    """[3, 3] float64 rotation of the wxyz quaternion q (normalised; zero gives the identity)."""
    q = np.asarray(q, np.float64)
    n = np.linalg.norm(q)
    w, x, y, z = q / n if n > 0 else (1.0, 0.0, 0.0, 0.0)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def look_at(center, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """World-to-camera rotation [3, 3] of an OpenCV camera at ``center`` looking at ``target``."""
    z = np.asarray(target, np.float64) - np.asarray(center, np.float64)
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, (1.0, 0.0, 0.0))
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z])


def unit_quats() -> st.SearchStrategy[tuple[float, float, float, float]]:
    """Unit wxyz quaternions (any rotation); never zero."""
    comp = st.floats(-1.0, 1.0, allow_nan=False)
    return st.tuples(comp, comp, comp, comp).map(
        lambda q: tuple(float(v) for v in (np.asarray(q) / np.linalg.norm(q)))
        if np.linalg.norm(q) > 1e-3 else (1.0, 0.0, 0.0, 0.0))


def directions(min_norm: float = 0.1) -> st.SearchStrategy[tuple[float, float, float]]:
    """Non-zero 3-vectors with components in [-1, 1] (too short ones map to +z, no filtering)."""
    comp = st.floats(-1.0, 1.0)
    return st.tuples(comp, comp, comp).map(
        lambda v: tuple(float(c) for c in v) if np.linalg.norm(v) > min_norm else (0.0, 0.0, 1.0))


def log_uniform(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Floats spread evenly in log10 between lo and hi (> 0), end points included."""
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: float(10.0 ** e))


seeds = st.integers(0, 2**32 - 1)

# ------------------------------------------------------------------------------------- cameras


@dataclass(frozen=True)
class CameraSpec:
    """A pinhole camera: intrinsics in pixels (COLMAP centres), world-to-camera rotation from a
    wxyz quaternion, centre in world metres."""

    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def R(self) -> np.ndarray:
        return rotation_from_quat(self.quat)

    @property
    def t(self) -> np.ndarray:
        return -self.R @ np.asarray(self.center, np.float64)

    def to_world(self, x_cam: np.ndarray) -> np.ndarray:
        """World points [N, 3] (float64) of camera-frame points x_cam [N, 3]."""
        return np.asarray(x_cam, np.float64) @ self.R + np.asarray(self.center, np.float64)

    def build(self, dtype: torch.dtype = torch.float32):
        """A :class:`splat.camera.Camera` (float64 pose arithmetic, stored in ``dtype``)."""
        from splat.camera import Camera

        vm = np.eye(4)
        vm[:3, :3], vm[:3, 3] = self.R, self.t
        as_t = lambda a: torch.as_tensor(np.asarray(a, np.float64), dtype=dtype)  # noqa: E731
        return Camera(K=as_t(self.K), viewmat=as_t(vm), width=self.width, height=self.height,
                      center=as_t(self.center))

    def scene_camera(self, index: int = 0):
        """The same view as a :class:`geocues.scene.Camera` (numpy float64)."""
        from geocues.scene import Camera

        return Camera(index, index + 1, f"{index:05d}.png", None, self.width, self.height, self.K,
                      self.R, self.t)


@st.composite
def cameras(draw, max_width: int = 24, max_height: int = 18, min_focal: float = 1e-1,
            max_focal: float = 1e5, far_centre: bool = True, min_width: int = 1, min_height: int = 1
            ) -> CameraSpec:
    """Extreme pinhole cameras: focal 1e-1..1e5 px (fx, fy independent or equal), principal
    point anywhere from 2 image sizes left/above to 2 right/below (off the image), 1x1 to
    max_width x max_height images, any rotation, centre at the origin or up to 1e4 m away."""
    width = draw(st.integers(min_width, max_width))
    height = draw(st.integers(min_height, max_height))
    fx = draw(log_uniform(min_focal, max_focal))
    fy = draw(st.one_of(st.just(fx), log_uniform(min_focal, max_focal)))
    frac = st.one_of(st.just(0.5), st.floats(-2.0, 3.0))
    cx, cy = draw(frac) * width, draw(frac) * height
    quat = draw(st.one_of(st.just((1.0, 0.0, 0.0, 0.0)), unit_quats()))
    coord = st.floats(-1e4, 1e4) if far_centre else st.floats(-10.0, 10.0)
    center = draw(st.one_of(st.just((0.0, 0.0, 0.0)), st.tuples(coord, coord, coord)))
    return CameraSpec(width, height, float(fx), float(fy), float(cx), float(cy), quat,
                      tuple(float(c) for c in center))


# ----------------------------------------------------------------------------------- gaussians

MEAN_KINDS = ("front", "front", "front", "behind", "straddle", "on_near", "off_frustum", "far")
SCALE_KINDS = ("normal", "normal", "mixed", "tiny", "huge", "needle", "disc", "plus40", "minus40")
QUAT_KINDS = ("random", "random", "zero", "tiny", "huge")
OPACITY_KINDS = ("normal", "normal", "plus50", "minus50")
VALID_SCALE_KINDS = ("normal", "normal", "mixed", "tiny", "huge", "needle", "disc")  # 1e-8..1e3 m


@dataclass(frozen=True)
class GaussianSpec:
    """Gaussians around a camera: per Gaussian one regime each for its mean (in the camera frame),
    log-scales, quaternion and opacity logit; a numpy seed for the values within the regimes."""

    mean_kinds: tuple[str, ...]
    scale_kinds: tuple[str, ...]
    quat_kinds: tuple[str, ...]
    opacity_kinds: tuple[str, ...]
    seed: int = 0
    sh_degree: int = 0

    @property
    def n(self) -> int:
        return len(self.mean_kinds)

    def build(self, cam: CameraSpec, dtype: torch.dtype = torch.float32, near: float = 0.01
              ) -> dict[str, torch.Tensor]:
        """The params dict of :func:`splat.rasterize.render` (means, quats, scales = log-scales,
        opacities = logits, sh0, shN), every tensor in ``dtype``; means placed in ``cam``'s frame."""
        rng = np.random.default_rng(self.seed)
        n = self.n
        tan_x = 0.5 * cam.width / cam.fx + abs(cam.cx - 0.5 * cam.width) / cam.fx
        tan_y = 0.5 * cam.height / cam.fy + abs(cam.cy - 0.5 * cam.height) / cam.fy
        tan_x, tan_y = min(tan_x, 1e3), min(tan_y, 1e3)
        x_cam = np.zeros((n, 3))
        for i, kind in enumerate(self.mean_kinds):
            if kind == "front":
                z = 10.0 ** rng.uniform(-1.5, 1.3)
            elif kind == "behind":
                z = -(10.0 ** rng.uniform(-3, 1))
            elif kind == "straddle":
                z = rng.uniform(-0.05, 0.05)
            elif kind == "on_near":
                z = near
            elif kind == "off_frustum":
                z = 10.0 ** rng.uniform(-1, 1)
            else:  # far
                z = 10.0 ** rng.uniform(2, 4)
            spread = 3.0 if kind == "off_frustum" else 1.1
            u = rng.uniform(-spread, spread, 2)
            x_cam[i] = ((cam.cx - 0.5 * cam.width) / cam.fx * -1 + u[0] * tan_x) * abs(z), \
                       ((cam.cy - 0.5 * cam.height) / cam.fy * -1 + u[1] * tan_y) * abs(z), z
        means = cam.to_world(x_cam)
        scales = np.zeros((n, 3))
        for i, kind in enumerate(self.scale_kinds):
            base = rng.uniform(math.log(1e-3), math.log(1.0))
            scales[i] = {
                "normal": base + rng.normal(0.0, 0.3, 3),
                "mixed": rng.uniform(math.log(1e-8), math.log(1e3), 3),
                "tiny": np.full(3, math.log(1e-8)),
                "huge": np.full(3, math.log(1e3)),
                "needle": np.array([base, math.log(1e-8), math.log(1e-8)]),
                "disc": np.array([base, base, math.log(1e-8)]),
                "plus40": np.full(3, 40.0),
                "minus40": np.full(3, -40.0),
            }[kind]
        quats = rng.normal(size=(n, 4))
        for i, kind in enumerate(self.quat_kinds):
            quats[i] *= {"random": 1.0, "zero": 0.0, "tiny": 1e-30, "huge": 1e30}[kind]
        opac = np.array([{"normal": rng.normal(0.0, 2.0), "plus50": 50.0, "minus50": -50.0}[k]
                         for k in self.opacity_kinds])
        nb = (self.sh_degree + 1) ** 2 - 1
        sh0 = rng.uniform(-1.0, 1.0, (n, 1, 3))
        shn = 0.2 * rng.normal(size=(n, max(nb, 0), 3))
        out = {"means": means, "quats": quats, "scales": scales, "opacities": opac, "sh0": sh0, "shN": shn}
        # float64 -> dtype (float32 rounds 1e30 quaternions to float32's 1e30: still finite)
        return {k: torch.as_tensor(v, dtype=dtype).reshape((n,) + np.shape(v)[1:]) for k, v in out.items()}


@st.composite
def gaussians(draw, min_n: int = 0, max_n: int = 64, valid: bool = False, max_sh_degree: int = 1
              ) -> GaussianSpec:
    """Gaussians with hard cases mixed in (module docstring). ``valid=True`` keeps log-scales in
    [log 1e-8, log 1e3] (no +-40): what a training run can legitimately hold."""
    n = draw(st.integers(min_n, max_n))
    scale_kinds = VALID_SCALE_KINDS if valid else SCALE_KINDS

    def kinds(options):
        return tuple(draw(st.lists(st.sampled_from(options), min_size=n, max_size=n)))

    return GaussianSpec(kinds(MEAN_KINDS), kinds(scale_kinds), kinds(QUAT_KINDS), kinds(OPACITY_KINDS),
                        draw(seeds), draw(st.integers(0, max_sh_degree)))


# ------------------------------------------------------------------------- projected 2D splats


@dataclass(frozen=True)
class Splat2DSpec:
    """Projected Gaussians for the compositor: n of them on a width x height image, with per
    Gaussian a regime for its 2D mean, covariance, opacity and radius."""

    width: int
    height: int
    mean_kinds: tuple[str, ...]
    cov_kinds: tuple[str, ...]
    opacity_kinds: tuple[str, ...]
    radius_kinds: tuple[str, ...]
    n_features: int = 9
    n_median: int = 3
    depth_ties: bool = False
    seed: int = 0

    def build(self, dtype: torch.dtype = torch.float64):
        """(means2d [N, 2], conics [N, 3], opacities [N], features [N, C], depths [N], radii [N]
        int32, background [C], median_features [N, M]) -- float tensors in ``dtype``, conics the
        inverse of a symmetric positive definite covariance (as projection makes them)."""
        rng = np.random.default_rng(self.seed)
        n, w, h = len(self.mean_kinds), self.width, self.height
        means = np.zeros((n, 2))
        for i, kind in enumerate(self.mean_kinds):
            if kind == "inside":
                means[i] = rng.uniform([0, 0], [w, h])
            elif kind == "pixel_centre":  # exactly on a pixel centre: power = 0
                means[i] = rng.integers(0, [w, h]) + 0.5
            elif kind == "near_edge":
                means[i] = rng.uniform([-5, -5], [w + 5, h + 5])
            else:  # far off the image
                means[i] = rng.choice([-1, 1], 2) * 10.0 ** rng.uniform(2, 6, 2) + [w / 2, h / 2]
        cov = np.zeros((n, 2, 2))
        for i, kind in enumerate(self.cov_kinds):
            sig = {"normal": 10.0 ** rng.uniform(-0.5, 1.0), "thin": 10.0 ** rng.uniform(-3, -1),
                   "huge": 10.0 ** rng.uniform(2, 4), "needle": 10.0 ** rng.uniform(0, 3)}[kind]
            L = rng.normal(size=(2, 2)) * sig
            if kind == "needle":  # rank one plus the low-pass: a long thin ellipse
                L[:, 1] = 0.0
            cov[i] = L @ L.T + (0.3 if kind != "thin" else 1e-4) * np.eye(2)
        inv = np.linalg.inv(cov)
        conics = np.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1)
        opac = np.array([{"normal": rng.uniform(0.01, 0.95), "zero": 0.0, "one": 1.0, "max": 0.99,
                          "threshold": 1.0 / 255.0}[k] for k in self.opacity_kinds])
        lam = np.linalg.eigvalsh(cov)[:, 1] if n else np.zeros(0)
        radii = np.ceil(3.0 * np.sqrt(lam))
        for i, kind in enumerate(self.radius_kinds):
            radii[i] = {"fit": radii[i], "culled": 0.0, "huge": 1e8, "small": 1.0}[kind]
        depths = 10.0 ** rng.uniform(-2, 4, n)
        if self.depth_ties and n > 1:
            depths[rng.integers(0, n, n // 2)] = depths[0]
        feats = rng.uniform(-0.5, 1.5, (n, self.n_features))
        medf = rng.uniform(-1.0, 1.0, (n, self.n_median))
        bg = rng.uniform(0.0, 1.0, self.n_features)
        as_t = lambda a: torch.as_tensor(a, dtype=dtype)  # noqa: E731
        return (as_t(means).reshape(n, 2), as_t(conics).reshape(n, 3), as_t(opac).reshape(n),
                as_t(feats).reshape(n, self.n_features), as_t(depths).reshape(n),
                torch.as_tensor(radii, dtype=torch.int32).reshape(n), as_t(bg),
                as_t(medf).reshape(n, self.n_median))


@st.composite
def splats2d(draw, max_n: int = 64, max_width: int = 24, max_height: int = 18) -> Splat2DSpec:
    """Projected Gaussians with the compositor's hard cases (module docstring)."""
    n = draw(st.integers(0, max_n))

    def kinds(options, weights=None):
        return tuple(draw(st.lists(st.sampled_from(options), min_size=n, max_size=n)))

    return Splat2DSpec(
        draw(st.integers(1, max_width)), draw(st.integers(1, max_height)),
        kinds(("inside", "inside", "pixel_centre", "near_edge", "far")),
        kinds(("normal", "normal", "thin", "huge", "needle")),
        kinds(("normal", "normal", "normal", "zero", "one", "max", "threshold")),
        kinds(("fit", "fit", "fit", "culled", "huge", "small")),
        draw(st.sampled_from((3, 4, 9))), draw(st.integers(1, 3)), draw(st.booleans()), draw(seeds))


# ------------------------------------------------------------------------ depth and normal maps


@dataclass(frozen=True)
class MapSpec:
    """An H x W prior: a smooth surface plus damage -- rectangles of holes (0), single-pixel
    spikes (x1e3), NaN and +-Inf regions."""

    height: int
    width: int
    base_depth: float = 2.0
    holes: int = 0
    spikes: int = 0
    nans: int = 0
    infs: int = 0
    seed: int = 0

    def _damage(self, out: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        h, w = self.height, self.width
        for count, value in ((self.holes, 0.0), (self.nans, np.nan), (self.infs, np.inf)):
            for _ in range(count):
                r0, c0 = rng.integers(0, h), rng.integers(0, w)
                r1, c1 = r0 + rng.integers(1, max(2, h // 2)), c0 + rng.integers(1, max(2, w // 2))
                sign = rng.choice([-1.0, 1.0]) if np.isinf(value) else 1.0
                out[r0:r1, c0:c1] = sign * value
        for _ in range(self.spikes):
            r, c = rng.integers(0, h), rng.integers(0, w)
            out[r, c] = out[r, c] * 1e3 if out.ndim == 2 else -out[r, c]  # depth x1e3, normal flipped
        return out

    def depth(self) -> np.ndarray:
        """[H, W] float32 z-depth in metres (> 0 where not damaged): a tilted plane's depth."""
        rng = np.random.default_rng(self.seed)
        i, j = np.meshgrid(np.arange(self.height), np.arange(self.width), indexing="ij")
        g = rng.uniform(-0.3, 0.3, 2) / max(self.height, self.width)
        d = self.base_depth * (1.0 + g[0] * i + g[1] * j) + 0.01 * rng.normal(size=i.shape)
        return self._damage(np.maximum(d, 1e-3 * self.base_depth), rng).astype(np.float32)

    def normal(self) -> np.ndarray:
        """[H, W, 3] float32 unit camera-frame normals facing the camera (n_z < 0) where not damaged."""
        rng = np.random.default_rng(self.seed + 1)
        n = rng.normal(size=(self.height, self.width, 3)) * 0.3 + [0.0, 0.0, -1.0]
        n[..., 2] = -np.abs(n[..., 2]) - 1e-3
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        return self._damage(n, rng).astype(np.float32)


@st.composite
def depth_maps(draw, max_height: int = 18, max_width: int = 24, min_side: int = 1, damage: bool = True,
               nan: bool = True) -> MapSpec:
    """Prior-like maps (see :class:`MapSpec`) from 1x1 up to max sizes, with damage."""
    count = st.integers(0, 3) if damage else st.just(0)
    return MapSpec(draw(st.integers(min_side, max_height)), draw(st.integers(min_side, max_width)),
                   draw(log_uniform(1e-2, 1e3)), draw(count), draw(count),
                   draw(count) if nan else 0, draw(count) if nan else 0, draw(seeds))


normal_maps = depth_maps  # the same spec: MapSpec.normal() reads it as a normal map

# ------------------------------------------------------------------------------- line segments


@dataclass(frozen=True)
class LinePairSpec:
    """Two cameras looking at a 3D segment. ``kind``: "general" (any direction), "epipolar" (along
    the baseline, so both projections lie on epipolar lines), "zero" (zero length: a point)."""

    cam_a: CameraSpec
    cam_b: CameraSpec
    p0: tuple[float, float, float]
    direction: tuple[float, float, float]
    length: float
    kind: str = "general"

    def segment(self) -> np.ndarray:
        """[2, 3] world endpoints of the 3D segment."""
        p0 = np.asarray(self.p0, np.float64)
        if self.kind == "zero":
            return np.stack([p0, p0])
        d = np.asarray(self.direction, np.float64)
        if self.kind == "epipolar":
            d = np.asarray(self.cam_b.center, np.float64) - np.asarray(self.cam_a.center, np.float64)
        d = d / np.linalg.norm(d)
        return np.stack([p0, p0 + self.length * d])


@st.composite
def line_pairs(draw, kind: str | None = None) -> LinePairSpec:
    """A 3D segment 0.5..10 m in front of camera a, seen by camera b from a baseline of 0.05..3 m;
    ``kind`` None draws it ("general" most of the time)."""
    kind = kind or draw(st.sampled_from(("general", "general", "general", "epipolar", "zero")))
    w, h = draw(st.integers(32, 640)), draw(st.integers(24, 480))
    f = draw(log_uniform(20.0, 2000.0))
    quat = draw(unit_quats())
    off = st.floats(-100.0, 100.0)
    ca = np.array(draw(st.tuples(off, off, off)))
    cam_a = CameraSpec(w, h, f, f, w / 2, h / 2, quat, tuple(float(c) for c in ca))
    depth = draw(st.floats(0.5, 10.0))
    uv = draw(st.tuples(st.floats(0.2, 0.8), st.floats(0.2, 0.8)))
    x_cam = np.array([(uv[0] * w - w / 2) / f * depth, (uv[1] * h - h / 2) / f * depth, depth])
    p0 = cam_a.to_world(x_cam[None])[0]
    base_dir = np.array(draw(st.tuples(*[st.floats(-1.0, 1.0)] * 3)))
    if np.linalg.norm(base_dir) < 1e-3:
        base_dir = np.array([1.0, 0.0, 0.0])
    cb = ca + draw(st.floats(0.05, 3.0)) * base_dir / np.linalg.norm(base_dir)
    # camera b looks at the segment's first point (plus a small offset) from its own centre
    R_b = look_at(cb, p0 + np.array(draw(st.tuples(*[st.floats(-0.2, 0.2)] * 3))))
    q_b = _quat_from_rotation(R_b)
    cam_b = CameraSpec(w, h, f, f, w / 2, h / 2, q_b, tuple(float(c) for c in cb))
    direction = draw(st.tuples(*[st.floats(-1.0, 1.0)] * 3))
    if np.linalg.norm(direction) < 1e-3:
        direction = (0.0, 0.0, 1.0)
    return LinePairSpec(cam_a, cam_b, tuple(float(c) for c in p0), tuple(float(c) for c in direction),
                        draw(st.floats(0.05, 2.0)), kind)


def _quat_from_rotation(R: np.ndarray) -> tuple[float, float, float, float]:
    """wxyz unit quaternion of a rotation matrix (Shepperd's method)."""
    m = np.asarray(R, np.float64)
    tr = np.trace(m)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = (0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s)
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        v = [0.0, 0.0, 0.0]
        v[i] = 0.25 * s
        v[j] = (m[j, i] + m[i, j]) / s
        v[k] = (m[k, i] + m[i, k]) / s
        q = ((m[k, j] - m[j, k]) / s, *v)
    q = np.asarray(q) / np.linalg.norm(q)
    return tuple(float(c) for c in q)


# ---------------------------------------------------------------------------------- point sets


@dataclass(frozen=True)
class PlanePointsSpec:
    """Points on the plane n . x + d = 0 (|n| = 1) with Gaussian noise and uniform outliers;
    ``layout``: "plane" (spread over a square patch), "collinear" (on one line in the plane),
    "duplicates" (a few distinct points repeated), "single" (one point repeated)."""

    normal: tuple[float, float, float]
    d: float
    n_points: int
    noise: float
    outlier_frac: float
    extent: float = 2.0
    layout: str = "plane"
    seed: int = 0

    @property
    def unit_normal(self) -> np.ndarray:
        n = np.asarray(self.normal, np.float64)
        return n / np.linalg.norm(n)

    def build(self) -> tuple[np.ndarray, np.ndarray]:
        """(points [N, 3] float64, inlier mask [N])."""
        rng = np.random.default_rng(self.seed)
        n = self.unit_normal
        e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        origin = -self.d * n
        k = self.n_points
        if self.layout == "plane":
            uv = rng.uniform(-self.extent, self.extent, (k, 2))
        elif self.layout == "collinear":
            uv = np.outer(rng.uniform(-self.extent, self.extent, k), rng.normal(size=2))
        elif self.layout == "duplicates":
            uv = rng.uniform(-self.extent, self.extent, (max(1, k // 10), 2))[rng.integers(0, max(1, k // 10), k)]
        else:  # single
            uv = np.repeat(rng.uniform(-self.extent, self.extent, (1, 2)), k, 0)
        pts = origin + uv[:, :1] * e1 + uv[:, 1:] * e2 + rng.normal(0.0, self.noise, (k, 1)) * n
        inlier = rng.random(k) >= self.outlier_frac
        pts[~inlier] += rng.uniform(-1.0, 1.0, (int((~inlier).sum()), 3)) * self.extent
        pts[~inlier] += n * self.extent * rng.choice([-1, 1], (int((~inlier).sum()), 1)) * 0.5
        return pts, inlier


@st.composite
def point_sets(draw, layouts: tuple[str, ...] = ("plane", "plane", "collinear", "duplicates", "single"),
               min_points: int = 3, max_points: int = 400) -> PlanePointsSpec:
    """Plane point sets (see :class:`PlanePointsSpec`), the layout drawn from ``layouts``."""
    normal = draw(directions())
    layout = draw(st.sampled_from(layouts))
    return PlanePointsSpec(tuple(float(c) for c in normal), draw(st.floats(-20.0, 20.0)),
                           draw(st.integers(min_points, max_points)), draw(st.floats(0.0, 0.003)),
                           draw(st.floats(0.0, 0.3)), draw(st.floats(0.5, 5.0)), layout, draw(seeds))
