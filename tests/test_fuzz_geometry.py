"""Property-based fuzzing of the geometry: depth alignment, line triangulation, plane fits, TSDF
meshing and mesh metrics (docs/testing.md, "Fuzzing"; inputs from tests/fuzz_strategies.py).

- depth alignment: ``fit_scale_shift`` recovers a known scale / shift with up to 40 % outliers
  (anchors hidden behind the surface and gross ones in front); ``align_depth_prior`` on a damaged
  prior (holes, spikes, NaN, Inf) never raises and returns a finite fit or a reason;
- lines: two-view triangulation recovers a known 3D segment from its exact projections; degenerate
  pairs (along the baseline, i.e. on epipolar lines, and zero length) are rejected with a reason by
  the matcher, and ``triangulate_matches`` never keeps a non-finite segment and accounts for every row;
- planes: RANSAC fits recover a known plane from noisy coplanar points with outliers; collinear,
  duplicate and single points give finite unit normals (or the documented fallback), no crash;
- TSDF: fusing damaged depth maps gives a finite mesh on the observed surface;
- mesh metrics: identical meshes give Chamfer 0 and F-score 1 (exact point-to-surface mode);
  swapping prediction and GT swaps accuracy with completeness and precision with recall.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
from hypothesis import assume, event, example, given, note
from hypothesis import strategies as st

import fuzz_strategies as fs

# ------------------------------------------------------------------------------ depth alignment


@given(scale=fs.log_uniform(1e-2, 1e2), shift_rel=st.floats(-0.5, 0.5), z_near=fs.log_uniform(0.3, 30.0),
       z_ratio=st.floats(1.5, 10.0), n=st.integers(40, 400), behind=st.floats(0.0, 0.25),
       front=st.floats(0.0, 0.15), noise=st.floats(0.0, 0.002), fit_shift=st.booleans(), seed=fs.seeds)
def test_fit_scale_shift_recovers_a_known_affine_map_under_outliers(scale, shift_rel, z_near, z_ratio, n,
                                                                     behind, front, noise, fit_shift, seed):
    """z = s d + b on the inliers; up to 25 % anchors hidden behind the surface (farther by 10-100 %)
    and 15 % gross outliers in front (30-80 % of the depth): s within 2 %, b within 2 % of the
    median depth, and no hidden anchor is used."""
    from geocues.depth_align import DepthAlignConfig, fit_scale_shift

    rng = np.random.default_rng(seed)
    z = rng.uniform(z_near, z_near * z_ratio, n)
    b = shift_rel * float(np.median(z)) if fit_shift else 0.0
    d = (z - b) / scale
    assume((d > 0).all())
    d = d * (1.0 + noise * rng.normal(size=n))
    z_obs = z.copy()
    kind = rng.random(n)
    hidden = kind < behind
    gross = (kind >= behind) & (kind < behind + front)
    z_obs[hidden] *= 1.0 + rng.uniform(0.1, 1.0, int(hidden.sum()))
    z_obs[gross] *= rng.uniform(0.3, 0.8, int(gross.sum()))
    s_hat, b_hat, used = fit_scale_shift(d, z_obs, DepthAlignConfig(fit_shift=fit_shift), np.random.default_rng(seed))
    note(f"fit s={s_hat:.6g} b={b_hat:.6g}, true s={scale:.6g} b={b:.6g}")
    assert math.isfinite(s_hat) and math.isfinite(b_hat)
    assert s_hat == pytest.approx(scale, rel=0.02)
    assert b_hat == pytest.approx(b, abs=0.02 * float(np.median(z)))
    assert not used[hidden].any(), "anchors hidden behind the surface were used"


def plane_scene(cam: fs.CameraSpec, tilt, depth0: float):
    """Exact z-depth [H, W] of a plane through (0, 0, depth0) (camera frame) with normal
    (tilt_x, tilt_y, -1), and world points on it seen at random pixels."""
    n = np.array([tilt[0], tilt[1], -1.0])
    u = np.arange(cam.width) + 0.5
    v = np.arange(cam.height) + 0.5
    rx = ((u[None, :] - cam.cx) / cam.fx) * np.ones((cam.height, 1))
    ry = ((v[:, None] - cam.cy) / cam.fy) * np.ones((1, cam.width))
    with np.errstate(divide="ignore", invalid="ignore"):
        z = (-depth0) / (n[0] * rx + n[1] * ry + n[2])  # n . (z r) = n . (0, 0, depth0)
    return np.where(np.isfinite(z) & (z > 0.05) & (z < 50.0), z, 0.0)


@given(cam=fs.cameras(max_width=64, max_height=48, min_focal=10.0, max_focal=100.0, min_width=8, min_height=6),
       tilt=st.tuples(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5)), depth0=st.floats(0.5, 5.0),
       scale=fs.log_uniform(0.1, 10.0), shift=st.floats(-0.3, 0.3), damage=fs.depth_maps(), seed=fs.seeds)
def test_align_depth_prior_on_a_damaged_prior_never_raises(cam, tilt, depth0, scale, shift, damage, seed):
    """A prior with holes, spikes, NaN and Inf regions: align_depth_prior returns ok with a finite
    fit near the truth, or not ok with a reason; it never raises."""
    from geocues.depth_align import DepthAlignConfig, align_depth_prior

    z = plane_scene(cam, tilt, depth0)
    prior = np.where(z > 0, (z - shift) / scale, 0.0)
    prior = np.where(prior > 0, prior, 0.0)
    spec = fs.MapSpec(cam.height, cam.width, 1.0, damage.holes, damage.spikes, damage.nans, damage.infs, damage.seed)
    bad = spec._damage(np.ones((cam.height, cam.width)), np.random.default_rng(damage.seed))
    prior = np.where(bad == 1.0, prior, np.where(np.isfinite(bad) & (bad > 1), prior * 1e3, bad)).astype(np.float32)
    rng = np.random.default_rng(seed)
    rows, cols = np.nonzero(z > 0)
    assume(len(rows) > 0)
    k = rng.choice(len(rows), size=min(300, len(rows)), replace=True)
    x_cam = np.stack([(cols[k] + 0.5 - cam.cx) / cam.fx, (rows[k] + 0.5 - cam.cy) / cam.fy, np.ones(len(k))], 1)
    anchors = cam.to_world(x_cam * z[rows[k], cols[k], None])
    res = align_depth_prior(cam.scene_camera(0), prior, anchors, DepthAlignConfig(min_anchors=20), seed=seed)
    event("aligned" if res.ok else f"skipped: {res.reason.split(' (')[0]}")
    if res.ok:
        assert math.isfinite(res.scale) and math.isfinite(res.shift) and res.scale > 0
        assert math.isfinite(res.residual_median_m) and math.isfinite(res.residual_p90_m)
        out = res.apply(np.nan_to_num(prior, nan=0.0, posinf=0.0, neginf=0.0))
        assert np.isfinite(out).all()
    else:
        assert res.reason


# ------------------------------------------------------------------------------------- lines


def segments_of(spec: fs.LinePairSpec):
    """(cam_a, cam_b, X [2, 3], seg_a [1, 4], seg_b [1, 4], depths in a [2], depths in b [2])."""
    a, b = spec.cam_a.scene_camera(0), spec.cam_b.scene_camera(1)
    X = spec.segment()
    ua, za = a.project(X)
    ub, zb = b.project(X)
    return a, b, X, ua.reshape(1, 4), ub.reshape(1, 4), za, zb


@given(spec=fs.line_pairs(kind="general"))
def test_triangulation_recovers_a_known_line(spec):
    """A segment in front of both cameras, not degenerate by the matcher's checks (>= 3 deg from
    the epipolar direction, >= 1 deg triangulation angle): both endpoints recovered (they follow
    a's rays exactly), or the row rejected as lying along the viewing rays of both views."""
    from geocues.lines import LineConfig
    from geocues.lines.match import epipolar_angle, ray_plane_angle
    from geocues.lines.triangulate import triangulate_matches

    a, b, X, sa, sb, za, zb = segments_of(spec)
    assume((za > 0.05).all() and (zb > 0.05).all())
    cfg = LineConfig(max_depth_m=1e3)
    e_a = a.K @ (a.R @ b.center + a.t)
    e_b = b.K @ (b.R @ a.center + b.t)
    assume(epipolar_angle(sa, e_a)[0] >= cfg.min_epipolar_angle_deg and epipolar_angle(sb, e_b)[0] >= cfg.min_epipolar_angle_deg)
    assume(min(ray_plane_angle(sa, a, sb, b)[0], ray_plane_angle(sb, b, sa, a)[0]) >= cfg.min_tri_angle_deg)
    Y, ok, counts = triangulate_matches(sa, a, sb, b, cfg)
    event("kept" if ok[0] else "rejected: " + ", ".join(k for k, v in counts.items() if v))
    if ok[0]:
        np.testing.assert_allclose(Y[0], X, rtol=0, atol=1e-6 * (1.0 + np.abs(X).max()))
    else:
        assert counts == {"behind_camera": 0, "too_far": 0, "ray_aligned": 1}, counts


@given(spec=fs.line_pairs(kind="epipolar") | fs.line_pairs(kind="zero"))
def test_degenerate_line_pairs_are_rejected_with_a_reason(spec):
    """Along the baseline (the projections lie on epipolar lines) or zero length: the matcher never
    returns the pair; when it is a candidate it is counted under a rejection reason."""
    from geocues.lines import LineConfig
    from geocues.lines.detect import Segments2D
    from geocues.lines.match import match_pair
    from geocues.lines.triangulate import triangulate_matches

    a, b, X, sa, sb, za, zb = segments_of(spec)
    assume((za > 0.05).all() and (zb > 0.05).all())
    assume(np.isfinite(sa).all() and np.isfinite(sb).all())
    cfg = LineConfig(matcher="epipolar")
    desc = np.zeros((1, 32), np.uint8)
    ia, ib, counts = match_pair(Segments2D(sa, np.zeros(1, np.uint8), desc, np.zeros((1, 3), np.float32)),
                                Segments2D(sb, np.zeros(1, np.uint8), desc, np.zeros((1, 3), np.float32)), a, b, cfg)
    event(f"{spec.kind}: " + ("not a candidate" if counts["candidates"] == 0 else
                              ", ".join(k for k, v in counts.items() if v and k != "candidates")))
    assert len(ia) == 0 and len(ib) == 0, counts
    rejected = sum(v for k, v in counts.items() if k != "candidates")
    assert rejected == counts["candidates"], counts
    # triangulate_matches on its own rejects them too (the planes are parallel: no finite point),
    # under "behind_camera", the label it gives every non-finite row
    Y, ok, counts_t = triangulate_matches(sa, a, sb, b, LineConfig(max_depth_m=1e3))
    assert not ok.any() and sum(counts_t.values()) == 1, counts_t


@given(spec=fs.line_pairs(), jitter=st.floats(0.0, 50.0), swap=st.booleans(), seed=fs.seeds)
def test_triangulate_matches_keeps_only_finite_segments_and_counts_every_row(spec, jitter, swap, seed):
    """Any pair of segments (true, jittered, degenerate, swapped endpoints, mismatched): each row
    is kept or counted under exactly one reason; kept segments are finite, in front of both
    cameras and within max_depth_m."""
    from geocues.lines import LineConfig
    from geocues.lines.triangulate import triangulate_matches

    a, b, X, sa, sb, za, zb = segments_of(spec)
    assume(np.isfinite(sa).all() and np.isfinite(sb).all())
    rng = np.random.default_rng(seed)
    segs_a = np.concatenate([sa, sa + rng.normal(0.0, jitter, (1, 4)), sa[:, [0, 1, 0, 1]]])
    segs_b = np.concatenate([sb, sb + rng.normal(0.0, jitter, (1, 4)), sb[:, [2, 3, 0, 1]] if swap else sb])
    cfg = LineConfig(max_depth_m=50.0)
    Y, ok, counts = triangulate_matches(segs_a, a, segs_b, b, cfg)
    assert int(ok.sum()) + sum(counts.values()) == len(segs_a), counts
    assert np.isfinite(Y[ok]).all()
    for cam in (a, b):
        _, z = cam.project(Y[ok].reshape(-1, 3))
        assert (z > 0).all() and (z <= cfg.max_depth_m).all()


# ------------------------------------------------------------------------------------ planes


@given(spec=fs.point_sets(layouts=("plane",), min_points=20))
def test_plane_fits_recover_a_known_plane(spec):
    """RANSAC (Open3D segment_plane) and the group-weighted RANSAC both recover n . x + d = 0 from
    noisy points with up to 30 % outliers: the normal within 1 deg + noise / extent, d within
    5 noise + 1 mm (up to the sign of (n, d))."""
    from geocues.plane_fit import fit_plane_groups, fit_plane_ransac

    pts, inlier = spec.build()
    assume(inlier.sum() >= 10 and inlier.mean() >= 0.7)
    n_true, d_true = spec.unit_normal, spec.d
    dist = max(4.0 * spec.noise, 0.005)
    for name, (n, d, mask) in (("ransac", fit_plane_ransac(pts, dist, seed=0)),
                               ("groups", fit_plane_groups(pts, np.arange(len(pts)), dist, np.random.default_rng(0))[:3])):
        assert np.isfinite(n).all() and math.isfinite(d) and abs(np.linalg.norm(n) - 1) < 1e-9, name
        sign = 1.0 if n @ n_true >= 0 else -1.0
        angle = math.degrees(math.acos(min(1.0, abs(float(n @ n_true)))))
        assert angle <= 1.0 + math.degrees(spec.noise / spec.extent) * 10, (name, angle)
        assert abs(sign * d - d_true) <= 0.05 * (1 + abs(d_true)) * angle + 5 * spec.noise + 1e-3, (name, d, d_true)
        assert mask[inlier].mean() >= 0.9, name


@given(spec=fs.point_sets(layouts=("collinear", "duplicates", "single"), max_points=100))
# regression (fixed in geocues/plane_fit.py): leaving one group of 65 collinear points out, the
# anchored plane's normal matrix was singular next to its absolute 1e-12 ridge: LinAlgError
@example(spec=fs.PlanePointsSpec(normal=(0.3313339565093456, -0.6801129512103445, 0.0026224330033275877),
                                 d=0.0026224330033275877, n_points=65, noise=0.0026224330033275877, outlier_frac=0.0,
                                 extent=1.4975710904627448, layout="collinear", seed=65))
def test_plane_fits_on_degenerate_points_are_finite(spec):
    """Collinear, duplicate and single (repeated) points: no crash, a finite unit normal and a
    finite offset (or the documented fallback: n = (0, 0, 1), d = 0, no inlier), finite
    leave-one-out residuals or NaN where the plane is not pinned down."""
    from geocues.plane_fit import AnchoredPlane, fit_plane_groups, fit_plane_ransac, loo_group_residuals

    pts, _ = spec.build()
    for name, (n, d, mask) in (("ransac", fit_plane_ransac(pts, 0.01, seed=0)),
                               ("groups", fit_plane_groups(pts, np.arange(len(pts)), 0.01, np.random.default_rng(0))[:3])):
        assert np.isfinite(n).all() and math.isfinite(d) and abs(np.linalg.norm(n) - 1) < 1e-9, (name, n, d)
        assert mask.dtype == bool and mask.shape == (len(pts),)
    groups = np.arange(len(pts)) % max(1, len(pts) // 3)
    ap = AnchoredPlane(pts, np.full(len(pts), 1.0 / len(pts)), spec.unit_normal, sigma=0.01, prior_normal_std_rad=0.2)
    assert np.isfinite(ap.n).all() and math.isfinite(ap.d) and np.isfinite(ap.std_at(pts)).all()
    _, r = loo_group_residuals(pts, groups, spec.unit_normal, sigma=0.01, max_std=0.015)
    assert not np.isinf(r).any()


# ----------------------------------------------------------------------------------- meshing


@given(cam=fs.cameras(max_width=24, max_height=18, min_focal=5.0, max_focal=200.0, far_centre=False),
       depth=fs.depth_maps(), base=st.floats(0.3, 5.0), voxel=st.floats(0.02, 0.2), views=st.integers(1, 3))
# property fix: a 1x1 image's one depth stands for a 0.36 m wide footprint; the bound now includes it
@example(cam=fs.CameraSpec(1, 1, 5.623413251903491, 5.623413251903491, 0.5, 0.5), depth=fs.MapSpec(1, 1),
         base=2.0, voxel=0.03125, views=1)
def test_tsdf_fusion_of_damaged_depth_gives_a_finite_mesh_on_the_surface(cam, depth, base, voxel, views):
    """Holes, spikes, NaN and Inf pixels: fusion never raises, the mesh is finite, and its vertices
    lie near the back-projected valid depth (within the truncation distance plus a voxel)."""
    from scipy.spatial import cKDTree

    from splat.mesh import TSDFConfig, backproject, fuse_views

    d = fs.MapSpec(cam.height, cam.width, base, depth.holes, depth.spikes, depth.nans, depth.infs, depth.seed).depth()
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = cam.R, cam.t
    cfg = TSDFConfig(voxel_size=voxel, block_count=16, depth_max=10.0)
    mesh = fuse_views([(d, None, cam.K, T)] * views, cfg, progress=False)
    V = np.asarray(mesh.vertices)
    event("mesh: " + ("empty" if len(V) == 0 else "non-empty"))
    assert np.isfinite(V).all()
    valid = np.where(np.isfinite(d) & (d > 0) & (d <= cfg.depth_max), d, 0.0)
    if len(V):
        P = backproject(valid, cam.K, T)
        dist, _ = cKDTree(P).query(V)
        # a pixel's depth stands for its whole footprint: up to a pixel diagonal from its centre
        footprint = float(valid.max()) * math.hypot(1.0 / cam.fx, 1.0 / cam.fy)
        assert dist.max() <= cfg.trunc + 2.0 * voxel + footprint, dist.max()


@st.composite
def meshes(draw, max_triangles: int = 24):
    """Triangle soups of 1..max_triangles triangles in a box of 0.1..10 m at up to 10 km from the
    origin, with duplicate vertices and zero-area triangles mixed in (total area > 0)."""
    from evaluation.mesh_metrics import TriMesh

    rng = np.random.default_rng(draw(fs.seeds))
    n_tri = draw(st.integers(1, max_triangles))
    size = draw(fs.log_uniform(0.1, 10.0))
    offset = np.array(draw(st.tuples(*[st.floats(-1e4, 1e4)] * 3)))
    V = rng.uniform(0.0, size, (3 * n_tri, 3)) + offset
    F = np.arange(3 * n_tri).reshape(n_tri, 3)
    k = draw(st.integers(0, n_tri - 1))
    F[:k, 2] = F[:k, 1]  # zero-area triangles (a repeated vertex)
    return TriMesh(V, F, name="fuzz")


def surface_cfg(n: int = 2000):
    from evaluation.mesh_metrics import MeshMetricsConfig

    return MeshMetricsConfig(n_samples=n, mode="surface", crop_to_gt_bounds=False, seed=0)


@given(mesh=meshes())
def test_identical_meshes_have_zero_chamfer_and_unit_f_score(mesh):
    """Chamfer 0 to float32 precision (Open3D's RaycastingScene holds float32 vertices and queries:
    the exact mode's error is ~4e-8 of the coordinates' magnitude, 0.4 mm at 10 km), F = 1."""
    from evaluation.mesh_metrics import evaluate_meshes

    r = evaluate_meshes(mesh, mesh, surface_cfg())
    scale = 1.0 + float(np.abs(mesh.vertices).max())
    assert r.chamfer_l1 <= 1e-6 * scale and r.accuracy <= 1e-6 * scale and r.completeness <= 1e-6 * scale
    assert r.precision == 1.0 and r.recall == 1.0 and r.f_score == 1.0


@given(a=meshes(), b=meshes(), shift=st.floats(0.0, 0.2))
def test_mesh_metrics_swap_prediction_and_ground_truth(a, b, shift):
    """evaluate(A, B) and evaluate(B, A) measure the same distances with other samples: accuracy
    and completeness swap, and precision and recall, within sampling error (6 standard errors)."""
    from evaluation.mesh_metrics import TriMesh, evaluate_meshes

    b = TriMesh(a.vertices + shift, a.faces, "shifted") if shift > 0.1 else b
    r1, r2 = evaluate_meshes(a, b, surface_cfg()), evaluate_meshes(b, a, surface_cfg())
    n = surface_cfg().n_samples

    def close_means(x, y, xs, ys):
        se = math.sqrt((np.var(xs) + np.var(ys)) / n)
        assert x == pytest.approx(y, abs=6.0 * se + 1e-6 * (1.0 + abs(x)))

    close_means(r1.accuracy, r2.completeness, r1.dist_pred_to_gt, r2.dist_gt_to_pred)
    close_means(r1.completeness, r2.accuracy, r1.dist_gt_to_pred, r2.dist_pred_to_gt)
    for p, q in ((r1.precision, r2.recall), (r1.recall, r2.precision)):
        se = math.sqrt((p * (1 - p) + q * (1 - q)) / n)
        assert p == pytest.approx(q, abs=6.0 * se + 1e-9)
    assert r1.chamfer_l1 >= 0 and 0.0 <= r1.f_score <= 1.0
