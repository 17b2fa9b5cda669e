"""`geocues mvs`: weight-free dense depth from the posed images themselves (an extension; the paper
takes depth from a monocular network).

Per reference view, a plane sweep (Collins 1996) over ``n_depths`` fronto-parallel planes, uniform
in inverse depth between the near and far bounds of the SfM points the view sees. For each plane,
each of ``n_neighbours`` source views is warped into the reference view (bilinear) and compared by
zero-mean normalised cross-correlation over a ``window`` × ``window`` patch:

    NCC(x, d) = cov(I_r, I_j∘w_d) / sqrt(var(I_r) · var(I_j∘w_d) + ε)

The score of a depth is the mean of the ``top_k`` best neighbours (occlusion-robust, as in
COLMAP's and ACMM's view selection); depth is the arg-max with a parabolic sub-plane refinement.
NCC is undefined on textureless patches: pixels whose reference patch has a standard deviation
below ``min_texture`` get no depth, and so do pixels whose best score is below ``min_ncc``.
A second pass keeps a depth only where it is geometrically consistent with at least
``min_consistent`` neighbours: reprojected into the neighbour, the neighbour's own depth lands
back within ``max_reproj_px`` pixels and ``max_rel_depth`` relative depth (forward–backward check,
as in COLMAP's fusion and PGSR's filtering).

With ``planar_fill`` the textureless pixels the sweep leaves empty are then completed from the planes
of a Delaunay triangulation of each view's consistent depth and kept only where they pass the same
check (geocues/mvs_fill.py, after ACMP's planar prior).

Output: ``OUT`` is a scene folder (images, sparse, gt linked to the source scene) whose
``priors/depth/<stem>.npy`` are the filtered MVS depths in the scene's unit (0 = no depth) at image size and
``priors/depth_conf/<stem>.npy`` their scores in [0, 1] (a planar fill's: half of ``min_ncc``, under every swept score); ``geocues extract OUT`` then aligns them,
builds plane cues from them and `splat train` uses them as depth priors.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
import torch
import torch.nn.functional as F

from geocues.atomic import atomic_path, check_not_input, check_output_dir, locks_output
from geocues.scene import Camera, Scene
from geocues.sfm import link_scene

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class MvsConfig:
    """Options of `geocues mvs`."""

    max_size: int = 320
    """longest image side the sweep works at (pixels); depths are upsampled to image size."""
    n_depths: int = 96
    """fronto-parallel planes per view, uniform in inverse depth."""
    n_neighbours: int = 4
    """source views per reference view."""
    top_k: int = 2
    """a depth's score is the mean NCC of its best top_k neighbours."""
    window: int = 7
    """NCC patch size (pixels at the working size; odd)."""
    min_texture: float = 0.01
    """minimum standard deviation of the reference patch (intensity in [0, 1]); below it NCC is undefined."""
    min_ncc: float = 0.5
    """minimum score of a kept depth."""
    min_consistent: int = 2
    """neighbours that must agree with a depth (forward-backward reprojection)."""
    max_reproj_px: float = 1.0
    """forward-backward reprojection tolerance (pixels at the working size)."""
    max_rel_depth: float = 0.01
    """forward-backward relative depth tolerance."""
    min_angle_deg: float = 2.0
    """minimum triangulation angle of a neighbour at the view's median depth."""
    max_angle_deg: float = 40.0
    """maximum angle between the optical axes of a view and its neighbour."""
    planar_fill: bool = True
    """complete the textureless pixels from the planes of a Delaunay triangulation of each view's consistent
    depth, then keep a fill only where it passes the same consistency check (geocues/mvs_fill.py; after ACMP's
    planar prior, an extension; docs/geocues.md measures it); --no-planar-fill keeps the sweep's depths alone."""
    fill_stride: int = 8
    """one consistent depth per fill_stride x fill_stride cell is triangulated (pixels at the working size)."""
    fill_max_edge: float = 2.0
    """a triangle whose longest 3D edge exceeds this times its mean depth gives no plane (a long sliver; depth jumps are left to the consistency check)."""
    fill_min_cos: float = 0.25
    """a triangle whose plane the view sees at |cos| below this (grazing) gives no plane."""

    def validate(self) -> None:
        from geocues.extract_checks import check_finite

        check_finite(self)  # --min-ncc nan was accepted (every comparison with NaN is False)
        if self.max_size < 16 or self.n_depths < 8 or self.window < 3 or self.window % 2 == 0:
            raise ValueError(f"mvs: need max_size >= 16, n_depths >= 8 and an odd window >= 3 "
                             f"(got {self.max_size}, {self.n_depths}, {self.window})")
        if not 1 <= self.top_k <= self.n_neighbours:
            raise ValueError(f"mvs: need 1 <= top_k <= n_neighbours (got {self.top_k}, {self.n_neighbours})")
        if not 0 <= self.min_consistent <= self.n_neighbours:
            raise ValueError(f"mvs: min_consistent must be in 0..n_neighbours, got {self.min_consistent}")
        if self.planar_fill and self.min_consistent < 1:
            raise ValueError("mvs: the planar fill keeps a fill only where neighbours agree: it needs --min-consistent >= 1 "
                             "(or pass --no-planar-fill)")
        if self.fill_stride < 1 or not self.fill_max_edge > 0 or not 0 <= self.fill_min_cos < 1:
            raise ValueError(f"mvs: need fill_stride >= 1, fill_max_edge > 0 and 0 <= fill_min_cos < 1 "
                             f"(got {self.fill_stride}, {self.fill_max_edge}, {self.fill_min_cos})")


