"""`geocues extract`: the cue stage chain of paper §4.1, scene folder in, ``CUES/`` out.

Stages (each can be switched off for the paper's ablations, each is timed):

1. ``sfm``    SfM points after statistical outlier removal            (geocues.sfm_cues)
2. ``lines``  3D line segments and their point samples                 (geocues.lines)
3. ``planes`` per image: weak-texture regions (geocues.texture), depth-prior alignment
              (geocues.depth_align, when the image has a prior and priors are on), plane-like
              points with or without the prior (geocues.planes); then a voxel merge
              (geocues.plane_stage). With ``--floor.lines`` a first pass of it gives the floor and
              the floor-contact lines join the anchors of the second (geocues.floor_lines).

Outputs: ``CUES/cues.ply`` (typed points), ``CUES/lines3d.npz``, ``CUES/lines3d.ply`` and
``CUES/cues_by_type.ply`` (to look at in MeshLab / CloudCompare), ``CUES/depth_alignments.json``
(the per-image prior alignments `splat train` reads), ``CUES/plane_anchors.npz`` (each image's kept
plane points, for `splat train --loss.plane-anchor`; geocues.plane_anchors), ``CUES/report.json`` (counts per
type, rejections with reasons, seconds per stage and per image, alignment residuals, notes on hard
cases) and ``CUES/cache/`` (per-image texture results and the line stage's cache, reused by later
runs). Every file is written atomically.
"""

from __future__ import annotations

import json
import logging
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Literal

import numpy as np

from geocues.advice import normal_axes_warning, registration_warning
from geocues.anchors import Anchors
from geocues.atomic import atomic_path, check_not_input, check_output_dir, locks_output
from geocues.camera_signature import camera_signature
from geocues.rescale import metric_warning
from geocues.cue_io import CueCloud, write_cues_by_type_ply, write_cues_ply, write_lines_npz, write_lines_ply
from geocues.ceiling import add_level_grids, ceiling_height
from geocues.floor_lines import FloorLineConfig, floor_line_anchors
from geocues.depth_align import DepthAlignConfig, write_alignments
from geocues.extract_checks import check_extract_options, idle_options, what_changed
from geocues.lines import LineConfig, LineCues
from geocues.plane_anchors import write_plane_anchors
from geocues.plane_stage import plane_stage
from geocues.planes import PlaneConfig
from geocues.scene import Scene, upsampling_warning
from geocues.sfm_cues import SfmCueConfig, SfmCues, extract_sfm_cues
from geocues.texture import TextureConfig, config_key, file_stamp, tree_stamp
from geocues.types import CueType
from geocues.walls import refit_wall_planes, wall_anchors, wall_planes

log = logging.getLogger(__name__)


@dataclass
class ExtractConfig:
    """Cue extraction (paper §4.1): SfM, line and plane-like cues; every stage can be switched off."""

    sfm: bool = True
    """Run the SfM-cue stage (statistical outlier removal of the model's 3D points)."""
    lines: bool = True
    """Run the line-cue stage (2D segments -> 3D lines -> point samples)."""
    planes: bool = True
    """Run the plane-like-cue stage (weak-texture regions -> planes)."""
    priors: bool = True
    """Use depth priors where the scene has them (False: a prior-free run for every image)."""
    prior_kind: Literal["scene", "depth", "disparity"] = "scene"
    """Depth priors hold depth, or disparity (inverse depth: Depth-Anything, MiDaS); scene: scene.json's choice."""
    prior_free_fallback: bool = True
    """Images without a usable prior (missing, or alignment skipped) get prior-free plane cues."""
    downscale: float = 1.0
    """Divide image size and intrinsics by this factor before extracting."""
    seed: int = 0
    """Seed of every random choice (RANSAC, subsampling)."""
    sor: SfmCueConfig = field(default_factory=SfmCueConfig)
    """SfM cues."""
    line: LineConfig = field(default_factory=LineConfig)
    """Line cues."""
    texture: TextureConfig = field(default_factory=TextureConfig)
    """Weak-texture regions."""
    align: DepthAlignConfig = field(default_factory=DepthAlignConfig)
    """Depth-prior alignment."""
    plane: PlaneConfig = field(default_factory=PlaneConfig)
    """Plane-like cues."""
    floor: FloorLineConfig = field(default_factory=FloorLineConfig)
    """Floor-contact lines as plane anchors (an extension, off by default)."""


