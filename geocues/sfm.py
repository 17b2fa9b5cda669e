"""`geocues sfm`: 3D points for a scene with pycolmap (hloc-style stage).

Two modes:

* **triangulate** (a posed model, with or without points): SIFT features (CPU), image pairs chosen
  from the known poses (k nearest camera centres whose viewing directions differ by less than an
  angle; exhaustive for few images, hloc's ``pairs_from_poses``), SIFT matching, geometric
  verification (by default against the *known* epipolar geometry; COLMAP's RANSAC as an option),
  then COLMAP's point triangulator with poses and intrinsics fixed.
* **map** (images only): the same features, exhaustive or sequential pairs, RANSAC verification and
  COLMAP's incremental mapper; the largest model is kept. When the scene had a posed model, the new
  model is aligned to its camera centres (similarity) so it lives in the scene's frame.

The database is cached in ``OUT/cache/sfm/`` with the parameters and the photos (names, sizes and
modification times) that made it; a re-run reuses the features (and the matches) unless
``recompute``, the parameters or a photo changed. The model is written
atomically; the report goes to ``OUT/sfm_report.json``. Entry: ``run(cfg, scene, out=None, *,
overwrite=False, recompute=False) -> OUT`` (SCENE itself when written in place).
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from geocues import sfm_steps as U
from geocues.sfm_checks import FEW_POINTS, command_flags, few_points_advice, more_points_advice
from geocues.atomic import atomic_dir, atomic_path, check_not_input, check_output_dir
from geocues.colmap_io import find_model_dir, load_reconstruction
from geocues.nerfstudio_io import find_transforms, transforms_reconstruction, write_colmap_model
from geocues.photos import check_photos, missing_images_error, photos_in_subfolders
from geocues.scene import ARBITRARY_SCALE, OWN_FRAME, list_images, no_images_folder, rescale_hint

if TYPE_CHECKING:  # pragma: no cover
    import pycolmap

log = logging.getLogger(__name__)


@dataclass
class SfmConfig:
    """Options of `geocues sfm` (defaults tuned on ICL living room 1 and the benchmark rooms)."""

    mode: Literal["auto", "triangulate", "map"] = "auto"
    """auto: triangulate when the scene has a posed model, else map (incremental SfM)."""
    max_image_size: int = 0
    """Longest image side for SIFT extraction (0 = full size); keypoints are rescaled back."""
    max_num_features: int = 8192
    """Most SIFT features per image."""
    peak_threshold: float = 0.004
    """SIFT peak (contrast) threshold; lower finds more features on weak texture (COLMAP: 0.0067)."""
    num_neighbors: int = 20
    """Pairs from poses: each image is matched to its k nearest cameras by centre distance."""
    pair_stride: int = 1
    """Pairs from poses: take every n-th of the k*n nearest cameras (wider baselines, same cost)."""
    max_pair_angle: float = 60.0
    """Pairs from poses: largest angle (degrees) between the two viewing directions."""
    exhaustive_below: int = 30
    """Match all pairs when the scene has at most this many images."""
    sequential_overlap: int = 15
    """Map mode on many images: match each image with this many following ones (name order)."""
    max_ratio: float = 0.8
    """SIFT matching: Lowe ratio test."""
    verification: Literal["poses", "ransac"] = "poses"
    """Triangulate mode: verify matches by the known epipolar geometry, or by COLMAP's RANSAC."""
    max_epipolar_error: float = 1.0
    """Known-pose verification: largest Sampson distance (pixels) of an inlier match."""
    min_num_inliers: int = 15
    """Smallest number of verified matches for a pair to be used."""
    min_tri_angle: float = 4.0
    """Smallest triangulation angle (degrees) to create and keep a point (COLMAP: 1.5; larger keeps
    fewer, more accurate points: see sfm_report.json's gt_check on a scene with a GT mesh)."""
    max_reproj_error: float = 1.0
    """Largest reprojection error (pixels) when creating, merging, completing and keeping points."""
    ignore_two_view_tracks: bool = True
    """Do not create points from a single pair (they are less reliable)."""
    min_track_length: int = 3
    """Drop points seen in fewer images after triangulation (filtering can shorten tracks to 2)."""
    camera_model: str = "SIMPLE_RADIAL"
    """Map mode without a model: COLMAP camera model to estimate (distorted ones need undistorting)."""
    num_threads: int = -1
    """Threads for extraction and matching (-1 = all cores)."""
    mapper_threads: int = 1
    """Threads of COLMAP's incremental mapper (map mode; -1 = all cores). With more than one it gives
    another model on each run, the seed notwithstanding (16 photos of a bare room: 2 or 6 of them
    registered); one thread gives the same model every time, at 1.4x the mapping time (ICL's 211
    photos: 318 s against 220 s on 2 cores, the same 211 images and 3216 points)."""
    seed: int = 0
    """Random seed for pycolmap's RANSAC and mapper."""
    model_format: Literal["auto", "bin", "txt"] = "auto"
    """The written model's files: "auto" is .bin, except that a model replaced in place (no -o) keeps
    its format."""
    check_gt: bool = True
    """When the scene has a GT mesh, report the share of points within 2 cm / 5 cm of it."""

    def validate(self) -> None:
        """Raise ValueError naming the first option out of range (geocues.sfm_checks)."""
        from geocues.sfm_checks import check_sfm_options

        check_sfm_options(self)