def depth_bounds(scene: Scene, i: int) -> tuple[float, float]:
    """Near / far sweep bounds of view ``i``: the 1st / 99th percentile depth of the SfM points it
    sees, widened by 20 %; without (10) points, 0.3 m to 3 × the camera spread (at least 5 m)."""
    cam = scene.cameras[i]
    pts = scene.points.xyz
    if len(pts):
        uv, z = cam.project(pts)
        z = z[(z > 1e-3) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)]
        if len(z) >= 10:
            return float(np.percentile(z, 1)) * 0.8, float(np.percentile(z, 99)) * 1.2
    centres = np.stack([c.center for c in scene.cameras])
    spread = float(np.linalg.norm(centres - centres.mean(0), axis=1).max()) if len(centres) > 1 else 1.0
    return 0.3, max(5.0, 3.0 * spread)


def select_neighbours(cameras: Sequence[Camera], i: int, cfg: MvsConfig, depth: float,
                      candidates: list[int] | None = None) -> list[int]:
    """Up to ``n_neighbours`` of ``cameras`` around camera ``i`` (among ``candidates``, default all):
    optical axes within ``max_angle_deg``, a triangulation angle at ``depth`` of at least
    ``min_angle_deg``, ranked by closeness of that angle to 10° and of the axes."""
    ci, zi = cameras[i].center, cameras[i].R[2]
    target = ci + depth * zi
    scored = []
    for j in range(len(cameras)) if candidates is None else candidates:
        cj = cameras[j]
        if j == i:
            continue
        axis = np.degrees(np.arccos(np.clip(zi @ cj.R[2], -1, 1)))
        a, b = ci - target, cj.center - target
        tri = np.degrees(np.arccos(np.clip(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12), -1, 1)))
        if axis <= cfg.max_angle_deg and tri >= cfg.min_angle_deg:
            scored.append((abs(tri - 10.0) + 0.5 * axis, j))
    return [j for _, j in sorted(scored)[: cfg.n_neighbours]]


def _gray(img: np.ndarray) -> torch.Tensor:
    g = torch.from_numpy(np.ascontiguousarray(img)).float()
    g = g / 255.0 if img.dtype == np.uint8 else g
    return (0.299 * g[..., 0] + 0.587 * g[..., 1] + 0.114 * g[..., 2])[None, None]  # [1, 1, H, W]