# Plane options added after cue folders were made that change nothing while fuse_surfaces is off:
# then they stay out of the configuration key, so a re-run of an older folder is still the same run.
_SURFACE_FIELDS = ("fuse_surfaces", "surface_angle_deg", "surface_consensus_deg", "fuse_prior_rel",
                   "fuse_prior_dist")

_WALL_FIELDS = ("walls", "wall_step", "wall_height")  # added after --floor.lines folders were made
_WALL_CHECK_FIELDS = ("wall_check", "wall_check_rel", "wall_front_gap")  # added after --floor.walls folders
_CEILING_FIELDS = ("ceiling", "ceiling_margin", "ceiling_min_views")  # added after --floor.wall-front-gap folders


def _key_config(cfg: ExtractConfig) -> dict:
    """The configuration as hashed for OUT's key (:data:`_SURFACE_FIELDS` and ``floor`` left out
    while off)."""
    d = asdict(cfg)
    if cfg.line.use_test_views:  # added later; only says which views to leave out when they are left out
        d["line"].pop("test_every")
    if cfg.floor.lines:  # added after --floor.wall-front-gap folders were made: out of the key while off
        for k in _CEILING_FIELDS if not cfg.floor.ceiling else ():
            d["floor"].pop(k)
        if not cfg.floor.floor_grid:
            d["floor"].pop("floor_grid")
        if not cfg.floor.level_snap:  # added after --floor.ceiling folders were made
            for k in ("level_snap", "level_rel"):
                d["floor"].pop(k)
        if not cfg.floor.wall_snap:  # added after --floor.level-snap folders were made
            for k in ("wall_snap", "wall_snap_height"):
                d["floor"].pop(k)
    if not cfg.floor.lines:  # added later, like the surface fields: off = the key of older folders
        d.pop("floor")
    elif not cfg.floor.walls:
        for k in _WALL_FIELDS + _WALL_CHECK_FIELDS:
            d["floor"].pop(k)
    elif not cfg.floor.wall_check:
        for k in _WALL_CHECK_FIELDS:
            d["floor"].pop(k)
    elif not cfg.floor.wall_front_gap:  # added after --floor.wall-check folders were made
        d["floor"].pop("wall_front_gap")
    if not cfg.plane.fuse_surfaces:
        for k in _SURFACE_FIELDS:
            d["plane"].pop(k)
    return d


def _json_default(o):
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def _line_confidence(lines: LineCues) -> np.ndarray:
    """Line-sample confidence: min(1, supporting views / 6) of the sample's line."""
    if len(lines.points) == 0:
        return np.zeros(0, np.float32)
    return np.minimum(1.0, lines.n_views[lines.point_line] / 6.0).astype(np.float32)


def triangulation_angles(scene: Scene, idx: np.ndarray) -> np.ndarray:
    """Largest angle (degrees) between two rays that observe each SfM point ``idx`` [M] (indices
    into scene.points), from the cameras in its track; inf where the model has no tracks."""
    pts = scene.points
    cams_of: list[list[int]] = [[] for _ in range(len(pts))]
    for c, ids in pts.visible_in.items():
        for k in np.asarray(ids, np.int64).tolist():
            cams_of[k].append(c)
    centers = np.array([c.center for c in scene.cameras])
    out = np.full(len(idx), np.inf)
    for j, k in enumerate(np.asarray(idx, np.int64)):
        if len(cams_of[k]) >= 2:
            r = centers[cams_of[k]] - pts.xyz[k]
            r /= np.linalg.norm(r, axis=1, keepdims=True)
            out[j] = np.degrees(np.arccos(np.clip((r @ r.T).min(), -1.0, 1.0)))
    return out