def _key(d: dict) -> str:
    return hashlib.sha1(json.dumps(d, sort_keys=True, default=str).encode()).hexdigest()[:16]


def link_scene(scene_dir: Path, out_dir: Path, parts: tuple[str, ...] = ("images", "priors", "gt")) -> None:
    """Make OUT a scene folder whose ``parts`` (images, priors, sparse, gt) are links to the source
    scene's and whose scene.json is a copy of its (the stages that write a new scene from an old
    one: `geocues sfm -o`, `mvs`, `rescale`). A dataset's reference mesh at the root becomes
    OUT/gt/mesh.ply; stale links are replaced, real folders never."""
    out_dir.mkdir(parents=True, exist_ok=True)
    src = Path(scene_dir).resolve()
    links = {part: src / part for part in parts}
    if "gt" in links and not (src / "gt" / "mesh.ply").is_file() and (src / "reference_mesh.ply").is_file():
        links.pop("gt")  # a dataset's reference mesh at the root becomes OUT/gt/mesh.ply
        (out_dir / "gt").mkdir(exist_ok=True)
        links["gt/mesh.ply"] = src / "reference_mesh.ply"
    for rel, target in links.items():
        if not target.exists():
            continue
        link = out_dir / rel
        if link.is_symlink() or link.is_file():
            link.unlink()
        elif link.is_dir():
            raise FileExistsError(f"{link} is a real folder; refusing to replace it with a link")
        link.symlink_to(target)
    if "sparse" in parts and not (src / "sparse").exists() and (transforms := find_transforms(src)) is not None:
        model = out_dir / "sparse" / "0"  # a nerfstudio scene: OUT gets its cameras as a COLMAP model
        if not model.exists():
            write_colmap_model(transforms, model)
    if (src / "scene.json").is_file():
        shutil.copyfile(src / "scene.json", out_dir / "scene.json")


def _warn_unregistered(names: list[str], rec: "pycolmap.Reconstruction") -> None:
    """Say which images the kept model lacks: the scene and everything after it leave them out."""
    reg = {rec.images[i].name for i in rec.reg_image_ids()}
    missing = [n for n in names if n not in reg]
    if missing:
        log.warning("sfm: %d of %d images are not in the model (%s%s): the scene leaves them out; more overlap "
                    "between neighbouring photos or texture in the room brings them in (--max-num-features or a "
                    "lower --peak-threshold sometimes does)",
                    len(missing), len(names), ", ".join(missing[:5]), ", ..." if len(missing) > 5 else "")


def _mark_scene(scene_json: Path, marks: dict) -> None:
    """Add ``marks`` to scene.json, atomically (the later steps copy it): ``scale`` arbitrary (read by
    ``geocues.rescale.metric_warning``; `geocues rescale` removes it), ``frame`` its own (read by
    `evaluate`), ``sfm_registered`` (read by :func:`geocues.advice.registration_warning`)."""
    meta = json.loads(scene_json.read_text()) if scene_json.is_file() else {}
    with atomic_path(scene_json) as tmp:
        tmp.write_text(json.dumps(meta | marks, indent=1))