def _box(x: torch.Tensor, w: int) -> torch.Tensor:
    return F.avg_pool2d(x, w, stride=1, padding=w // 2, count_include_pad=False)


def ncc(ref: torch.Tensor, src: torch.Tensor, w: int, min_var: float = 1e-9, ref_stats=None) -> torch.Tensor:
    """Zero-mean NCC over w × w patches of [B, 1, H, W] images (``ref`` broadcasts), in [-1, 1];
    0 where either patch is flat (variance < ``min_var``: NCC undefined), so finite everywhere. No ε
    in the denominator: one would swamp the faint texture of indoor walls (a patch std of 0.01 is a
    variance of 1e-4). ``ref_stats``: the reference's (mean, variance) patches, computed once."""
    mr, vr = ref_stats if ref_stats is not None else patch_stats(ref, w)
    ms, vs = patch_stats(src, w)
    cov = _box(ref * src, w) - mr * ms
    defined = (vr > min_var) & (vs > min_var)
    denom = torch.sqrt(torch.where(defined, vr * vs, torch.ones_like(vs)))
    return torch.where(defined, cov / denom, torch.zeros_like(cov)).clamp(-1, 1)


def patch_stats(img: torch.Tensor, w: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(mean, variance) over w × w patches of a [B, 1, H, W] image."""
    m = _box(img, w)
    return m, (_box(img * img, w) - m * m).clamp_min(0)


def textureless(variance: torch.Tensor, cfg: MvsConfig) -> torch.Tensor:
    """[H, W] bool: patches whose standard deviation is under ``min_texture`` (``variance``: the
    [1, 1, H, W] patch variance of :func:`patch_stats`), where NCC is undefined — the sweep gives them
    no depth, the planar fill completes them."""
    return torch.sqrt(variance)[0, 0] < cfg.min_texture


def _project(cam_src, R_rel: torch.Tensor, t_rel: torch.Tensor, rays: torch.Tensor, d: torch.Tensor):
    """Pixel coordinates [..., 2] and depth [...] in the source view of points d · rays of the reference."""
    X = (d[..., None] * rays) @ R_rel.T + t_rel
    z = X[..., 2]
    K = torch.as_tensor(cam_src.K, dtype=torch.float32)
    uv = (X @ K.T)[..., :2] / z.clamp_min(1e-6)[..., None]
    return uv, z


def _relative(ref, src) -> tuple[torch.Tensor, torch.Tensor]:
    R = src.R @ ref.R.T
    return torch.as_tensor(R, dtype=torch.float32), torch.as_tensor(src.t - R @ ref.t, dtype=torch.float32)


def _rays(cam) -> torch.Tensor:
    return torch.as_tensor(cam.pixel_rays(), dtype=torch.float32)  # [H, W, 3], z = 1


def _sample(img: torch.Tensor, uv: torch.Tensor, w: int, h: int) -> tuple[torch.Tensor, torch.Tensor]:
    grid = torch.stack([2 * uv[..., 0] / w - 1, 2 * uv[..., 1] / h - 1], -1)[None]
    inside = (grid.abs() <= 1).all(-1)[0]
    return F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False), inside


MVS_PRIORS = {"source": "geocues mvs", "simulated": False,
              "method": "plane-sweep stereo of the posed images (depth in the scene's unit, no normals)"}
"""scene.json's "priors" of a `geocues mvs` scene (`geocues info` advises the mvs recipe for it)."""


def sweep_view(scene: Scene, i: int, neighbours: list[int], bounds: tuple[float, float], cfg: MvsConfig,
               images: dict[int, torch.Tensor]) -> tuple[np.ndarray, np.ndarray]:
    """Plane-sweep depth [H, W] (0 = none) and score [H, W] of view ``i`` (module docstring)."""
    ref = scene.cameras[i]
    H, W = ref.height, ref.width
    if not neighbours:
        return np.zeros((H, W), np.float32), np.zeros((H, W), np.float32)
    rays = _rays(ref)
    inv = torch.linspace(1 / bounds[0], 1 / bounds[1], cfg.n_depths)
    I_r = images[i]
    stats = patch_stats(I_r, cfg.window)
    srcs = [scene.cameras[j] for j in neighbours]
    rel = [_relative(ref, c) for c in srcs]
    R_all = torch.stack([r for r, _ in rel])  # [n, 3, 3]
    t_all = torch.stack([t for _, t in rel])  # [n, 3]
    K_all = torch.as_tensor(np.stack([c.K for c in srcs]), dtype=torch.float32)  # [n, 3, 3]
    wh = torch.as_tensor([[c.width, c.height] for c in srcs], dtype=torch.float32)  # [n, 2]
    stack = torch.cat([images[j] for j in neighbours])  # [n, 1, H', W'] (views share one size)
    scores = torch.empty(cfg.n_depths, H, W)
    for k, d_inv in enumerate(inv):
        X = torch.einsum("nij,hwj->nhwi", R_all, rays / float(d_inv)) + t_all[:, None, None]  # [n, H, W, 3]
        z = X[..., 2]
        uv = torch.einsum("nij,nhwj->nhwi", K_all, X)[..., :2] / z.clamp_min(1e-6)[..., None]
        grid = 2 * uv / wh[:, None, None] - 1
        inside = (grid.abs() <= 1).all(-1) & (z > 1e-3)  # [n, H, W]
        warped = F.grid_sample(stack, grid, mode="bilinear", padding_mode="border", align_corners=False)
        s = ncc(I_r, warped, cfg.window, ref_stats=stats)[:, 0]  # [n, H, W]
        s = torch.where(inside, s, torch.full_like(s, -1.0))
        scores[k] = s.topk(min(cfg.top_k, len(neighbours)), dim=0).values.mean(0)  # a view with fewer neighbours: all
    best = scores.argmax(0)  # [H, W]
    conf = scores.gather(0, best[None])[0]
    # parabolic refinement in inverse depth between the neighbouring planes
    lo, hi = (best - 1).clamp(0, cfg.n_depths - 1), (best + 1).clamp(0, cfg.n_depths - 1)
    s0, s1, s2 = scores.gather(0, lo[None])[0], conf, scores.gather(0, hi[None])[0]
    denom = s0 - 2 * s1 + s2
    offset = torch.where((denom < -1e-6) & (lo != best) & (hi != best), 0.5 * (s0 - s2) / denom,
                         torch.zeros_like(denom)).clamp(-0.5, 0.5)
    step = (inv[-1] - inv[0]) / (cfg.n_depths - 1)
    depth = 1.0 / (inv[best] + offset * step)
    keep = (conf >= cfg.min_ncc) & ~textureless(stats[1], cfg) & torch.isfinite(depth) & (depth > 0)
    return (torch.where(keep, depth, torch.zeros_like(depth)).numpy().astype(np.float32),
            conf.clamp(0, 1).numpy().astype(np.float32))


def consistency_filter(cameras: Sequence[Camera], depths: dict[int, np.ndarray],
                       neighbours: dict[int, list[int]], cfg: MvsConfig) -> dict[int, np.ndarray]:
    """Keep a depth of camera ``i`` (``depths[i]``: z-depth [H, W] in metres, 0 = none) where at
    least ``min_consistent`` of ``neighbours[i]`` agree (forward-backward check)."""
    out = {}
    for i, d_np in depths.items():
        ref = cameras[i]
        d = torch.from_numpy(d_np)
        rays = _rays(ref)
        pix = torch.stack(torch.meshgrid(torch.arange(ref.height) + 0.5, torch.arange(ref.width) + 0.5,
                                         indexing="ij")[::-1], -1)  # [H, W, 2] pixel centres (u, v)
        votes = torch.zeros_like(d, dtype=torch.int32)
        for j in neighbours[i]:
            src = cameras[j]
            R_rel, t_rel = _relative(ref, src)
            uv, z = _project(src, R_rel, t_rel, rays, d)
            d_src, inside = _sample(torch.from_numpy(depths[j])[None, None], uv, src.width, src.height)
            # bilinear mixes 0 (no depth) in: keep only samples whose taps all hold a depth
            valid_src = _sample((torch.from_numpy(depths[j]) > 0).float()[None, None], uv, src.width, src.height)[0]
            d_src = d_src[0, 0]
            R_back, t_back = _relative(src, ref)
            rays_src = torch.cat([(uv - torch.as_tensor(src.K[:2, 2], dtype=torch.float32))
                                  / torch.as_tensor([src.K[0, 0], src.K[1, 1]], dtype=torch.float32),
                                  torch.ones_like(uv[..., :1])], -1)
            uv_back, z_back = _project(ref, R_back, t_back, rays_src, d_src)
            err = (uv_back - pix).norm(dim=-1)
            ok = (inside & (valid_src[0, 0] > 0.999) & (d > 0) & (z > 1e-3) & (err < cfg.max_reproj_px)
                  & ((z_back - d).abs() < cfg.max_rel_depth * d))
            votes += ok.int()
        out[i] = np.where(votes.numpy() >= cfg.min_consistent, d_np, 0).astype(np.float32)
    return out


def fill_textureless(scene: Scene, depths: dict[int, np.ndarray], images: dict[int, torch.Tensor],
                     bounds: dict[int, tuple[float, float]], neighbours: dict[int, list[int]],
                     cfg: MvsConfig) -> dict[int, np.ndarray]:
    """``depths`` (consistent, per view) with their textureless holes filled by
    :func:`geocues.mvs_fill.planar_fill` where the fills pass :func:`consistency_filter` (checked
    with the swept depths beside them); the swept depths are kept as they are."""
    from tqdm.auto import tqdm

    from geocues.mvs_fill import planar_fill

    filled = {}
    for i, d in tqdm(depths.items(), desc="mvs: planar fill", unit="view"):
        flat = textureless(patch_stats(images[i], cfg.window)[1], cfg).numpy()
        fill = planar_fill(d, flat, scene.cameras[i].pixel_rays(), bounds[i], stride=cfg.fill_stride,
                           max_edge=cfg.fill_max_edge, min_cos=cfg.fill_min_cos)
        filled[i] = np.where(d > 0, d, fill).astype(np.float32)
    log.info("mvs: checking the planar fills against %d views' neighbours", len(filled))
    kept = consistency_filter(scene.cameras, filled, neighbours, cfg)
    return {i: np.where(d > 0, d, kept[i]).astype(np.float32) for i, d in depths.items()}


def _sweep_key(scene: Scene, i: int, neighbours: list[int], bounds: tuple[float, float], cfg: MvsConfig) -> str:
    """What view ``i``'s sweep depends on: the sweep's options, the working size, the depth bounds, and the
    poses, intrinsics and image files (name, size, mtime) of the view and of its neighbours."""
    from geocues.texture import config_key, file_stamp

    sweep = {k: getattr(cfg, k) for k in ("max_size", "n_depths", "top_k", "window", "min_texture", "min_ncc")}
    cams = [scene.cameras[j] for j in [i, *neighbours]]
    poses = [np.round(np.concatenate([c.K.ravel(), c.R.ravel(), c.t.ravel()]), 9).tolist() for c in cams]
    files = file_stamp(*[c.image_path for c in cams])
    return config_key(sweep, cams[0].width, cams[0].height, [round(b, 9) for b in bounds], poses, files)


def _load_sweep(path: Path) -> tuple[np.ndarray, np.ndarray] | None:
    """(depth, conf) of a cached sweep, or None (absent or unreadable: then it is computed again)."""
    if not path.is_file():
        return None
    try:
        with np.load(path) as z:
            return z["depth"], z["conf"]
    except (OSError, KeyError, ValueError) as exc:
        log.warning("mvs: cached sweep %s unreadable (%s); sweeping again", path, exc)
        return None


@locks_output("geocues mvs")  # two runs into one OUT mixed their priors
def run(cfg: MvsConfig, scene_dir: str | Path, out_dir: str | Path, *, overwrite: bool = False) -> Path:
    """MVS depth priors of every view of ``scene_dir`` into the scene folder ``out_dir``; returns it."""
    import cv2
    from tqdm.auto import tqdm

    cfg.validate()
    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    if scene_dir.resolve() == out_dir.resolve():
        raise ValueError("geocues mvs writes a new scene folder: pass an OUT other than SCENE")
    check_not_input(out_dir, {"scene": scene_dir})
    report_path = out_dir / "mvs_report.json"
    if report_path.is_file() and not overwrite:
        raise ValueError(f"{out_dir} holds MVS priors already; pass --overwrite to compute them again")
    check_output_dir(out_dir)
    full = Scene.load(scene_dir, check_priors=False)
    size = max(max(c.width, c.height) for c in full.cameras)
    scene = Scene.load(scene_dir, downscale=max(1.0, size / cfg.max_size), check_priors=False)
    t0 = time.perf_counter()
    images = {i: _gray(scene.load_image(i)) for i in tqdm(range(len(scene)), desc="mvs: images", unit="img")}
    depths, conf, neighbours, bounds = {}, {}, {}, {}
    cache_dir, cached = out_dir / "cache" / "mvs_sweep", 0
    for i in tqdm(range(len(scene)), desc="mvs: plane sweep", unit="view"):
        bounds[i] = depth_bounds(scene, i)
        neighbours[i] = select_neighbours(scene.cameras, i, cfg, float(np.sqrt(bounds[i][0] * bounds[i][1])))
        path = cache_dir / f"{scene.cameras[i].stem}_{_sweep_key(scene, i, neighbours[i], bounds[i], cfg)}.npz"
        hit = _load_sweep(path)
        if hit is None:
            hit = sweep_view(scene, i, neighbours[i], bounds[i], cfg, images)
            with atomic_path(path) as tmp, open(tmp, "wb") as f:
                np.savez(f, depth=hit[0], conf=hit[1])
        else:
            cached += 1
        depths[i], conf[i] = hit
    if cached:
        log.info("mvs: %d of %d views' sweeps from %s", cached, len(scene), cache_dir)
    raw_valid = {i: float((d > 0).mean()) for i, d in depths.items()}
    filtered = consistency_filter(scene.cameras, depths, neighbours, cfg) if cfg.min_consistent > 0 else depths
    swept_valid = {i: float((d > 0).mean()) for i, d in filtered.items()}
    if cfg.planar_fill:
        swept = filtered
        filtered = fill_textureless(scene, filtered, images, bounds, neighbours, cfg)
        conf = {i: np.where(swept[i] > 0, conf[i], max(0.5 * cfg.min_ncc, 1e-3)).astype(np.float32) for i in conf}
    # an earlier run's report marks OUT finished: gone before the first file is replaced, so that a kill among
    # the writes (--overwrite) leaves an unfinished folder (Scene.load warns; the rerun computes it again), not a
    # mix of two runs that a rerun would take as finished
    report_path.unlink(missing_ok=True)
    link_scene(scene_dir, out_dir, ("images", "sparse", "gt"))
    meta = json.loads((out_dir / "scene.json").read_text()) if (out_dir / "scene.json").is_file() else {}
    meta.pop("depth_png_scale", None)  # the MVS priors are .npy in the scene's unit
    meta["priors"] = MVS_PRIORS  # not the source scene's (its simulated or network priors are not these)
    with atomic_path(out_dir / "scene.json") as tmp:
        tmp.write_text(json.dumps(meta, indent=1))
    for i, cam in enumerate(full.cameras):
        size_wh = (cam.width, cam.height)
        for kind, arr in (("depth", filtered[i]), ("depth_conf", np.where(filtered[i] > 0, conf[i], 0))):
            up = cv2.resize(arr, size_wh, interpolation=cv2.INTER_NEAREST).astype(np.float32)
            with atomic_path(out_dir / "priors" / kind / f"{cam.stem}.npy") as tmp, open(tmp, "wb") as f:
                np.save(f, up)
    valid = {cam.name: float((filtered[i] > 0).mean()) for i, cam in enumerate(scene.cameras)}
    report = {"config": asdict(cfg), "scene": str(scene_dir.resolve()), "working_size": [scene.cameras[0].width,
              scene.cameras[0].height], "seconds": round(time.perf_counter() - t0, 1),
              "valid_fraction": {"mean": float(np.mean(list(valid.values()))),
                                 "mean_before_consistency": float(np.mean(list(raw_valid.values()))),
                                 "mean_before_planar_fill": float(np.mean(list(swept_valid.values())))},
              "per_view": {cam.name: {"valid": valid[cam.name], "valid_before_consistency": raw_valid.get(i),
                                      "neighbours": [scene.cameras[j].name for j in neighbours[i]],
                                      "bounds_m": list(bounds[i])} for i, cam in enumerate(scene.cameras)}}
    with atomic_path(report_path) as tmp:
        tmp.write_text(json.dumps(report, indent=1))
    log.info("mvs: %d views in %.0f s, %.0f %% of pixels with a depth (%.0f %% before the consistency check%s)",
             len(scene), report["seconds"], 100 * report["valid_fraction"]["mean"],
             100 * report["valid_fraction"]["mean_before_consistency"],
             f", {100 * report['valid_fraction']['mean_before_planar_fill']:.0f} % before the planar fill"
             if cfg.planar_fill else "")
    return out_dir