def _per_image_seconds(rows: list[dict], timings: dict[str, float], n_img: int) -> dict:
    """Mean / max seconds per image of the per-image stages (lines: whole stage / images)."""
    out: dict[str, dict] = {}
    for key in ("texture_s", "align_s", "planes_s"):
        v = [r[key] for r in rows if key in r]
        if v:
            out[key[:-2]] = {"mean": float(np.mean(v)), "max": float(np.max(v))}
    if rows:
        tot = [r.get("texture_s", 0) + r.get("align_s", 0) + r.get("planes_s", 0) for r in rows]
        out["planes_chain"] = {"mean": float(np.mean(tot)), "max": float(np.max(tot))}
    if "lines" in timings and n_img:
        out["lines"] = {"mean": timings["lines"] / n_img}
    return out


def _run_lines(scene: Scene, cfg: ExtractConfig, cache_dir: Path) -> LineCues:
    from geocues.lines import extract_line_cues  # lazy: the heaviest stage

    return extract_line_cues(scene, cfg.line, cache_dir)


@locks_output("geocues extract")  # two extracts into one OUT mixed their files
def run(cfg: ExtractConfig | None, scene_dir: str | Path, out_dir: str | Path, *,
        overwrite: bool = False, cache_dir: str | Path | None = None) -> Path:
    """Extract the cues of the scene at ``scene_dir`` into ``out_dir`` with ``cfg`` (None: the
    defaults); returns ``out_dir``.

    If ``out_dir/report.json`` already holds a run with the same configuration, nothing is redone
    unless ``overwrite``; a run with a different configuration there raises ValueError unless
    ``overwrite``. The per-image cache (``cache_dir``, default ``out_dir/cache``) is keyed by
    parameters and reused; runs of one scene may share it.
    """
    cfg = cfg or ExtractConfig()
    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    if not scene_dir.exists():
        raise FileNotFoundError(f"scene folder does not exist: {scene_dir}")
    check_extract_options(cfg)  # NaN, inf and values that gave empty cues in silence, before any work
    for sentence in idle_options(cfg):
        log.warning("%s", sentence)
    cfg.line.validate()
    cfg.floor.validate()
    check_not_input(out_dir, {"scene": scene_dir})  # cues.ply and report.json written into a scene mix with it
    check_output_dir(out_dir)
    scene = Scene.load(scene_dir, downscale=cfg.downscale, test_every=0)
    if up := upsampling_warning(cfg.downscale, "work per image", "extracts at the photos' own size"):
        log.warning("%s", up)
    far = metric_warning(scene)
    if far:
        log.warning("%s", far)
    kind = _prior_kind(cfg, scene)
    # the scene's content, not only its path: a scene regenerated in place is extracted again
    key = config_key(_key_config(cfg), scene_dir.resolve(), tree_stamp(scene_dir, ("images", "priors", "sparse")),
                     file_stamp(scene.root / "scene.json", *scene.sources))
    report_path = out_dir / "report.json"
    if report_path.is_file() and not overwrite:
        old = json.loads(report_path.read_text())
        if old.get("config_key") == key and (out_dir / "cues.ply").is_file():
            log.info("extract: %s already holds this run (config %s); skipping", out_dir, key)
            return out_dir
        raise ValueError(f"{out_dir} holds cues of another configuration or scene "
                         f"(config {old.get('config_key')} vs {key}: {what_changed(old, _key_config(cfg), _key_config(ExtractConfig()), scene_dir)}); "
                         "pass --overwrite to replace them")
    log.info("extract: %s -> %s, config %s:\n%s", scene_dir, out_dir, key,
             json.dumps(asdict(cfg), indent=1, default=_json_default))
    t_all = time.perf_counter()
    cache = Path(cache_dir) if cache_dir is not None else out_dir / "cache"
    if few := registration_warning(scene.metadata):
        log.warning("%s", few)
    if away := normal_axes_warning(scene):
        log.warning("%s", away)
    n_img = len(scene.cameras)
    timings: dict[str, float] = {}
    rejections: dict[str, dict] = {}
    notes: list[str] = []

    # ---- 1. SfM cues
    sfm: SfmCues | None = None
    if cfg.sfm:
        t0 = time.perf_counter()
        sfm = extract_sfm_cues(scene.points, cfg.sor)
        timings["sfm"] = time.perf_counter() - t0
        rejections["sfm"] = sfm.removed
        if sfm.n_input == 0:
            notes.append("the SfM model has no 3D points: no SFM cues (`geocues sfm` triangulates them; when it ran and found none, its warning says why)")
        else:
            notes.append(f"SOR removed {sfm.n_removed} of {sfm.n_input} SfM points")

    # ---- 2. line cues
    lines: LineCues | None = None
    if cfg.lines:
        t0 = time.perf_counter()
        lines = _run_lines(scene, cfg, cache / "lines")
        timings["lines"] = time.perf_counter() - t0
        rejections["lines"] = dict(lines.rejected)
        seen = np.zeros(n_img, bool)
        for v in lines.views:
            seen[np.asarray(v, np.int64)] = True
        if len(lines) == 0:
            notes.append("no 3D line was reconstructed: no LINE cues")
        if (~seen).any():
            notes.append(f"{int((~seen).sum())} of {n_img} images support no 3D line")

    # ---- 3. plane-like cues (texture -> alignment -> planes, per image)
    anchors = _anchors(scene, sfm, lines)
    plane_ok = np.ones(len(anchors), bool)  # anchors the planes may use
    if not cfg.plane.sfm_anchors:
        plane_ok &= anchors.cue_type != int(CueType.SFM)
    elif sfm is not None and cfg.plane.sfm_min_angle_deg > 0 and len(sfm.kept):
        angle = triangulation_angles(scene, sfm.kept)  # [M] degrees, inf where unknown
        plane_ok[:len(angle)] &= angle >= cfg.plane.sfm_min_angle_deg  # SfM anchors come first
    floor_stats, assumed, cuts, levels, snap_walls, measured = None, None, None, None, None, None
    if cfg.planes and cfg.floor.lines:
        extra, walls, floor_stats = _floor_lines(scene, cfg, kind, anchors, plane_ok, lines, cache, timings, notes)
        if len(extra[0]):
            anchors = _anchors(scene, sfm, lines, extra)
            first_row = int(anchors.group.max()) + 1  # rows are lines after every other line
            anchors = anchors.with_unknown(walls[0], walls[1] + first_row)  # seen wherever they project
            plane_ok = np.concatenate([plane_ok, np.ones(len(extra[0]) + len(walls[0]), bool)])  # they come last
            assumed = np.zeros(len(anchors), bool)
            assumed[len(anchors) - len(walls[0]):] = True  # the raised walls (last) are assumptions, not cues
            cuts = walls[2]
            levels = walls[3] if cfg.floor.level_snap and len(walls[3]) else None
            snap_walls = walls[4] if len(walls[4]) else None
            measured = anchors.group < (len(lines.views) if lines is not None else 0)  # SfM points, 3D lines
    per_image: list[dict] = []
    plane_cloud = CueCloud.empty()
    plane_stats: dict = {}
    anchor_pts = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64))  # plane anchors: X, normal, image
    if cfg.planes:
        plane_cloud, per_image, pr, plane_stats, anchor_pts = plane_stage(scene, cfg, kind, anchors, plane_ok,
                                                                           lines, cache, timings, notes,
                                                                           assumed=assumed, cuts=cuts,
                                                                           levels=levels, walls=snap_walls,
                                                                           wall_veto=measured)
        rejections.update(pr)

    # ---- merge and write
    t0 = time.perf_counter()
    clouds = []
    if sfm is not None:
        clouds.append(sfm.cloud)
    if lines is not None and len(lines.points):
        clouds.append(CueCloud.make(lines.points, lines.point_colors, CueType.LINE,
                                    normal=lines.normals, confidence=_line_confidence(lines)))
    clouds.append(plane_cloud)
    cues = CueCloud.concat(clouds)
    out_dir.mkdir(parents=True, exist_ok=True)
    # an earlier run's report marks OUT finished: gone before the first file is replaced, so that a kill
    # among the writes (--overwrite) leaves no mix of two runs that a rerun would take as finished
    report_path.unlink(missing_ok=True)
    write_cues_ply(out_dir / "cues.ply", cues)
    write_cues_by_type_ply(out_dir / "cues_by_type.ply", cues)  # for looking at: coloured by type
    lc = lines if lines is not None else LineCues.empty()
    write_lines_npz(out_dir / "lines3d.npz", lc.segments, lc.n_views, lc.views, lc.colors,
                    lc.points, lc.point_colors, lc.point_line)
    write_lines_ply(out_dir / "lines3d.ply", lc.segments, lc.colors)  # for looking at: a line set
    write_plane_anchors(out_dir, [c.name for c in scene.cameras], *anchor_pts)  # for --loss.plane-anchor
    timings["write"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    report = {
        "scene": str(scene_dir), "n_images": n_img, "cameras": camera_signature(scene), "config_key": key,
        "config": asdict(cfg),
        "counts": cues.counts(), "n_points": len(cues), "n_lines": len(lc),
        "n_plane_anchors": len(anchor_pts[0]),
        "stages": {"sfm": cfg.sfm, "lines": cfg.lines, "planes": cfg.planes, "priors": cfg.priors},
        "prior_kind": kind,
        "rejections": rejections, "seconds": timings,
        "line_timings": dict(lc.timings),
        "planes": plane_stats, "per_image_seconds": _per_image_seconds(per_image, timings, n_img),
        "per_image": per_image, "notes": notes,
    }
    if floor_stats is not None:
        report["floor_lines"] = floor_stats
    if sfm is not None:
        report["sfm"] = {"n_input": sfm.n_input, "n_kept": len(sfm.kept), "n_removed": sfm.n_removed,
                         "sor_threshold_m": sfm.sor_threshold if np.isfinite(sfm.sor_threshold) else None}
    write_alignments(out_dir, json.loads(json.dumps(per_image, default=_json_default)), kind)
    with atomic_path(report_path) as tmp:  # last: its config key marks a finished extract
        tmp.write_text(json.dumps(report, indent=1, default=_json_default))
    for line in notes:
        log.info("extract: %s", line)
    log.info("extract: %s -> %s in %.1f s", cues.counts(), out_dir, timings["total"])
    return out_dir


def _anchors(scene: Scene, sfm: SfmCues | None, lines: LineCues | None,
             extra: tuple[np.ndarray, np.ndarray, list[np.ndarray]] | None = None) -> Anchors:
    """The plane stage's anchors: SfM cues, line samples, then ``extra`` line-like anchors (points,
    their line index from 0, views per line: the floor-contact lines) after them."""
    lp, lo, lv = (lines.points, lines.point_line, list(lines.views)) if lines else (None, None, None)
    if extra is not None:
        n = len(lv) if lv is not None else 0
        lp = extra[0] if lp is None else np.concatenate([lp, extra[0]])
        lo = extra[1] if lo is None else np.concatenate([lo, extra[1] + n])
        lv = (lv or []) + list(extra[2])
    return Anchors.build(
        sfm_xyz=sfm.cloud.xyz if sfm else None,
        sfm_views=({c: np.flatnonzero(np.isin(sfm.kept, v)) for c, v in scene.points.visible_in.items()}
                   if sfm and len(sfm.kept) else None),
        line_points=lp, line_of_point=lo, line_views=lv)


def _floor_lines(scene: Scene, cfg: ExtractConfig, kind: str, anchors: Anchors, plane_ok: np.ndarray,
                 lines: LineCues | None, cache: Path, timings: dict[str, float], notes: list[str]
                 ) -> tuple[tuple[np.ndarray, np.ndarray, list[np.ndarray]], tuple[np.ndarray, ...], dict]:
    """A first plane pass for the floor, then the floor-contact lines (geocues.floor_lines): returns
    ((points, line index, views per line), (--floor.walls' raised points, their row index, the edges
    that cut the regions: --floor.ceiling's, the level planes [L, 4] of the ceiling and the floor
    grid: n . X + d = 0, the wall planes [K, 4] of --floor.wall-snap), statistics for the report)."""
    from geocues.lines.detect import detect_all

    t0 = time.perf_counter()
    aligned: dict[int, np.ndarray] = {}
    first, *_ = plane_stage(scene, cfg, kind, anchors, plane_ok, lines, cache, {}, [],
                             aligned if cfg.floor.prior_check or cfg.floor.wall_check else None,
                             desc="planes (first pass: the floor)")
    segments, _ = detect_all(scene, cfg.line, cache / "lines")  # the line stage's, cached
    P, L, V, stats = floor_line_anchors(scene.cameras, [s.segs for s in segments], first.xyz, first.normal,
                                        cfg.floor, aligned, lines.segments if lines is not None else None,
                                        anchors.xyz[plane_ok])  # SfM points of too narrow an angle left out
    W, WL, cuts, levels = np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros((0, 2, 3)), np.zeros((0, 4))
    snap_walls = np.zeros((0, 4))
    if cfg.floor.walls and len(P):
        checked: dict = {}
        up, floor_h = np.array(stats["floor"]["normal"]), stats["floor"]["height"]
        wall_cfg, ceiling = cfg.floor, None
        if cfg.floor.ceiling:
            ceiling, stats["ceiling"] = ceiling_height(scene.cameras, aligned, up, floor_h, cfg.floor.ceiling_margin,
                                                       cfg.floor.ceiling_min_views)
            if ceiling is not None:
                wall_cfg = replace(cfg.floor, wall_height=ceiling)
        raised: list = []
        W, WL, top = wall_anchors(P, L, up, floor_h, first.xyz, scene.cameras, wall_cfg, V, aligned, checked,
                                  raised)
        stats["walls"] = {"samples": len(W), "top": round(top, 3)}
        if cfg.floor.wall_snap:
            feet = wall_planes(raised, up, top, cfg.floor.wall_snap_height)
            snap_walls = refit_wall_planes(feet, first.xyz, first.normal, up)
            stats["walls"]["snap_planes"] = {"from_feet": len(feet), "confirmed_by_cues": len(snap_walls),
                                             "planes": np.round(snap_walls, 4).tolist()}
        if cfg.floor.wall_check:
            stats["walls"]["check"] = checked or {"note": "no aligned prior: nothing checked"}
        W, WL, cuts, grids = add_level_grids(W, WL, up, floor_h, ceiling, cfg.floor.floor_grid, cfg.floor.wall_step)
        if "ceiling_samples" in grids:
            stats["ceiling"]["samples"] = grids["ceiling_samples"]
            levels = np.concatenate([levels, [np.r_[up, -(floor_h + ceiling)]]])
        if "floor_samples" in grids:
            levels = np.concatenate([levels, [np.r_[up, -floor_h]]])
            stats["floor_grid"] = {"samples": grids["floor_samples"]}
    n_wall = len(W)
    timings["floor_lines"] = time.perf_counter() - t0
    if "note" in stats:
        notes.append(f"floor lines: {stats['note']}; no floor-line anchors")
        log.warning("--floor.lines: %s: no floor lines, walls or level planes (the cues are those without them)",
                    stats["note"])
    else:
        notes.append(f"floor lines: floor fitted to {stats['floor']['n_points']} cues; {stats['kept']} of "
                     f"{stats['lifted']} lifted segments kept, {stats['samples']} plane anchors"
                     + (f", {n_wall} raised up to {stats['walls']['top']:.2f} m (--floor.walls)" if n_wall else "")
                     + (f", a ceiling grid of {stats['ceiling']['samples']} at {stats['ceiling']['height']:.3f} m "
                        f"(--floor.ceiling; {stats['ceiling']['views']} views)" if "samples" in stats.get("ceiling", {})
                        else ""))
        if "note" in stats.get("ceiling", {}):
            notes.append(f"--floor.ceiling: no ceiling placed: {stats['ceiling']['note']}")
    return (P, L, V), (W, WL, cuts, levels, snap_walls), stats


def _prior_kind(cfg: ExtractConfig, scene: Scene) -> str:
    """What the depth priors hold: ``cfg.prior_kind``, or scene.json's priors.depth_kind for "scene"."""
    if cfg.prior_kind not in ("scene", "depth", "disparity"):
        raise ValueError(f"prior_kind must be 'scene', 'depth' or 'disparity', got {cfg.prior_kind!r}")
    if cfg.prior_kind == "scene":
        return scene.depth_kind
    if scene.depth_kind != cfg.prior_kind and "depth_kind" in (scene.metadata.get("priors") or {}):
        log.warning("--prior-kind %s overrides priors.depth_kind %r of %s", cfg.prior_kind,
                    scene.depth_kind, scene.root / "scene.json")
    return cfg.prior_kind
