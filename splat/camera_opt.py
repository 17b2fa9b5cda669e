"""Refining the training cameras during training (an extension; gsplat's ``pose_opt``).

Real captures come with imperfect poses and intrinsics: a colour camera offset from the depth
camera whose poses a dataset ships, SfM poses a few millimetres off, a focal 5 % wrong. With
``TrainConfig.pose_opt`` every training view gets a rigid correction in its own camera frame,

    viewmat' = [[Rodrigues(w_k), v_k], [0, 1]] @ viewmat_k        (w_k rad, v_k metres; 0 at the start)

and with ``TrainConfig.focal_opt`` all views share one focal factor, fx' = fx e^s, fy' = fy e^s
(principal point kept). They are learnt with the Gaussians by their own Adam (rotation lr
``pose_lr``, translation ``pose_lr`` x the scene scale, focal ``focal_lr``, each decaying to a tenth
by the end), through the torch projection, which carries gradients to the camera (the C++ and CUDA
projections do not): a step with refinement costs more on the CPU (docs/training.md). The mesh is
fused with the refined cameras. Held-out test views keep their poses (nothing in training sees
them) but take the shared focal factor: they come from the same camera. ``splat render`` applies
the saved corrections (RUN/camera_refinement.npz, :func:`load_refinement`) the same way.

Each view's correction is a parameter of its own, so Adam moves only the view that was rendered
(a parameter without a gradient is skipped) and counts its steps per view. One [V, 6] tensor would
move every view at every step by its decaying first moment: ~13 x lr per visit for a view seen every
184 steps, which on ICL made the poses worse than they started (docs/training.md).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import Tensor

from splat.camera import Camera


def rodrigues(w: Tensor) -> Tensor:
    """Rotation matrix [3, 3] of the axis-angle vector w [3] (radians), differentiable at w = 0."""
    theta2 = (w * w).sum()
    wx = torch.zeros(3, 3, dtype=w.dtype, device=w.device)
    rows = torch.tensor([0, 0, 1, 1, 2, 2], device=w.device)
    cols = torch.tensor([1, 2, 0, 2, 0, 1], device=w.device)
    wx = wx.index_put((rows, cols),
                      torch.stack([-w[2], w[1], w[2], -w[0], -w[1], w[0]]))
    small = theta2 < 1e-8
    theta = torch.sqrt(torch.where(small, torch.ones_like(theta2), theta2))
    # sin(t)/t and (1 - cos t)/t^2, by their Taylor series near 0 (exact to float there)
    a = torch.where(small, 1.0 - theta2 / 6.0, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24.0, (1.0 - torch.cos(theta)) / (theta * theta))
    return torch.eye(3, dtype=w.dtype, device=w.device) + a * wx + b * (wx @ wx)


class CameraRefiner:
    """Per-view pose corrections and a shared focal factor for ``n_views`` training views."""

    def __init__(self, n_views: int, scene_scale: float, pose: bool, focal: bool, pose_lr: float,
                 focal_lr: float, device: torch.device | str = "cpu") -> None:
        if n_views < 1:
            raise ValueError(f"n_views must be >= 1, got {n_views}")
        if not (pose_lr > 0 and focal_lr > 0 and scene_scale > 0):
            raise ValueError(f"pose_lr, focal_lr and scene_scale must be positive, got {pose_lr}, {focal_lr}, "
                             f"{scene_scale}")
        self.pose, self.focal = bool(pose), bool(focal)
        self.rots = [torch.nn.Parameter(torch.zeros(3, device=device)) for _ in range(n_views)]
        self.transs = [torch.nn.Parameter(torch.zeros(3, device=device)) for _ in range(n_views)]
        self.log_focal = torch.nn.Parameter(torch.zeros(1, device=device))
        groups = []
        if self.pose:
            groups += [{"params": self.rots, "lr": pose_lr, "name": "rot"},
                       {"params": self.transs, "lr": pose_lr * scene_scale, "name": "trans"}]
        if self.focal:
            groups.append({"params": [self.log_focal], "lr": focal_lr, "name": "focal"})
        if not groups:
            raise ValueError("a CameraRefiner needs pose or focal refinement on")
        self.base_lr = [g["lr"] for g in groups]
        self.optimizer = torch.optim.Adam(groups, eps=1e-15)

    @property
    def rot(self) -> Tensor:
        """[V, 3] rotation corrections (axis-angle, radians), a copy."""
        return torch.stack([r.detach() for r in self.rots])

    @property
    def trans(self) -> Tensor:
        """[V, 3] translation corrections (metres, camera frame), a copy."""
        return torch.stack([t.detach() for t in self.transs])

    def camera(self, k: int | None, cam: Camera) -> Camera:
        """View k's camera with its correction (differentiable in the corrections); k None: a held-out
        view, the shared focal only."""
        vm, K = cam.viewmat, cam.K
        if self.pose and k is not None:
            top = torch.cat([rodrigues(self.rots[k]), self.transs[k][:, None]], 1).to(vm.dtype)  # [3, 4]
            vm = torch.cat([top, vm.new_tensor([[0.0, 0.0, 0.0, 1.0]])]) @ vm
        if self.focal:
            f = torch.exp(self.log_focal[0]).to(K.dtype)
            K = torch.stack([K[0] * torch.stack([f, f.new_ones(()), f.new_ones(())]),
                             K[1] * torch.stack([f.new_ones(()), f, f.new_ones(())]), K[2]])
        centre = -(vm[:3, :3].T @ vm[:3, 3])  # differentiable (Camera would detach it)
        return Camera(K=K, viewmat=vm, width=cam.width, height=cam.height, center=centre)

    def view(self, k: int, view):
        """A copy of the training view ``view`` (splat.views.View, k-th of its set) with its refined camera."""
        return dataclasses.replace(view, camera=self.camera(k, view.camera))

    def test_view(self, view):
        """A copy of a held-out view with the shared focal factor (its pose unchanged); ``view`` itself
        without focal refinement."""
        if not self.focal:
            return view
        with torch.no_grad():
            return dataclasses.replace(view, camera=self.camera(None, view.camera))

    def set_progress(self, fraction: float, frozen: bool = False) -> None:
        """Learning rates decayed exponentially to a tenth at the end of the run (fraction 0..1);
        0 when ``frozen`` (TrainConfig.geometry_until)."""
        mult = 0.0 if frozen else 0.1 ** min(max(fraction, 0.0), 1.0)
        for g, lr in zip(self.optimizer.param_groups, self.base_lr):
            g["lr"] = lr * mult

    def step(self) -> None:
        self.optimizer.step()
        self.optimizer.zero_grad(set_to_none=True)

    def zero_grad(self) -> None:
        self.optimizer.zero_grad(set_to_none=True)

    def state_dict(self) -> dict:
        return {"rot": self.rot.clone(), "trans": self.trans.clone(),
                "log_focal": self.log_focal.detach().clone(), "optimizer": self.optimizer.state_dict()}

    def load_state_dict(self, sd: dict) -> None:
        with torch.no_grad():
            for k in range(len(self.rots)):
                self.rots[k].copy_(sd["rot"][k])
                self.transs[k].copy_(sd["trans"][k])
            self.log_focal.copy_(sd["log_focal"])
        self.optimizer.load_state_dict(sd["optimizer"])

    def refined_scene_camera(self, k: int, cam):
        """The scene camera ``cam`` (geocues.scene.Camera, numpy) of training view k with its correction."""
        with torch.no_grad():
            R = rodrigues(self.rots[k].detach().double().cpu()).numpy() if self.pose else np.eye(3)
            v = self.transs[k].detach().double().cpu().numpy() if self.pose else np.zeros(3)
            f = math.exp(float(self.log_focal.detach()[0])) if self.focal else 1.0
        K, R, t = refine_Rt(cam.K, cam.R, cam.t, (R, v) if self.pose else None, f)
        return dataclasses.replace(cam, K=K, R=R, t=t)

    def save(self, path, names: list[str]) -> None:
        """The corrections as an npz: names [V] (the views' image names), rot [V, 3] (axis-angle, rad),
        trans [V, 3] (m, camera frame; viewmat' = [Rodrigues(rot) | trans] @ viewmat), focal_factor."""
        if len(names) != len(self.rots):
            raise ValueError(f"{len(names)} names for {len(self.rots)} views")
        np.savez(path, names=np.asarray(names), rot=self.rot.cpu().numpy(), trans=self.trans.cpu().numpy(),
                 focal_factor=np.float64(math.exp(float(self.log_focal.detach()[0]))),
                 pose=np.bool_(self.pose), focal=np.bool_(self.focal))

    def summary(self) -> dict:
        """The corrections learnt: per view rotation (degrees) and translation (metres), the focal factor."""
        rot_deg = np.degrees(self.rot.norm(dim=1).cpu().numpy())
        trans_m = self.trans.norm(dim=1).cpu().numpy()
        return {"pose": self.pose, "focal": self.focal, "focal_factor": math.exp(float(self.log_focal.detach()[0])),
                "rotation_deg": {"median": float(np.median(rot_deg)), "max": float(rot_deg.max())},
                "translation_m": {"median": float(np.median(trans_m)), "max": float(trans_m.max())}}


def load_refinement(path) -> tuple[dict[str, tuple[np.ndarray, np.ndarray]], float]:
    """RUN/camera_refinement.npz as ({image name: (R_corr [3, 3], trans [3])}, focal factor)."""
    from scipy.spatial.transform import Rotation

    with np.load(path) as z:
        names, rot, trans = [str(n) for n in z["names"]], z["rot"], z["trans"]
        focal = float(z["focal_factor"]) if bool(z["focal"]) else 1.0
        pose = bool(z["pose"])
    if not pose:
        return {}, focal
    mats = Rotation.from_rotvec(rot.astype(np.float64)).as_matrix()
    return {n: (m, v.astype(np.float64)) for n, m, v in zip(names, mats, trans)}, focal


def refine_Rt(K: np.ndarray, R: np.ndarray, t: np.ndarray, correction: tuple[np.ndarray, np.ndarray] | None,
              focal: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(K, R, t) of a world-to-camera pose with a saved correction (None: pose kept) and focal factor."""
    K = np.array(K, dtype=np.float64, copy=True)
    K[0, 0] *= focal
    K[1, 1] *= focal
    if correction is None:
        return K, R, t
    Rc, v = correction
    return K, Rc @ R, Rc @ t + v
