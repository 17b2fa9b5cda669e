"""splat/camera_opt.py: per-view pose and shared focal refinement during training (TrainConfig.pose_opt,
focal_opt): the correction's algebra, that a perturbed camera is pulled back by the photometric loss
alone, and a `splat train` run with it (report, mesh with the refined cameras, resume)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from splat.bench import bench_camera, surface_gaussians
from splat.camera import Camera
from splat.camera_opt import CameraRefiner, rodrigues
from splat.rasterize import render


def test_rodrigues_matches_scipy_and_is_smooth_at_zero():
    rng = np.random.default_rng(0)
    for w in [np.zeros(3), 1e-6 * rng.standard_normal(3), 0.01 * rng.standard_normal(3), rng.standard_normal(3)]:
        R = rodrigues(torch.tensor(w, dtype=torch.float64)).numpy()
        np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
    for w0 in (torch.zeros(3, dtype=torch.float64), torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)):
        assert torch.autograd.gradcheck(rodrigues, (w0.clone().requires_grad_(),))


def _scene_camera(cam: Camera):
    from geocues.scene import Camera as SceneCamera

    vm = cam.viewmat.double().numpy()
    return SceneCamera(index=0, image_id=1, name="a.png", image_path=None, width=cam.width, height=cam.height,
                       K=cam.K.double().numpy(), R=vm[:3, :3].copy(), t=vm[:3, 3].copy())


def test_zero_correction_is_the_camera_and_the_numpy_camera_agrees_with_the_torch_one():
    cam = bench_camera(64, 48)
    ref = CameraRefiner(2, 1.0, pose=True, focal=True, pose_lr=1e-3, focal_lr=1e-3)
    c0 = ref.camera(1, cam)
    torch.testing.assert_close(c0.viewmat, cam.viewmat)
    torch.testing.assert_close(c0.K, cam.K)
    torch.testing.assert_close(c0.center, cam.center, atol=1e-5, rtol=0)
    with torch.no_grad():
        ref.rots[1].copy_(torch.tensor([0.01, -0.02, 0.005]))
        ref.transs[1].copy_(torch.tensor([0.02, 0.0, -0.01]))
        ref.log_focal[0] = np.log(1.05)
    c1 = ref.camera(1, cam)
    sc = ref.refined_scene_camera(1, _scene_camera(cam))
    np.testing.assert_allclose(sc.R, c1.viewmat[:3, :3].detach().double().numpy(), atol=1e-6)
    np.testing.assert_allclose(sc.t, c1.viewmat[:3, 3].detach().double().numpy(), atol=1e-6)
    np.testing.assert_allclose(sc.K, c1.K.detach().double().numpy(), rtol=1e-6)
    np.testing.assert_allclose(sc.center, c1.center.detach().double().numpy(), atol=1e-5)
    assert abs(sc.K[0, 0] / cam.K[0, 0].item() - 1.05) < 1e-6 and sc.K[0, 2] == pytest.approx(cam.K[0, 2].item())
    s = ref.summary()
    assert s["focal_factor"] == pytest.approx(1.05) and s["translation_m"]["max"] == pytest.approx(np.hypot(0.02, 0.01))
    assert s["translation_m"]["median"] == pytest.approx(np.hypot(0.02, 0.01) / 2)


def _perturbed(cam: Camera, w, v, focal: float) -> Camera:
    d = np.eye(4)
    d[:3, :3], d[:3, 3] = Rotation.from_rotvec(w).as_matrix(), v
    vm = torch.tensor(d, dtype=torch.float32) @ cam.viewmat
    K = cam.K.clone()
    K[0, 0] *= focal
    K[1, 1] *= focal
    return Camera(K=K, viewmat=vm, width=cam.width, height=cam.height)


def _fit(refiner, start: Camera, target_rgb, params, steps: int):
    for step in range(steps):
        refiner.set_progress(step / steps)
        out = render(params, refiner.camera(0, start), backend="cpu")
        loss = (out["rgb"] - target_rgb).abs().mean()
        loss.backward()
        refiner.step()
    return float(loss.detach())


@pytest.fixture(scope="module")
def truth():
    params = surface_gaussians(6000, sh_degree=0, seed=1)
    return {k: v for k, v in params.items()}


def test_the_photometric_loss_pulls_a_perturbed_pose_back(truth):
    """A view 0.6 deg and 2 cm off its true pose: refining only its camera (the Gaussians fixed and
    exact) brings the rendered image back onto the photo and the pose to within a fifth of the error."""
    cam = bench_camera(96, 72)
    with torch.no_grad():
        target = render(truth, cam, backend="cpu")["rgb"]
    w, v = np.radians(0.6) * np.array([0.6, -0.8, 0.0]), np.array([0.012, -0.016, 0.0])
    start = _perturbed(cam, w, v, 1.0)
    with torch.no_grad():
        loss0 = float((render(truth, start, backend="cpu")["rgb"] - target).abs().mean())
    ref = CameraRefiner(1, 1.0, pose=True, focal=False, pose_lr=2e-3, focal_lr=1e-3)
    loss1 = _fit(ref, start, target, truth, 150)
    fixed = ref.camera(0, start).viewmat.detach()
    err0 = (start.viewmat - cam.viewmat).abs().max().item()
    err1 = (fixed - cam.viewmat).abs().max().item()
    assert loss1 < 0.5 * loss0, (loss0, loss1)
    assert err1 < 0.2 * err0, (err0, err1)


def test_the_photometric_loss_recovers_a_focal_5_percent_off(truth):
    cam = bench_camera(96, 72)
    with torch.no_grad():
        target = render(truth, cam, backend="cpu")["rgb"]
    start = _perturbed(cam, np.zeros(3), np.zeros(3), 0.95)
    ref = CameraRefiner(1, 1.0, pose=False, focal=True, pose_lr=1e-3, focal_lr=2e-3)
    _fit(ref, start, target, truth, 120)
    assert abs(ref.summary()["focal_factor"] * 0.95 - 1.0) < 0.01, ref.summary()


def test_only_the_rendered_view_moves(truth):
    """A step moves the correction of the view that was rendered and no other, also on later steps
    (one [V, 6] Adam tensor would keep moving every view seen before by its decaying momentum)."""
    cam = bench_camera(48, 36)
    with torch.no_grad():
        target = render(truth, cam, backend="cpu")["rgb"]
    start = _perturbed(cam, np.radians(0.5) * np.array([1.0, 0, 0]), np.zeros(3), 1.0)
    ref = CameraRefiner(3, 1.0, pose=True, focal=False, pose_lr=1e-3, focal_lr=1e-3)
    for k in (0, 1, 1, 1):
        out = render(truth, ref.camera(k, start), backend="cpu")
        (out["rgb"] - target).abs().mean().backward()
        ref.step()
        if k == 0:
            after_0 = ref.rot[0].clone()
    assert after_0.abs().max() > 0 and torch.equal(ref.rot[0], after_0)  # view 0 untouched while 1 trains
    assert ref.rot[1].abs().max() > 0 and not ref.rot[2].abs().any() and not ref.trans[2].abs().any()


def test_held_out_views_take_the_shared_focal_and_keep_their_pose():
    from dataclasses import dataclass

    @dataclass
    class View:
        camera: Camera

    cam = bench_camera(64, 48)
    ref = CameraRefiner(2, 1.0, pose=True, focal=True, pose_lr=1e-3, focal_lr=1e-3)
    with torch.no_grad():
        ref.rots[0].copy_(torch.tensor([0.02, 0.0, 0.01]))
        ref.log_focal[0] = np.log(0.95)
    held_out = ref.test_view(View(cam)).camera
    torch.testing.assert_close(held_out.viewmat, cam.viewmat)
    torch.testing.assert_close(held_out.K[0, 0], cam.K[0, 0] * 0.95)
    torch.testing.assert_close(held_out.K[1, 1], cam.K[1, 1] * 0.95)
    torch.testing.assert_close(held_out.K[:, 2], cam.K[:, 2])
    assert CameraRefiner(2, 1.0, True, False, 1e-3, 1e-3).test_view(View(cam)).camera is cam


def test_refiner_needs_something_to_refine():
    with pytest.raises(ValueError, match="pose or focal"):
        CameraRefiner(3, 1.0, pose=False, focal=False, pose_lr=1e-3, focal_lr=1e-3)


def test_train_with_camera_refinement_reports_it_meshes_and_resumes(tmp_path):
    """`splat train --pose-opt --focal-opt` on the tiny room: the report holds the corrections, the mesh
    is fused with the refined cameras, and a run stopped half-way resumes to the uninterrupted result."""
    from cues_synth import make_room_scene
    from geocues.cue_io import write_cues_ply
    from splat.checkpoint import TrainingInterrupted
    from splat.train import TrainConfig, run
    from test_train import surface_cues

    root = make_room_scene(tmp_path / "room", n_views=8, w=48, h=36, priors="none")
    write_cues_ply(tmp_path / "cues.ply", surface_cues(root, n_plane=400))
    cfg = TrainConfig(iters=40, pose_opt=True, focal_opt=True, checkpoints=(), seed=0)
    out = run(cfg, root, tmp_path / "cues.ply", tmp_path / "a")
    rep = json.loads((out / "report.json").read_text())
    cr = rep["camera_refinement"]
    assert cr["pose"] and cr["focal"] and cr["translation_m"]["max"] > 0 and cr["focal_factor"] != 1.0
    assert (out / "mesh.ply").is_file()
    z = np.load(out / "camera_refinement.npz")
    assert z["rot"].shape == (len(z["names"]), 3) and float(z["focal_factor"]) == pytest.approx(cr["focal_factor"])
    # `splat render` draws the training views with their corrections and every view with the focal
    from splat.render_run import RenderConfig, _chosen, load_run

    scene, _, _ = load_run(out)
    names = [str(n) for n in z["names"]]
    # cameras.json (SIBR, the reference render.py, web viewers) holds the cameras the Gaussians were
    # fitted to, as `splat render` draws them: not the scene's unrefined ones
    exported = json.loads((out / "cameras.json").read_text())
    for which in ("train", "test"):
        cams = _chosen(RenderConfig(views=which), scene, out)
        assert cams
        for v in cams:
            c = scene.cameras[v.index]
            e = exported[v.index]
            assert e["fx"] == pytest.approx(v.K[0, 0], rel=1e-12) and e["fx"] != pytest.approx(c.K[0, 0], rel=1e-6)
            np.testing.assert_allclose(e["position"], -v.R.T @ v.t, atol=1e-12)
            np.testing.assert_allclose(e["rotation"], v.R.T, atol=1e-12)
            np.testing.assert_allclose(v.K[0, 0], c.K[0, 0] * cr["focal_factor"], rtol=1e-9)
            np.testing.assert_allclose(v.K[0, 2], c.K[0, 2])
            if which == "test":
                np.testing.assert_array_equal(v.R, c.R)
                continue
            Rc = Rotation.from_rotvec(z["rot"][names.index(c.name)]).as_matrix()
            np.testing.assert_allclose(v.R, Rc @ c.R, atol=1e-9)
            np.testing.assert_allclose(v.t, Rc @ c.t + z["trans"][names.index(c.name)], atol=1e-9)

    import splat.train as train_mod

    calls = {"n": 0}
    real = train_mod.train_step

    def stop_at_20(*a, **k):
        calls["n"] += 1
        if calls["n"] == 20:
            import os
            import signal
            os.kill(os.getpid(), signal.SIGINT)
        return real(*a, **k)

    train_mod.train_step = stop_at_20
    try:
        with pytest.raises(TrainingInterrupted):
            run(cfg, root, tmp_path / "cues.ply", tmp_path / "b")
    finally:
        train_mod.train_step = real
    out_b = run(cfg, root, tmp_path / "cues.ply", tmp_path / "b", resume=True)
    rep_b = json.loads((out_b / "report.json").read_text())
    assert rep_b["resumed_from_step"] is not None
    assert rep_b["camera_refinement"]["focal_factor"] == pytest.approx(cr["focal_factor"], rel=1e-5)
    assert rep_b["camera_refinement"]["translation_m"]["max"] == pytest.approx(cr["translation_m"]["max"], rel=1e-4)


def test_frozen_geometry_freezes_the_camera_corrections_too(tmp_path, monkeypatch):
    """`--geometry-until 0.5` with pose and focal refinement: the colour step renders the refined
    cameras, detached, and leaves the corrections as the full step with rates at 0 does."""
    from cues_synth import make_room_scene
    from geocues.cue_io import write_cues_ply
    import splat.train as train_mod
    from splat.train import TrainConfig, run
    from test_train import surface_cues

    root = make_room_scene(tmp_path / "room", n_views=8, w=48, h=36, priors="none")
    write_cues_ply(tmp_path / "cues.ply", surface_cues(root, n_plane=400))
    cfg = TrainConfig(iters=40, pose_opt=True, focal_opt=True, checkpoints=(), seed=0, mesh=False, geometry_until=0.5)
    corrections = []
    for fast in (True, False):
        monkeypatch.setattr(train_mod, "COLOUR_STEP_WHEN_FROZEN", fast)
        out = run(cfg, root, tmp_path / "cues.ply", tmp_path / f"run_{fast}")
        z = np.load(out / "camera_refinement.npz")
        corrections.append((z["rot"], z["trans"], float(z["focal_factor"])))
    (rot, trans, focal), (rot_o, trans_o, focal_o) = corrections
    assert np.abs(rot).max() > 0 and focal != 1.0
    np.testing.assert_array_equal(rot, rot_o)
    np.testing.assert_array_equal(trans, trans_o)
    assert focal == focal_o


@pytest.mark.parametrize("field", ["pose_lr", "focal_lr"])
def test_a_bad_learning_rate_is_refused_before_any_work(field):
    from splat.train import TrainConfig

    for bad in (0.0, -1e-3, float("nan")):
        with pytest.raises(ValueError, match=f"--{field.replace('_', '-')} must be a finite number > 0"):
            TrainConfig(pose_opt=True, **{field: bad}).validate()
