"""The options of `splat train` (one dataclass per concern, tyro turns them into the CLI).

Kept apart from splat/train.py so that splat/presets.py (named configurations, config files) and the
trainer both import it without importing each other.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass, field

from geocues.types import CueType
from splat.config_types import check_types
from splat.gaussians import InitConfig
from splat.guard import GuardConfig
from splat.losses import LossConfig, without_priors
from splat.mesh import TSDFConfig
from splat.strategy import PAPER_ITERS, IndoorStrategyConfig


@dataclass
class LearningRates:
    """Adam learning rates per parameter (3DGS defaults; positions scale with the scene)."""

    means: float = 1.6e-4
    """Initial position learning rate, times the scene scale."""
    means_final: float = 1.6e-6
    """Final position learning rate (exponential decay over the run), times the scene scale."""
    scales: float = 5e-3
    """Log-scale learning rate."""
    quats: float = 1e-3
    """Rotation learning rate."""
    opacities: float = 5e-2
    """Opacity-logit learning rate."""
    sh0: float = 2.5e-3
    """SH DC learning rate."""
    shN: float = 2.5e-3 / 20
    """Higher SH bands' learning rate."""


@dataclass
class TrainConfig:
    """Options of `splat train`."""

    iters: int = 30_000
    """Training iterations (the paper's 30k; every schedule of the paper scales with this)."""
    downscale: float = 1.0
    """Divide image size and intrinsics by this (2 = half resolution)."""
    test_every: int = 8
    """Every n-th image (name order) is a held-out test view (3DGS); 0 = none."""
    sh_degree: int = 3
    """Final SH degree of the colours (raised by one every iters/30 iterations, 3DGS: 1000 of 30k)."""
    cue_types: tuple[str, ...] = ("SFM", "LINE", "PLANE")
    """Cue types that seed Gaussians (the paper's ablations drop some)."""
    init_from: str = "cues"
    """Seed the Gaussians from "cues" (CUES/cues.ply, typed) or "sfm" (the scene's own COLMAP points,
    all SFM-typed, no outlier removal: the 3DGS / RaDe-GS baseline)."""
    init_ply: str | None = None
    """Start from the Gaussians of this PLY instead (this project's, the 3DGS reference's or gsplat's
    export; cue types from its cue_type.npy sidecar, else all SFM). Overrides init_from."""
    view: bool = False
    """Show the training live in the browser (viser, like `splat view`) at http://127.0.0.1:VIEW_PORT."""
    view_port: int = 8080
    """Port of the live view (0: any free port)."""
    view_every: int = 100
    """Refresh the live view every this many iterations."""
    device: str = "auto"
    """"cpu", "cuda" or "auto" (CUDA when available)."""
    backend: str = "auto"
    """Rasterizer backend: "auto" (the C++ kernels on the CPU, the CUDA kernels on a GPU), "cpu", "cuda", "torch"."""
    adam: str = "fused"
    """Adam implementation: "fused" (torch's single-kernel Adam, ~5x faster on the CPU) or "torch"
    (torch's default implementation); the same update up to float rounding (tests/test_train_step.py)."""
    pose_opt: bool = False
    """Refine each training view's pose during training (an extension, gsplat's pose_opt; splat/camera_opt.py):
    a rigid correction per view, learnt with the Gaussians; the mesh is fused with the refined poses."""
    focal_opt: bool = False
    """Refine one focal-length factor shared by all views during training (an extension; splat/camera_opt.py)."""
    pose_lr: float = 2e-3
    """Learning rate of the pose corrections: radians for the rotation, x the scene scale for the translation."""
    focal_lr: float = 5e-4
    """Learning rate of the log focal factor."""
    compile: bool = False
    """On a GPU, compile the render's per-pixel maps with torch.compile (fused Triton kernels,
    splat/compiled.py), and the loss terms where the CUDA loss kernels (--loss.kernels fused, the
    default) did not build: the same loss up to float rounding (tests/test_compiled.py). About 90 s of
    compiling on a machine without torch's kernel cache; what it saves next to the CUDA kernels is in
    docs/rasterizer.md. No effect on the CPU."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Background colour behind the Gaussians."""
    checkpoints: tuple[float, ...] = (0.1, 0.25, 0.5, 1.0)
    """Fractions of the run after which test views are evaluated (accuracy against time)."""
    geometry_until: float = 1.0
    """Fraction of the run after which the Gaussians' geometry (means, scales, rotations, opacities)
    and the camera refinement stop learning (learning rate 0), density control stops (if it has not
    yet), and only the colours train on (1.0: never; an extension). The mesh is fused from that
    geometry: with 0.5 it is the mesh of the step-0.5 checkpoint, and the rest of the run refines the
    novel views' colours only, by a colour-only step (splat/frozen.py, about 1.8x cheaper on the CPU).
    `--preset room-mesh` is `room` with 0.5."""
    priors_until: float = 1.0
    """Fraction of the run after which the prior terms stop (L_d, L_a, L_n and L_mv; see
    splat.losses.without_priors) while L_rgb, L_s and L_nc and the whole geometry go on learning
    (1.0: never; an extension). The priors place the surface early; the rest of the run fits the
    photos without pulling towards priors that disagree with them."""
    priors_kept: tuple[str, ...] = ()
    """The prior terms that go on after priors_until ("depth", "anchor", "normal", "mv")."""
    log_every: int = 50
    """Write a train_log.jsonl line every this many iterations."""
    mesh: bool = True
    """Fuse a TSDF mesh from the rendered depth (--tsdf.depth) of the training views at the end."""
    mesh_at_checkpoints: bool = False
    """Also fuse a mesh at every checkpoint (OUT/checkpoints/mesh_STEP.ply), for accuracy against time."""
    mesh_every: int = 1
    """Use every n-th training view for the TSDF fusion."""
    seed: int = 0
    """Seed of the view order, the loss patches and the density control."""
    save_every: float = 300.0
    """Write OUT.partial/ckpt/last.pt every this many seconds of training (0: only when stopped by
    SIGINT / SIGTERM); `--resume` continues from it."""
    keep_ckpt: bool = False
    """Write OUT/ckpt/last.pt (the final state) at the end of a finished run and keep it."""
    lr: LearningRates = field(default_factory=LearningRates)
    init: InitConfig = field(default_factory=InitConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    strategy: IndoorStrategyConfig = field(default_factory=IndoorStrategyConfig)
    tsdf: TSDFConfig = field(default_factory=TSDFConfig)
    guard: GuardConfig = field(default_factory=GuardConfig)

    def validate(self) -> None:
        """Raise ValueError naming the first impossible option."""
        def finite_pos(name: str, value: float, zero_ok: bool = False) -> None:
            if not (math.isfinite(value) and (value >= 0 if zero_ok else value > 0)):
                raise ValueError(f"--{name} must be a finite number {'>= 0' if zero_ok else '> 0'}, got {value}")

        check_types(self)  # a value of another type (10.5 iterations, "abc") names its field first
        if self.adam not in ("fused", "torch"):
            raise ValueError(f"--adam must be 'fused' or 'torch', got {self.adam!r}")
        if self.loss.kernels not in ("fused", "torch"):
            raise ValueError(f"--loss.kernels must be 'fused' or 'torch', got {self.loss.kernels!r}")
        if self.iters <= 0:
            raise ValueError(f"--iters must be positive, got {self.iters}")
        if len(self.background) != 3 or not all(math.isfinite(c) for c in self.background):
            raise ValueError(f"--background must be three finite numbers (RGB), got {self.background!r}")
        if self.strategy.total_iters != PAPER_ITERS:  # the run's length sets it (it was ignored in silence)
            raise ValueError(f"--strategy.total-iters is the run's length, set from --iters; leave it out "
                             f"(got {self.strategy.total_iters}; a config file that sets it: pass "
                             f"--strategy.total-iters {PAPER_ITERS})")
        if not 0 <= self.loss.lambda_dssim <= 1:  # (1 - l) L1 + l D-SSIM: above 1 the L1 term pushes away
            raise ValueError(f"--loss.lambda-dssim weighs D-SSIM against L1 and must be in [0, 1], "
                             f"got {self.loss.lambda_dssim}")
        budget = self.strategy.max_gaussians
        if budget != "auto" and (isinstance(budget, bool) or not isinstance(budget, numbers.Integral) or budget < 0):
            raise ValueError(f"--strategy.max-gaussians must be 'auto' or an integer >= 0 (0: no limit), got {budget!r}")
        finite_pos("downscale", self.downscale)
        finite_pos("pose-lr", self.pose_lr)
        finite_pos("focal-lr", self.focal_lr)
        if not 0 <= self.sh_degree <= 3:
            raise ValueError(f"--sh-degree must be in 0..3, got {self.sh_degree}")
        bad = [t for t in self.cue_types if t not in CueType.__members__]
        if bad:
            raise ValueError(f"--cue-types: unknown cue types {bad}; choose from {list(CueType.__members__)}")
        for name, value in asdict(self.lr).items():
            finite_pos(f"lr.{name.replace('_', '-')}", value)
        if not 0 < self.init.init_opacity < 1:
            raise ValueError(f"--init.init-opacity must be in (0, 1), got {self.init.init_opacity}")
        for name in ("min_scale", "flat_ratio", "max_scale_mult"):
            finite_pos(f"init.{name.replace('_', '-')}", getattr(self.init, name))
        if self.init.knn < 1:
            raise ValueError(f"--init.knn must be >= 1, got {self.init.knn}")
        finite_pos("init.hole-voxel", self.init.hole_voxel)
        if self.init.hole_stride < 1 or not 0 < self.init.hole_alpha <= 1:
            raise ValueError(f"--init.hole-stride must be >= 1 and --init.hole-alpha in (0, 1], got "
                             f"{self.init.hole_stride}, {self.init.hole_alpha}")
        if self.loss.plane_first and not self.loss.plane_anchor:
            raise ValueError("--loss.plane-first puts the plane cues' depth first in L_a: it needs --loss.plane-anchor")
        if self.loss.plane_views != "own" and not (self.loss.plane_anchor or self.loss.plane_normals):
            raise ValueError("--loss.plane-views chooses the plane cues of --loss.plane-anchor / --loss.plane-normals: "
                             "it needs one of them")
        if not 0 <= self.init.plane_share <= 1:
            raise ValueError(f"--init.plane-share must be in [0, 1], got {self.init.plane_share}")
        finite_pos("loss.fused-voxel", self.loss.fused_voxel)
        if self.loss.fused_neighbours < 1 or self.loss.fused_method not in ("tsdf", "median"):
            raise ValueError(f"--loss.fused-neighbours must be >= 1 and --loss.fused-method 'tsdf' or 'median', "
                             f"got {self.loss.fused_neighbours}, {self.loss.fused_method!r}")
        finite_pos("loss.fused-trunc", self.loss.fused_trunc)
        for name, value in asdict(self.loss).items():
            if isinstance(value, float):
                finite_pos(f"loss.{name.replace('_', '-')}", value, zero_ok=True)
        if self.loss.mv_patch < 3 or self.loss.mv_patch % 2 == 0 or self.loss.mv_samples < 1 or self.loss.mv_neighbours < 1:
            raise ValueError(f"--loss.mv-patch must be odd and >= 3, --loss.mv-samples and --loss.mv-neighbours >= 1 "
                             f"(got {self.loss.mv_patch}, {self.loss.mv_samples}, {self.loss.mv_neighbours})")
        if not 0 < self.geometry_until <= 1:
            raise ValueError(f"--geometry-until must be a fraction in (0, 1], got {self.geometry_until}")
        if not 0 <= self.priors_until <= 1:
            raise ValueError(f"--priors-until must be a fraction in [0, 1], got {self.priors_until}")
        without_priors(self.loss, self.priors_kept)  # names an unknown --priors-kept term
        if not all(0 < c <= 1 for c in self.checkpoints):
            raise ValueError(f"--checkpoints must be fractions in (0, 1], got {self.checkpoints}")
        finite_pos("save-every", self.save_every, zero_ok=True)
        if self.log_every < 1 or self.mesh_every < 1 or self.view_every < 1:
            raise ValueError("--log-every, --mesh-every and --view-every must be >= 1")
        if not 0 <= self.view_port < 65536:
            raise ValueError(f"--view-port must be in 0..65535, got {self.view_port}")
        self.strategy.validate()
        self.tsdf.validate()
        self.guard.validate()
