"""The steps of `geocues sfm` (see :mod:`geocues.sfm`): database, features, pairs, matches,
verification against known poses, triangulation / mapping, summary and a check against a GT mesh.

All pycolmap calls live here. The database keeps the model's camera, rig, frame and image ids so
that COLMAP's point triangulator can tie features to the known poses.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from tqdm import tqdm

if TYPE_CHECKING:  # pragma: no cover
    import pycolmap

    from geocues.sfm import SfmConfig

log = logging.getLogger(__name__)

EXTRACT_CHUNK = 16  # images per pycolmap.extract_features call (one progress-bar step each)
MATCH_CHUNK = 64  # pairs per pycolmap.match_image_pairs call


def quiet_pycolmap() -> None:
    """Keep COLMAP's glog output to warnings (errors with `-q`), everything with `-v`: its level
    follows the geocues logger's."""
    import pycolmap

    logger = logging.getLogger("geocues")
    pycolmap.logging.minloglevel = (0 if logger.isEnabledFor(logging.DEBUG) else 1 if logger.isEnabledFor(logging.INFO)
                                    else 2)


def database_from_model(db_path: Path, ref: "pycolmap.Reconstruction") -> None:
    """Create a database whose cameras, rigs, frames and images carry the model's ids (hloc)."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        for cam in ref.cameras.values():
            cam.has_prior_focal_length = True  # known intrinsics (used by the mapper's init)
            db.write_camera(cam, use_camera_id=True)
        for rig in ref.rigs.values():
            db.write_rig(rig, use_rig_id=True)
        for frame in ref.frames.values():
            db.write_frame(frame, use_frame_id=True)
        for im in ref.images.values():
            db.write_image(im, use_image_id=True)
    finally:
        db.close()


def extract(db_path: Path, image_dir: Path, names: list[str], cfg: "SfmConfig",
            camera_model: str | None, sizes: dict[tuple[int, int], list[str]] | None = None) -> None:
    """SIFT features (CPU) for ``names`` that have none yet; images already in the database keep
    their ids and cameras. ``camera_model`` is used for images new to the database: one camera per
    pixel size (``sizes``: size -> names, from ``geocues.photos.check_photos``; with one shared
    camera COLMAP skipped every photo of another size, and a phone's portrait photos)."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        todo = [n for n in names if not _has_keypoints(db, n)]
    finally:
        db.close()
    groups = [todo]
    if camera_model is not None and sizes:  # one camera per size (a database is kept only when whole)
        left = set(todo)
        groups = [[n for n in group if n in left] for group in sizes.values()]
    if not todo:
        log.info("sfm: features of %d images reused from %s", len(names), db_path)
        return
    opts = pycolmap.FeatureExtractionOptions()
    opts.num_threads = cfg.num_threads
    opts.max_image_size = cfg.max_image_size if cfg.max_image_size > 0 else -1
    opts.sift.max_num_features = cfg.max_num_features
    opts.sift.peak_threshold = cfg.peak_threshold
    reader = pycolmap.ImageReaderOptions()
    if camera_model is not None:
        reader.camera_model = camera_model
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(level, 2)  # skip the per-call "maximum number of threads" warning
    with tqdm(total=len(todo), desc="sfm: SIFT", unit="img") as bar:
        for group in groups:
            reader.existing_camera_id = -1  # the group's first chunk makes its camera
            for k in range(0, len(group), EXTRACT_CHUNK):
                chunk = group[k:k + EXTRACT_CHUNK]
                pycolmap.extract_features(str(db_path), str(image_dir), image_names=chunk,
                                          camera_mode=pycolmap.CameraMode.SINGLE,
                                          reader_options=reader, extraction_options=opts,
                                          device=pycolmap.Device.cpu)
                if camera_model is not None and reader.existing_camera_id < 0:  # later chunks share it
                    reader.existing_camera_id = _camera_of(db_path, chunk[0])
                bar.update(len(chunk))
    pycolmap.logging.minloglevel = level


def _has_keypoints(db: "pycolmap.Database", name: str) -> bool:
    if not db.exists_image(name):
        return False
    return db.exists_keypoints(db.read_image_with_name(name).image_id)


def _camera_of(db_path: Path, name: str) -> int:
    """The camera id the database gives the image ``name``."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        return int(db.read_image_with_name(name).camera_id)
    finally:
        db.close()


def pairs_from_poses(ref: "pycolmap.Reconstruction", names: list[str], k: int, max_angle: float,
                     exhaustive_below: int, stride: int = 1) -> list[tuple[str, str]]:
    """Image pairs from known poses (hloc ``pairs_from_poses``): each image with ``k`` of its
    nearest camera centres (every ``stride``-th of the ``k * stride`` nearest, for wider baselines)
    among those whose viewing directions differ by at most ``max_angle`` degrees; all pairs when
    there are at most ``exhaustive_below`` images. Unordered, deduplicated, sorted."""
    by_name = {im.name: im for im in ref.images.values()}
    if len(names) <= exhaustive_below:
        return [(a, b) for i, a in enumerate(names) for b in names[i + 1:]]
    centers = np.stack([by_name[n].projection_center() for n in names])  # [N, 3]
    dirs = np.stack([by_name[n].viewing_direction() for n in names])  # [N, 3]
    return [(names[i], names[j]) for i, j in select_pairs(centers, dirs, k, max_angle, stride)]


def select_pairs(centers: np.ndarray, dirs: np.ndarray, k: int, max_angle: float,
                 stride: int = 1) -> list[tuple[int, int]]:
    """Index pairs (i < j): j is one of every ``stride``-th of the ``k * stride`` nearest centres of
    i (or i of j), among the cameras whose viewing direction differs from i's by at most
    ``max_angle`` degrees. centers, dirs: [N, 3]."""
    centers, dirs = np.asarray(centers, np.float64), np.asarray(dirs, np.float64)
    if centers.ndim != 2 or centers.shape[1] != 3 or dirs.shape != centers.shape:
        raise ValueError(f"centers and dirs must both be [N, 3], got {centers.shape} and {dirs.shape}")
    if k < 1 or stride < 1:
        raise ValueError(f"num_neighbors and pair_stride must be >= 1, got {k} and {stride}")
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    dist = np.linalg.norm(centers[:, None] - centers[None], axis=-1)  # [N, N]
    cos = np.clip(dirs @ dirs.T, -1.0, 1.0)
    dist[np.degrees(np.arccos(cos)) > max_angle] = np.inf
    np.fill_diagonal(dist, np.inf)
    pairs = set()
    for i in range(len(centers)):
        for j in np.argsort(dist[i])[:k * stride:stride]:
            if np.isfinite(dist[i, j]):
                pairs.add((min(i, int(j)), max(i, int(j))))
    return sorted(pairs)


def clear_matches(db_path: Path) -> None:
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        db.clear_matches()
        db.clear_two_view_geometries()
    finally:
        db.close()


def match(db_path: Path, pairs: list[tuple[str, str]], cfg: "SfmConfig", work: Path, verify: bool) -> None:
    """SIFT matching of ``pairs`` (by name) with pycolmap, in chunks for a progress bar; with
    ``verify`` COLMAP's RANSAC two-view geometry is estimated too (else only raw matches)."""
    import pycolmap

    mopts = pycolmap.FeatureMatchingOptions()
    mopts.num_threads = cfg.num_threads
    mopts.use_gpu = False
    mopts.skip_geometric_verification = not verify
    mopts.sift.max_ratio = cfg.max_ratio
    vopts = pycolmap.TwoViewGeometryOptions()
    vopts.min_num_inliers = cfg.min_num_inliers
    vopts.ransac.random_seed = cfg.seed
    pair_file = work / "pairs.txt"
    with tqdm(total=len(pairs), desc="sfm: match", unit="pair") as bar:
        for k in range(0, len(pairs), MATCH_CHUNK):
            chunk = pairs[k:k + MATCH_CHUNK]
            pair_file.write_text("".join(f"{a} {b}\n" for a, b in chunk))
            popts = pycolmap.ImportedPairingOptions()
            popts.match_list_path = str(pair_file)
            pycolmap.match_image_pairs(str(db_path), matching_options=mopts, pairing_options=popts,
                                       verification_options=vopts, device=pycolmap.Device.cpu)
            bar.update(len(chunk))
    (work / "pairs_all.txt").write_text("".join(f"{a} {b}\n" for a, b in pairs))


def sampson_sq(F: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Squared Sampson distance (px^2) of correspondences x1 [M, 2] <-> x2 [M, 2] under F [3, 3]:
    (x2' F x1)^2 / ((F x1)_1^2 + (F x1)_2^2 + (F' x2)_1^2 + (F' x2)_2^2)."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)  # [M, 3]
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    Fx1, Ftx2 = h1 @ F.T, h2 @ F  # [M, 3]
    num = np.einsum("ij,ij->i", h2, Fx1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return num / np.maximum(den, 1e-12)


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])


def verify_with_poses(db_path: Path, ref: "pycolmap.Reconstruction", cfg: "SfmConfig") -> None:
    """Geometric verification with the known poses: keep the matches whose Sampson distance to the
    epipolar geometry F = K2^-T [t]x R K1^-1 (cam2_from_cam1 = (R, t)) is at most
    ``cfg.max_epipolar_error`` px; pairs with fewer than ``cfg.min_num_inliers`` get none."""
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        db.clear_two_view_geometries()
        pair_ids, matches = db.read_all_matches()
        kps: dict[int, np.ndarray] = {}
        kept = 0
        for pid, m in tqdm(list(zip(pair_ids, matches)), desc="sfm: verify", unit="pair"):
            i1, i2 = pycolmap.pair_id_to_image_pair(pid)
            if len(m) < cfg.min_num_inliers:
                continue
            im1, im2 = ref.images[i1], ref.images[i2]
            for i in (i1, i2):
                if i not in kps:
                    kps[i] = db.read_keypoints(i)[:, :2].astype(np.float64)  # COLMAP pixel centres
            rel = im2.cam_from_world() * im1.cam_from_world().inverse()  # cam2_from_cam1
            R, t = np.asarray(rel.rotation.matrix()), np.asarray(rel.translation)
            if np.linalg.norm(t) < 1e-9:  # no baseline: nothing to triangulate from this pair
                continue
            E = _skew(t / np.linalg.norm(t)) @ R
            K1 = np.asarray(im1.camera.calibration_matrix())
            K2 = np.asarray(im2.camera.calibration_matrix())
            F = np.linalg.inv(K2).T @ E @ np.linalg.inv(K1)
            m = np.asarray(m)
            err = sampson_sq(F, kps[i1][m[:, 0]], kps[i2][m[:, 1]])
            inl = m[err <= cfg.max_epipolar_error ** 2]
            if len(inl) < cfg.min_num_inliers:
                continue
            tvg = pycolmap.TwoViewGeometry()
            tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            tvg.E, tvg.F, tvg.cam2_from_cam1 = E, F, rel
            tvg.inlier_matches = inl.astype(np.uint32)
            db.write_two_view_geometry(i1, i2, tvg)
            kept += 1
        log.info("sfm: %d of %d matched pairs verified by the known poses", kept, len(pair_ids))
    finally:
        db.close()


def num_verified_pairs(db_path: Path, min_inliers: int) -> int:
    import pycolmap

    db = pycolmap.Database.open(str(db_path))
    try:
        _, n = db.read_two_view_geometry_num_inliers()
        return int(sum(1 for v in n if v >= min_inliers))
    finally:
        db.close()


def _pipeline_options(cfg: "SfmConfig") -> "pycolmap.IncrementalPipelineOptions":
    import pycolmap

    o = pycolmap.IncrementalPipelineOptions()
    o.num_threads = cfg.num_threads
    o.random_seed = cfg.seed
    o.min_num_matches = cfg.min_num_inliers
    o.triangulation.min_angle = cfg.min_tri_angle
    o.triangulation.merge_max_reproj_error = cfg.max_reproj_error
    o.triangulation.complete_max_reproj_error = cfg.max_reproj_error
    o.triangulation.ignore_two_view_tracks = cfg.ignore_two_view_tracks
    o.mapper.filter_max_reproj_error = cfg.max_reproj_error
    o.mapper.filter_min_tri_angle = cfg.min_tri_angle
    return o


def triangulate(ref: "pycolmap.Reconstruction", db_path: Path, image_dir: Path, work: Path,
                cfg: "SfmConfig") -> "pycolmap.Reconstruction":
    """COLMAP's point triangulator on a copy of ``ref``: poses and intrinsics stay fixed."""
    import pycolmap

    rec = pycolmap.Reconstruction(ref)  # copy; the input model is left untouched
    log.info("sfm: triangulating with fixed poses (%d images)", rec.num_reg_images())
    return pycolmap.triangulate_points(rec, str(db_path), str(image_dir), str(work), clear_points=True,
                                       options=_pipeline_options(cfg), refine_intrinsics=False)


def camera_model_note(cfg: "SfmConfig") -> str:
    """A note on a --camera-model other than the default (every pair can fail verification with one
    that does not fit the lens: OPENCV_FISHEYE on ordinary photos)."""
    default = type(cfg)().camera_model
    if cfg.camera_model == default:
        return ""
    return f"; or --camera-model {cfg.camera_model} does not fit the photos' lens (the default is {default})"


def incremental_map(db_path: Path, image_dir: Path, work: Path, cfg: "SfmConfig",
                    ref: "pycolmap.Reconstruction | None") -> "pycolmap.Reconstruction":
    """COLMAP's incremental mapper with its own triangulation defaults (registration needs the
    weak points too); the model with the most registered images is kept, its points filtered by
    ``cfg``'s angle and error limits and, when a posed reference model exists, it is aligned to it."""
    import pycolmap

    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads, opts.random_seed, opts.min_num_matches = cfg.mapper_threads, cfg.seed, cfg.min_num_inliers
    if ref is not None:  # intrinsics are known: keep them in registration and bundle adjustment
        opts.ba_refine_focal_length = opts.ba_refine_extra_params = False
        opts.ba_refine_principal_point = False
        opts.mapper.abs_pose_refine_focal_length = opts.mapper.abs_pose_refine_extra_params = False
    log.info("sfm: incremental mapping")
    models = pycolmap.incremental_mapping(str(db_path), str(image_dir), str(work), options=opts)
    if not models:
        pairs = num_verified_pairs(db_path, cfg.min_num_inliers)
        why = ("no two photos share enough matches: more overlap between neighbouring photos, more features "
               "(--max-num-features) or a lower --peak-threshold" + camera_model_note(cfg) if pairs == 0 else
               f"{pairs} pairs of photos match, but none is a starting pair COLMAP accepts (its views of the "
               f"matches {opts.mapper.init_min_tri_angle:g} degrees or more apart): photos taken from one spot, "
               "or too few of them; walk around the room while taking them")
        raise ValueError(f"incremental mapping found no model for the images in {image_dir}: {why}")
    rec = max(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()))
    log.info("sfm: kept the largest of %d models (%d images registered)", len(models), rec.num_reg_images())
    n = filter_points(rec, cfg.min_tri_angle, cfg.max_reproj_error)
    log.info("sfm: %d mapped points above %.2f px or below %.1f degrees removed", n, cfg.max_reproj_error,
             cfg.min_tri_angle)
    if ref is not None:
        sim, err = align_to_reference(rec, ref)
        rec.transform(sim)
        log.info("sfm: mapped model aligned to the scene's poses (scale %.4f, median centre error %.4f)",
                 sim.scale, err)
    return rec


def align_to_reference(rec: "pycolmap.Reconstruction", ref: "pycolmap.Reconstruction"
                       ) -> tuple["pycolmap.Sim3d", float]:
    """Similarity ref_from_rec from the images both models share (by name): the rotation is the
    chordal mean of R_ref_i^T R_rec_i (cam_from_world rotations; robust to a straight trajectory,
    unlike centres alone), then scale and translation by least squares on the camera centres
    c_ref = s R c_rec + t. Returns the Sim3d and the median centre error after alignment."""
    import pycolmap

    common = [(im, ref.find_image_with_name(im.name)) for im in (rec.images[i] for i in rec.reg_image_ids())]
    common = [(a, b) for a, b in common if b is not None and b.has_pose]
    if len(common) < 3:
        raise ValueError(f"cannot align the mapped model to the scene's poses: only {len(common)} "
                         f"images in common (need 3)")
    M = sum(np.asarray(b.cam_from_world().rotation.matrix()).T @ np.asarray(a.cam_from_world().rotation.matrix())
            for a, b in common)
    U_, _, Vt = np.linalg.svd(M)
    R = U_ @ np.diag([1, 1, np.linalg.det(U_ @ Vt)]) @ Vt  # [3, 3] nearest rotation
    a = np.stack([R @ x.projection_center() for x, _ in common])  # [M, 3]
    c = np.stack([y.projection_center() for _, y in common])  # [M, 3]
    da, dc = a - a.mean(0), c - c.mean(0)
    scale = float((da * dc).sum() / max((da * da).sum(), 1e-18))
    if scale <= 0:
        raise ValueError("cannot align the mapped model to the scene's poses: degenerate camera centres")
    t = c.mean(0) - scale * a.mean(0)
    err = float(np.median(np.linalg.norm(scale * a + t - c, axis=1)))
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(R), t), err


def filter_points(rec: "pycolmap.Reconstruction", min_angle: float, max_error: float) -> int:
    """Delete points whose mean reprojection error exceeds ``max_error`` px or whose largest angle
    between two observing rays is below ``min_angle`` degrees; return how many."""
    centers = {i: rec.images[i].projection_center() for i in rec.reg_image_ids()}
    cos_max = np.cos(np.radians(min_angle))
    bad = []
    for pid, p in rec.points3D.items():
        if p.error > max_error:
            bad.append(pid)
            continue
        rays = np.stack([centers[e.image_id] for e in p.track.elements]) - p.xyz  # [T, 3]
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        if (rays @ rays.T).min() > cos_max:
            bad.append(pid)
    for pid in bad:
        rec.delete_point3D(pid)
    return len(bad)


def drop_short_tracks(rec: "pycolmap.Reconstruction", min_length: int) -> int:
    """Delete the points observed in fewer than ``min_length`` images; return how many."""
    short = [pid for pid, p in rec.points3D.items() if p.track.length() < min_length]
    for pid in short:
        rec.delete_point3D(pid)
    return len(short)
