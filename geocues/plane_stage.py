"""The plane-like-cue stage of `geocues extract` (paper §4.1), per image: weak-texture regions
(geocues.texture), cut along the projected 3D lines, depth-prior alignment (geocues.depth_align),
plane points with or without the prior (geocues.planes), optional surface fusion
(geocues.plane_surfaces), then the voxel merge (geocues.plane_merge)."""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

from geocues.anchors import Anchors
from geocues.cue_io import CueCloud
from geocues.depth_align import DepthAlignment, align_depth_prior, kind_warning
from geocues.lines import LineCues
from geocues.plane_merge import merge_plane_points
from geocues.plane_regions import split_regions_by_lines
from geocues.planes import plane_cues_with_prior
from geocues.planes_free import plane_cues_prior_free
from geocues.scene import Scene
from geocues.texture import load_or_compute
from geocues.types import CueType

if TYPE_CHECKING:
    from geocues.extract import ExtractConfig

log = logging.getLogger(__name__)


def plane_stage(scene: Scene, cfg: "ExtractConfig", kind: str, anchors: Anchors, plane_ok: np.ndarray,
                 lines: LineCues | None, cache: Path,
                 timings: dict[str, float], notes: list[str], aligned_out: dict | None = None,
                 desc: str = "planes", assumed: np.ndarray | None = None, cuts: np.ndarray | None = None,
                 levels: np.ndarray | None = None, walls: np.ndarray | None = None,
                 wall_veto: np.ndarray | None = None) -> tuple[CueCloud, list[dict], dict[str, dict], dict, tuple[np.ndarray, ...]]:
    """Texture, alignment and plane points for every image; returns (PLANE cloud, per-image report
    rows, rejections by stage, summary statistics, the plane anchors: kept points, normals, image).
    ``aligned_out``: filled with image index -> its aligned prior depth, every 4th pixel;
    ``assumed`` [P]: anchors that are assumptions, not cues (`--floor.walls`' raised rows): left out of
    the depth alignment and of prior-free planes (which they would place on their own), and a prior
    plane counts their lines only whole (geocues.planes). ``cuts`` [M, 2, 3]: assumed edges (the
    ceiling's, geocues.ceiling) that cut every image's regions like the 3D lines it sees. ``levels``
    [L, 4]: level planes (n . X + d = 0; `--floor.level-snap`) a region whose prior lies on one is
    cut onto; ``walls`` [K, 4]: wall planes the pixels left by the anchored planes are cut onto
    (`--floor.wall-snap`; geocues.planes), unless the anchors flagged ``wall_veto`` [P] (the
    measured ones) put the surface elsewhere; those are also the ones a prior is fitted to."""
    n_img = len(scene.cameras)
    rej_tex: dict[str, int] = {}
    rej_align: dict[str, int] = {}
    rej_plane: dict[str, int] = {}
    rows: list[dict] = []
    xyz, rgb, nrm, pid, planes, plane_view = [], [], [], [], [], []
    n_planes = 0
    for k in ("texture", "depth_align", "planes"):
        timings.setdefault(k, 0.0)
    cache_hits = 0
    n_prior = n_aligned = 0
    fits: list[DepthAlignment] = []
    has_priors = scene.has_depth_priors
    strict = anchors.cue_type == int(CueType.SFM)  # SfM anchors count only inside a region
    candidates: list = []  # the images' prior planes, for surface fusion (cfg.plane.fuse_surfaces)
    lines_of: dict[int, list[int]] = {}  # camera -> lines it supports (they cut its regions)
    for li, v in enumerate(lines.views if lines is not None else []):
        for c in np.asarray(v, np.int64).tolist():
            lines_of.setdefault(c, []).append(li)
    for cam in tqdm(scene.cameras, desc=desc, unit="img"):
        i = cam.index
        row: dict = {"index": i, "name": cam.name}
        t0 = time.perf_counter()
        image = scene.load_image(i)  # [H, W, 3] float32
        wt, hit = load_or_compute(cam.image_path, lambda: image, cfg.texture, cache / "texture",
                                  (cam.width, cam.height))
        cache_hits += hit
        t1 = time.perf_counter()
        row.update(texture_s=t1 - t0, texture_cached=hit, n_segments=wt.n_segments,
                   n_keypoints=wt.n_keypoints, n_weak_regions=wt.n_regions,
                   weak_fraction=round(wt.weak_fraction, 4))
        timings["texture"] += t1 - t0
        cand = anchors.candidates(i)
        depth = scene.depth_prior(i) if cfg.priors else None
        aligned = None
        if depth is not None:
            n_prior += 1
            ca = cand if assumed is None else cand[~assumed[cand]]
            al = align_depth_prior(cam, depth, anchors.xyz[ca], cfg.align, seed=cfg.seed, kind=kind,
                                   measured=None if wall_veto is None else wall_veto[ca])
            row["alignment"] = al.to_dict()
            fits.append(al)
            if al.ok:
                n_aligned += 1
                aligned = al.apply(depth, cfg.align.warp_max)
                if aligned_out is not None:
                    aligned_out[i] = aligned[::4, ::4].copy()
            else:
                rej_align[al.reason.split(" (")[0]] = rej_align.get(al.reason.split(" (")[0], 0) + 1
        t2 = time.perf_counter()
        timings["depth_align"] += t2 - t1
        row["align_s"] = t2 - t1
        regions = wt.regions
        pc = cand[plane_ok[cand]]  # the planes' anchors
        pf = pc if assumed is None else pc[~assumed[pc]]  # the prior-free planes': cues only
        cut = lines.segments[lines_of[i]] if lines is not None and lines_of.get(i) else np.zeros((0, 2, 3))
        if cuts is not None and len(cuts):
            cut = np.concatenate([cut, cuts])
        if cfg.plane.cut_px > 0 and len(cut):
            regions = split_regions_by_lines(cam, regions, cut,
                                             cfg.plane.cut_px * cam.width / 640.0,
                                             int(cfg.texture.min_region_frac * cam.width * cam.height))
        n_regions = int(regions.max(initial=-1)) + 1
        row["n_regions_after_cut"] = n_regions
        if n_regions == 0:
            rej_tex["no_weak_region"] = rej_tex.get("no_weak_region", 0) + 1
            pp = None
            row["plane_mode"] = "none"
        elif aligned is not None:
            pp = plane_cues_with_prior(cam, image, regions, aligned, anchors.xyz[pc], cfg.plane,
                                       seed=cfg.seed + i, inside_only=strict[pc],
                                       anchors_group=anchors.group[pc], anchor_ids=pc,
                                       whole_lines=None if assumed is None else assumed[pc],
                                       levels=levels, level_rel=cfg.floor.level_rel, walls=walls,
                                       wall_veto=None if wall_veto is None else wall_veto[pc])
            candidates += pp.candidates
            row["plane_mode"] = "prior"
            if pp.no_depth_regions:  # fill_holes: regions the prior has no depth in
                row["regions_prior_free"] = len(pp.no_depth_regions)
                relabel = np.full(n_regions + 1, -1, regions.dtype)  # region id -> hole id; -1 stays -1
                relabel[pp.no_depth_regions] = np.arange(len(pp.no_depth_regions))
                holes = relabel[regions]
                pp = pp.concat(plane_cues_prior_free(cam, image, holes, anchors.xyz[pf], anchors.group[pf],
                                                     cfg.plane, seed=cfg.seed + i, inside_only=strict[pf]))
        elif cfg.prior_free_fallback or not cfg.priors or not has_priors:
            pp = plane_cues_prior_free(cam, image, regions, anchors.xyz[pf], anchors.group[pf],
                                       cfg.plane, seed=cfg.seed + i, inside_only=strict[pf])
            row["plane_mode"] = "prior_free"
        else:
            pp = None
            row["plane_mode"] = "skipped_no_prior"
            rej_plane["image_without_usable_prior"] = rej_plane.get("image_without_usable_prior", 0) + 1
        if pp is not None:
            for r, c in pp.rejected.items():
                rej_plane[r] = rej_plane.get(r, 0) + c
            row.update(plane_points=len(pp.xyz), regions_accepted=pp.n_accepted)
            xyz.append(pp.xyz)
            rgb.append(pp.rgb)
            nrm.append(pp.normal)
            pid.append(pp.plane_id + n_planes)
            planes.append(pp.planes)
            plane_view.append(np.full(len(pp.planes), i))
            n_planes += len(pp.planes)
        t3 = time.perf_counter()
        timings["planes"] += t3 - t2
        row["planes_s"] = t3 - t2
        rows.append(row)
    t0 = time.perf_counter()
    surface_stats = None
    if cfg.plane.fuse_surfaces:
        from geocues.plane_surfaces import fuse_surfaces

        fused, surface_stats = fuse_surfaces(candidates, scene.cameras, anchors.xyz, anchors.group, cfg.plane)
        for view, fx, frgb, fn, fplane in fused:
            xyz.append(fx)
            rgb.append(frgb)
            nrm.append(fn.astype(np.float32))
            pid.append(np.full(len(fx), n_planes, np.int64))
            planes.append(fplane[None])
            plane_view.append(np.array([view]))
            n_planes += 1
        log.info("surface fusion: %s", surface_stats)
    timings["planes_surfaces"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    centers = np.array([c.center for c in scene.cameras])
    cloud, merge_rej, anchor_pts = merge_plane_points(centers, cfg.plane, xyz, rgb, nrm, pid, planes, plane_view)
    rej_plane.update(merge_rej)
    timings["planes_merge"] = time.perf_counter() - t0
    timings["planes"] += timings["planes_merge"] + timings["planes_surfaces"]
    if not has_priors:
        notes.append("the scene has no depth priors: plane-like cues are prior-free for every image "
                     "(`geocues mvs SCENE -o SCENE_MVS` computes depth priors from the photos; on ICL living "
                     "room 1 they lowered the mesh's Chamfer-L1 from 5.0 to 3.8 cm, docs/geocues.md)")
    elif not cfg.priors:
        notes.append("depth priors ignored (priors off): plane-like cues are prior-free")
    else:
        if n_prior < n_img:
            notes.append(f"depth priors for {n_prior} of {n_img} images; the others get "
                         + ("prior-free plane cues" if cfg.prior_free_fallback else "no plane cues"))
        if n_aligned < n_prior:
            notes.append(f"depth alignment skipped for {n_prior - n_aligned} of {n_prior} images: "
                         + ", ".join(f"{k} x{v}" for k, v in rej_align.items()))
            if n_aligned < 0.5 * n_prior:  # priors given and mostly unused: said at INFO only, nothing with -q
                log.warning("the depth priors of %d of %d images could not be aligned to the scene (%s): their "
                            "plane cues are %s, and splat train's anchored depth term reads no aligned prior there; are the priors "
                            "this scene's, and depth (or --prior-kind disparity)?", n_prior - n_aligned, n_prior,
                            ", ".join(f"{k} x{v}" for k, v in rej_align.items()),
                            "prior-free" if cfg.prior_free_fallback else "none")
        warning = kind_warning(fits, scene.root / "scene.json", cfg.align.inlier_rel)
        if warning:
            log.warning("%s", warning)
            notes.append(warning)
    notes.append(f"texture cache: {cache_hits} of {n_img} images reused")
    stats = {"texture_cache_hits": cache_hits, "images_with_prior": n_prior, "images_aligned": n_aligned,
             "plane_modes": {m: sum(r["plane_mode"] == m for r in rows)
                             for m in ("prior", "prior_free", "none", "skipped_no_prior")}}
    if surface_stats is not None:
        stats["surface_fusion"] = surface_stats
    return cloud, rows, {"texture": rej_tex, "depth_align": rej_align, "planes": rej_plane}, stats, anchor_pts