def points_xyz(rec: "pycolmap.Reconstruction") -> np.ndarray:
    """[N, 3] point positions of a reconstruction."""
    if rec.num_points3D() == 0:
        return np.zeros((0, 3))
    return np.stack([p.xyz for p in rec.points3D.values()])


def summarize(rec: "pycolmap.Reconstruction", *, mode: str, n_images: int, n_pairs: int,
              n_verified: int, seconds: dict[str, float]) -> dict:
    """The report's figures: points, mean track length, mean reprojection error, pairs, seconds."""
    return {
        "mode": mode,
        "images": n_images,
        "registered_images": int(rec.num_reg_images()),
        "points": int(rec.num_points3D()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "mean_reproj_error": float(rec.compute_mean_reprojection_error()),
        "observations": int(rec.compute_num_observations()),
        "pairs": n_pairs,
        "verified_pairs": n_verified,
        "seconds": {k: round(v, 2) for k, v in seconds.items()},
        "seconds_total": round(sum(seconds.values()), 2),
    }


def distance_to_mesh_stats(xyz: np.ndarray, mesh_path: Path) -> dict:
    """Unsigned distances of points xyz [N, 3] to a mesh (Open3D RaycastingScene): shares within
    2 cm / 5 cm, median and 90th percentile in metres."""
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(filename=str(mesh_path))
    if len(mesh.triangles) == 0:
        raise ValueError(f"mesh {mesh_path} has no triangles")
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(mesh=o3d.t.geometry.TriangleMesh.from_legacy(mesh_legacy=mesh))
    d = scene.compute_distance(query_points=o3d.core.Tensor(np.asarray(xyz, np.float32))).numpy()
    return {"mesh": str(Path(mesh_path).resolve()), "within_2cm": float(np.mean(d <= 0.02)),
            "within_5cm": float(np.mean(d <= 0.05)), "median_m": float(np.median(d)),
            "p90_m": float(np.percentile(d, 90))}


def run(cfg: SfmConfig, scene_dir: str | Path, out_dir: str | Path | None = None, *,
        overwrite: bool = False, recompute: bool = False) -> Path:
    """Fill a scene's 3D points (triangulate) or reconstruct it from images (map); return the scene
    folder written (``scene_dir`` in place, else ``out_dir``), whose ``sfm_report.json`` holds the
    report (points, track length, reprojection error, pairs, seconds, config).

    ``out_dir=None`` writes ``SCENE/sparse/0`` in place; otherwise OUT becomes a complete scene
    folder (images/priors/gt linked, scene.json copied, OUT/sparse/0 the new model). An OUT that
    holds a finished run (``sfm_report.json``) is replaced only with ``overwrite``; ``recompute``
    discards the cached features and matches.
    """
    import pycolmap

    scene_dir = Path(scene_dir)
    image_dir = scene_dir / "images"
    if not image_dir.is_dir():
        raise no_images_folder(image_dir)
    cfg.validate()
    try:
        model_dir = find_model_dir(scene_dir)
    except FileNotFoundError:
        model_dir = None
    transforms = find_transforms(scene_dir) if model_dir is None and cfg.mode != "map" else None
    if transforms is not None:  # a nerfstudio scene: its known poses, as a COLMAP model
        log.info("sfm: %s is a nerfstudio scene: triangulating with its poses", scene_dir)
    posed = model_dir is not None or transforms is not None
    mode = cfg.mode if cfg.mode != "auto" else ("triangulate" if posed else "map")
    if mode == "triangulate" and not posed:
        raise FileNotFoundError(f"triangulate mode needs a posed model: no cameras.txt or cameras.bin "
                                f"in {scene_dir / 'sparse' / '0'} or {scene_dir / 'sparse'}")
    in_place = out_dir is None or Path(out_dir).resolve() == scene_dir.resolve()
    root = scene_dir if in_place else Path(out_dir)
    if not in_place:
        check_not_input(root, {"scene": scene_dir})
    if in_place and not os.access(scene_dir, os.W_OK):
        raise ValueError(f"{scene_dir} is not writable: pass an output folder (-o OUT) to write a new scene")
    check_output_dir(root)
    if not in_place and (root / "sfm_report.json").is_file() and not overwrite:
        raise ValueError(f"{root} holds a finished `geocues sfm` run; pass --overwrite to replace it "
                         "(its cached features are reused; --recompute discards them)")
    log.info("sfm %s -> %s (mode %s) config %s", scene_dir, root, mode, asdict(cfg))

    U.quiet_pycolmap()
    pycolmap.set_random_seed(cfg.seed)
    ref = None
    if posed:
        ref = load_reconstruction(model_dir) if model_dir is not None else transforms_reconstruction(transforms)
        source = model_dir if model_dir is not None else transforms
        if ref.num_reg_images() == 0:
            raise ValueError(f"the COLMAP model in {source} has no registered images")
        if err := missing_images_error(source, sorted(image_dir / im.name for im in ref.images.values())):
            raise err
        names = sorted(ref.images[i].name for i in ref.reg_image_ids())
    else:
        names = list_images(image_dir)
        if len(names) < 2:
            raise ValueError(f"map mode needs at least 2 images in {image_dir}, found {len(names)}")
        if hidden := photos_in_subfolders(image_dir):
            log.warning("%d photos in subfolders of %s are left out: the folder holds photos of its own, and "
                        "then only those are the scene's; move them all to one level", hidden, image_dir)
    sizes = check_photos(image_dir, names)
    if len(sizes) > 1 and not posed:
        log.info("sfm: photos of %d pixel sizes, one camera each: %s", len(sizes),
                 ", ".join(f"{w}x{h} ({len(g)})" for (w, h), g in sizes.items()))
    if not in_place:
        link_scene(scene_dir, root)

    seconds: dict[str, float] = {}
    cache = root / "cache" / "sfm"
    cache.mkdir(parents=True, exist_ok=True)
    db_path, state_path = cache / "database.db", cache / "state.json"
    cams = ({int(c): str(ref.cameras[c]) for c in ref.cameras} if ref is not None else cfg.camera_model)
    stats = [(n, st.st_size, st.st_mtime_ns) for n in names for st in [(image_dir / n).stat()]]
    extract_key = _key({"names": stats, "cams": cams, "size": cfg.max_image_size,
                        "n": cfg.max_num_features, "peak": cfg.peak_threshold})
    state = json.loads(state_path.read_text()) if state_path.is_file() else {}
    state.pop("failed", None)
    if recompute or state.get("extract") != extract_key:
        if db_path.exists():
            log.info("sfm: discarding cached database %s (--recompute, other parameters, or an extraction that was stopped)", db_path)
        db_path.unlink(missing_ok=True)
        state = {}
    state["scene"] = str(scene_dir.resolve())  # for `geocues info OUT`'s advice on an unfinished run
    state["flags"] = command_flags(cfg)
    state_path.write_text(json.dumps(state))

    # ---- features
    t0 = time.perf_counter()
    if not db_path.exists() and ref is not None:
        U.database_from_model(db_path, ref)
    U.extract(db_path, image_dir, names, cfg, camera_model=None if ref is not None else cfg.camera_model,
              sizes=sizes)
    state["extract"] = extract_key
    state_path.write_text(json.dumps(state))
    seconds["extract"] = time.perf_counter() - t0

    # ---- pairs
    t0 = time.perf_counter()
    if mode == "triangulate":
        pairs = U.pairs_from_poses(ref, names, cfg.num_neighbors, cfg.max_pair_angle,
                                   cfg.exhaustive_below, cfg.pair_stride)
    elif len(names) <= cfg.exhaustive_below:
        pairs = [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    else:
        pairs = [(a, names[j]) for i, a in enumerate(names)
                 for j in range(i + 1, min(len(names), i + 1 + cfg.sequential_overlap))]
    seconds["pairs"] = time.perf_counter() - t0
    verify_by_poses = mode == "triangulate" and cfg.verification == "poses"
    # matches (and COLMAP's RANSAC verification) are cached apart from the cheap known-pose check
    match_key = _key({"pairs": pairs, "ratio": cfg.max_ratio, "poses": verify_by_poses, "seed": cfg.seed,
                      "inl": None if verify_by_poses else cfg.min_num_inliers})
    verify_key = _key({"epi": cfg.max_epipolar_error, "inl": cfg.min_num_inliers}) if verify_by_poses else ""

    # ---- matching and verification
    t0 = time.perf_counter()
    seconds["match"] = 0.0
    if state.get("match") != match_key:
        U.clear_matches(db_path)
        state.pop("verify", None)
        U.match(db_path, pairs, cfg, cache, verify=not verify_by_poses)
        seconds["match"] = time.perf_counter() - t0
        state["match"] = match_key
        state_path.write_text(json.dumps(state))
    else:
        log.info("sfm: reusing the matches of %d cached pairs", len(pairs))
    t0 = time.perf_counter()
    if verify_by_poses and state.get("verify") != verify_key:
        U.verify_with_poses(db_path, ref, cfg)
        state["verify"] = verify_key
        state_path.write_text(json.dumps(state))
    seconds["verify"] = time.perf_counter() - t0
    n_verified = U.num_verified_pairs(db_path, cfg.min_num_inliers)

    # ---- triangulation or mapping
    t0 = time.perf_counter()
    tmp = Path(tempfile.mkdtemp(prefix="sfm.", dir=cache))
    try:
        if mode == "triangulate":
            rec = U.triangulate(ref, db_path, image_dir, tmp, cfg)
        else:
            rec = U.incremental_map(db_path, image_dir, tmp, cfg, ref)
        n_short = U.drop_short_tracks(rec, cfg.min_track_length)
        if mode == "map" and (rec.num_reg_images() < 3 or rec.num_points3D() == 0):
            raise ValueError(f"incremental mapping registered {rec.num_reg_images()} of the {len(names)} images in "
                             f"{image_dir} and kept {rec.num_points3D()} points: no scene to build on. "
                             + more_points_advice(cfg))
    except ValueError as e:  # recorded for `geocues info OUT`: a rerun of the same command fails the same way
        state["failed"] = str(e)
        state_path.write_text(json.dumps(state))
        raise
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    seconds["triangulate" if mode == "triangulate" else "map"] = time.perf_counter() - t0

    # ---- write
    target = (model_dir if in_place and model_dir is not None else root / "sparse" / "0")
    with atomic_dir(target) as tmp_model:
        binary = (cfg.model_format == "bin" if cfg.model_format != "auto"
                  else not (in_place and model_dir is not None and (model_dir / "images.txt").is_file()))
        (rec.write_binary if binary else rec.write_text)(str(tmp_model))
    report = summarize(rec, mode=mode, n_images=len(names), n_pairs=len(pairs),
                         n_verified=n_verified, seconds=seconds)
    report.update(scene=str(scene_dir.resolve()), model=str(target.resolve()), dropped_short_tracks=n_short,
                  config=asdict(cfg))
    gt = root / "gt" / "mesh.ply"
    if cfg.check_gt and gt.is_file() and report["points"] > 0:
        report["gt_check"] = distance_to_mesh_stats(points_xyz(rec), gt)
    if mode == "map":  # before the report that marks the run finished
        # a posed model's images are its own; mapping may leave photos out
        marks = {"sfm_registered": {"images": report["registered_images"], "photos": len(names)}}
        if ref is None:  # no poses to align to: COLMAP's normalised, arbitrary unit, its own frame (rescale keeps it)
            marks |= {"scale": ARBITRARY_SCALE, "frame": OWN_FRAME}
            log.warning("sfm: the model was mapped from images alone, so its unit is arbitrary while every threshold "
                        "of geocues and splat is in metres: %s", rescale_hint(root))
        _mark_scene(root / "scene.json", marks)
    with atomic_path(root / "sfm_report.json") as tmp_report:
        tmp_report.write_text(json.dumps(report, indent=2))
    _warn_unregistered(names, rec)
    if in_place:
        log.info("sfm: the model in %s was replaced in place (%s)", target, "binary" if binary else "text")
    log.info("sfm: %d points, mean track %.2f, mean reprojection error %.3f px, %.1f s",
             report["points"], report["mean_track_length"], report["mean_reproj_error"],
             sum(seconds.values()))
    if report["points"] < FEW_POINTS:
        log.warning("%s", few_points_advice(report["points"], len(names), n_short, cfg))
    return root
