"""Named training presets: the rows of the paper's ablation (Tab. 3) and this project's extensions.

One table (nerfstudio's method-config style): each preset is a set of overrides of
:class:`splat.train.TrainConfig` fields, named by their dotted path. ``splat train --preset NAME``
starts from it (options given after it still win) and ``splat ablate`` runs one `splat train` per
preset. ``full`` is the default config: IndoorGS as this project runs it.

A preset that only differs from ``full`` through priors the scene lacks (``no-ld`` on a scene
without depth priors, say) ``needs`` them: the ablation reports such a row as n/a instead of
running ``full`` a second time under another name.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from geocues.presets import apply_overrides
from splat.config_types import typed

# The paper's ScanNet++ ablation (Tab. 3): Chamfer-L1 (m), F-score at 5 cm, normal consistency.
PAPER_TAB3 = {
    "no-cues": (0.055, 0.681, 0.859), "sfm-cues-only": (0.051, 0.717, 0.789),
    "no-plane-cues": (0.050, 0.728, 0.862), "no-custom-adc": (0.052, 0.711, 0.839),
    "no-line-adc": (0.051, 0.720, 0.848), "no-sfm-adc": (0.040, 0.771, 0.875),
    "no-plane-adc": (0.046, 0.741, 0.871), "no-ld": (0.044, 0.762, 0.864),
    "no-ln": (0.051, 0.725, 0.848), "no-lnc": (0.044, 0.744, 0.808),
    "full": (0.040, 0.776, 0.877),
}

# The RaDe-GS-style baseline: SfM-point init, plain 3DGS density control for every Gaussian, no
# prior losses; RaDe-GS depth / normal rendering and L_nc kept.
_NO_CUES = {"init_from": "sfm", "strategy.custom_types": (), "loss.use_depth": False,
            "loss.use_normal": False, "loss.lambda_anchor": 0.0}

# The room recipe (docs/training.md): plane-first L_a over every view, PLANE seeds thinned to 90 %.
_ROOM = {"loss.plane_anchor": True, "loss.plane_first": True, "loss.plane_views": "all", "init.plane_share": 0.9}


# The recipe for `geocues mvs` depth priors (docs/training.md, "Photos only: the `mvs` recipe"): L_mv and
# each view's plane normals in L_n, hole seeds at the MVS depth, a TSDF of multi-view consistent depth, smoothed;
# PLANE seeds thinned to 90 % of the budget where the cues would fill it (a no-op on ICL: 46k cues, 150k budget);
# L_d, L_a and L_n stop after a quarter of the run, L_mv goes on (ICL, against stopping them half-way: +0.3 dB held
# out over three seeds at the same mesh; docs/training.md, "Stopping the priors at a quarter").
_MVS = {"loss.lambda_mv": 0.15, "loss.plane_normals": True, "init.fill_holes": True, "init.plane_share": 0.9,
        "tsdf.consistent_views": 2, "tsdf.max_depth_spread": 0.02, "tsdf.weight_threshold": 1.0,
        "tsdf.smooth_iters": 30, "priors_until": 0.25, "priors_kept": ("mv",)}


@dataclass(frozen=True)
class Preset:
    """One named training configuration."""

    name: str
    label: str
    """Row label as the paper's Tab. 3 writes it (or this project's name for an extension)."""
    overrides: dict[str, Any] = field(default_factory=dict)
    """TrainConfig fields (dotted paths) and their values."""
    needs: tuple[str, ...] = ()
    """"depth_priors" / "normal_priors": the row equals ``full`` on a scene without them;
    "plane_anchors": the cue folder must hold them (cue folders written before they existed do not);
    "views_without_normal_priors": the row equals ``full`` (or its base row) when every view has one."""
    iters_factor: float = 1.0
    """Multiplies the run's iterations (no-cues-long: 3x)."""
    extension: bool = False
    """Not a row of the paper: one of this project's additions switched off or on."""

    @property
    def paper(self) -> tuple[float, float, float] | None:
        return PAPER_TAB3.get(self.name)


PRESETS: dict[str, Preset] = {p.name: p for p in [
    Preset("full", "Full model"),
    Preset("no-cues", "w/o cues (baseline)", _NO_CUES),
    Preset("no-cues-long", "w/o cues, 3x iterations", _NO_CUES, iters_factor=3.0),
    Preset("sfm-cues-only", "SfM cues only", {"cue_types": ("SFM",)}),
    Preset("no-plane-cues", "w/o plane cues", {"cue_types": ("SFM", "LINE")}),
    Preset("no-custom-adc", "w/o customised ADC", {"strategy.custom_types": ()}),
    Preset("no-line-adc", "w/o line ADC", {"strategy.custom_types": ("SFM", "PLANE")}),
    Preset("no-sfm-adc", "w/o SfM ADC", {"strategy.custom_types": ("LINE", "PLANE")}),
    Preset("no-plane-adc", "w/o plane ADC", {"strategy.custom_types": ("SFM", "LINE")}),
    Preset("no-ld", "w/o L_d", {"loss.use_depth": False}, needs=("depth_priors",)),
    Preset("no-ln", "w/o L_n", {"loss.use_normal": False}, needs=("normal_priors",)),
    Preset("no-lnc", "w/o L_nc", {"loss.use_nc": False}),
    Preset("paper", "paper's loss (w/o L_a)", {"loss.lambda_anchor": 0.0}, needs=("depth_priors",),
           extension=True),
    Preset("literal-line-clone", "LINE clone at mu + grad (paper verbatim)",
           {"strategy.line_clone_literal": True}, extension=True),
    Preset("mv", "+ multi-view photometric consistency L_mv (PGSR)", {"loss.lambda_mv": 0.15}, extension=True),
    Preset("plane-tangent-adc", "+ PLANE grows within its plane (LINE's tangent clone / split)",
           {"strategy.plane_rule": "tangent"}, extension=True),
    Preset("plane-anchor", "+ L_a on each view's own plane cues", {"loss.plane_anchor": True},
           needs=("plane_anchors",), extension=True),
    Preset("plane-first", "+ L_a holds every view's plane cues first, before the aligned prior",
           {"loss.plane_anchor": True, "loss.plane_first": True, "loss.plane_views": "all"},
           needs=("plane_anchors",), extension=True),
    Preset("fused-anchor", "+ L_a against the TSDF fusion of every view's aligned prior",
           {"loss.fused_anchor": True}, needs=("depth_priors",), extension=True),
    Preset("fused-fill-holes", "+ fused-prior L_a and hole seeds at its depth",
           {"loss.fused_anchor": True, "init.fill_holes": True}, needs=("depth_priors",), extension=True),
    Preset("median-fill-holes", "+ L_a against the median of the views' aligned priors, hole seeds at its depth",
           {"loss.fused_anchor": True, "loss.fused_method": "median", "init.fill_holes": True},
           needs=("depth_priors",), extension=True),
    Preset("fill-holes", "+ Gaussians seeded where the cue Gaussians leave a view open (at its L_a anchor)",
           {"init.fill_holes": True}, needs=("depth_priors",), extension=True),
    Preset("plane-normals", "+ L_n on each view's own plane normals (views without a normal prior)",
           {"loss.plane_normals": True}, needs=("plane_anchors", "views_without_normal_priors"), extension=True),
    Preset("mv-plane-normals", "+ L_mv and L_n on each view's own plane normals",
           {"loss.lambda_mv": 0.15, "loss.plane_normals": True}, needs=("plane_anchors", "views_without_normal_priors"),
           extension=True),
    Preset("flat-all", "+ L_s flattens every Gaussian, not only LINE's (PGSR / 2DGS-like thin Gaussians)",
           {"loss.flat_types": (0, 1, 2)}, extension=True),
    Preset("room", "+ plane cues first, thinned PLANE seeds (train `geocues extract --preset room` cues)",
           _ROOM, needs=("plane_anchors",), extension=True),
    Preset("room-mesh", "room, the geometry frozen from mid-run (colours only after; the mesh-first preset)",
           {**_ROOM, "geometry_until": 0.5}, needs=("plane_anchors",), extension=True),
    Preset("mvs", "photos only: mv-plane-normals, hole seeds, consistent smoothed TSDF, priors off after a quarter but L_mv "
           "(train `geocues mvs` scenes, `geocues extract --preset mvs` cues)", _MVS, needs=("plane_anchors",), extension=True),
    Preset("camera-opt", "+ per-view pose and shared focal refinement (gsplat's pose_opt)",
           {"pose_opt": True, "focal_opt": True}, extension=True),
]}

DEFAULT_ROWS = tuple(PRESETS)


def get_preset(name: str) -> Preset:
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; choose from {', '.join(PRESETS)}")
    return PRESETS[name]


def preset_config(name: str, base: Any = None) -> Any:
    """The TrainConfig of preset ``name`` (on top of ``base``, default TrainConfig())."""
    from splat.train_config import TrainConfig

    preset = get_preset(name)
    cfg = apply_overrides(TrainConfig() if base is None else base, preset.overrides)
    if preset.iters_factor != 1.0:
        cfg = dataclasses.replace(cfg, iters=max(1, round(cfg.iters * preset.iters_factor)))
    return cfg


def config_from_dict(cls, data: dict) -> Any:
    """Rebuild a (nested) config dataclass from its ``asdict()`` form (lists become tuples; keys
    the dataclass does not have are an error naming them)."""
    unknown = sorted(set(data) - {f.name for f in dataclasses.fields(cls)})
    if unknown:
        raise ValueError(f"{cls.__name__}: unknown options {unknown}")
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value = data[f.name]
        sub = f.default_factory() if f.default_factory is not dataclasses.MISSING else None
        if isinstance(value, dict) and dataclasses.is_dataclass(sub):
            value = config_from_dict(type(sub), value)
        elif isinstance(value, list):
            value = tuple(value)
        kwargs[f.name] = typed(cls, f, value)
    return cls(**kwargs)


def load_config_file(path: str | Path) -> Any:
    """The TrainConfig stored in a run's ``config.yaml`` (``splat train --load-config``)."""
    import yaml

    from splat.train_config import TrainConfig

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no config file at {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f"{path} is not valid YAML ({exc})") from None
    if not isinstance(data, dict) or "train" not in data:
        raise ValueError(f"{path} holds no 'train' section (write it with `splat train`)")
    try:
        return config_from_dict(TrainConfig, data["train"])
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None


def write_config_file(path: str | Path, cfg: Any, extra: dict | None = None) -> Path:
    """``config.yaml``: the resolved TrainConfig under ``train`` plus package version and git commit."""
    import subprocess

    import yaml

    from geocues.atomic import atomic_path

    try:
        commit = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5,
                                cwd=Path(__file__).resolve().parent).stdout.strip() or None
    except (OSError, subprocess.SubprocessError):
        commit = None
    try:
        from importlib.metadata import version

        ver = version("indoorgs")
    except Exception:  # noqa: BLE001 - not installed as a package
        ver = None
    doc = {"indoorgs_version": ver, "git_commit": commit, **(extra or {}),
           "train": json.loads(json.dumps(dataclasses.asdict(cfg)))}
    with atomic_path(Path(path)) as tmp:
        tmp.write_text(yaml.safe_dump(doc, sort_keys=False))
    return Path(path)


def missing_needs(preset: Preset, has_depth_priors: bool, has_normal_priors: bool,
                  has_plane_anchors: bool = True, all_normal_priors: bool = False) -> str | None:
    """Why ``preset`` cannot run as itself on this scene and cue folder ("no depth priors"), or None.
    ``all_normal_priors``: every view of the scene has a normal prior."""
    if "plane_anchors" in preset.needs and not has_plane_anchors:
        return "cue folder without plane anchors (written by `geocues extract` since they exist)"
    if "views_without_normal_priors" in preset.needs and all_normal_priors:
        return "every view has a normal prior"
    have = {"depth_priors": has_depth_priors, "normal_priors": has_normal_priors}
    lacking = [n.replace("_", " ") for n in preset.needs if n in have and not have[n]]
    return f"no {' / '.join(x.removesuffix(' priors') for x in lacking)} priors" if lacking else None


def unmet_needs(name: str, scene: Any, cues: str | Path) -> str | None:
    """:func:`missing_needs` of preset ``name`` on ``scene`` (a loaded ``geocues.scene.Scene`` or its
    folder) and the cue folder ``cues``: why it would train as another row there, or None (also when
    the scene cannot be read: the training names that)."""
    preset = get_preset(name)
    if not preset.needs:
        return None
    from geocues.scene import Scene

    if not isinstance(scene, Scene):
        try:
            scene = Scene.load(scene, check_priors=False)
        except (OSError, ValueError):
            return None
    return missing_needs(preset, *needs_facts(scene, cues))


def needs_facts(scene: Any, cues: str | Path) -> tuple[bool, bool, bool, bool]:
    """What :func:`missing_needs` asks of a scene (a ``geocues.scene.Scene``) and a cue folder: depth
    priors, normal priors, plane anchors, a normal prior for every view."""
    from geocues.plane_anchors import plane_anchors_path

    normals = [scene.normal_prior_path(i) is not None for i in range(len(scene.cameras))]
    return scene.has_depth_priors, any(normals), plane_anchors_path(cues).is_file(), all(normals)


# Training presets measured on the cues of an extract preset (docs/training.md): trained on other cues,
# the preset's gains were never measured.
CUE_PRESETS = {"room": "room", "room-mesh": "room", "mvs": "mvs"}


def cue_preset_mismatch(train_preset: str, cues: str | Path) -> str | None:
    """A sentence when training preset ``train_preset`` is the recipe of an extract preset that the
    cues at ``cues`` (a folder or its cues.ply) were not extracted with (their report.json's config),
    else None (also when the cues record no config)."""
    from geocues.cue_io import read_cue_report
    from geocues.presets import EXTRACT_PRESETS
    from splat.checkpoint import config_value

    want = CUE_PRESETS.get(train_preset)
    config = read_cue_report(cues).get("config") if want is not None else None
    if not config:
        return None
    differ = []
    for path, value in EXTRACT_PRESETS[want].items():
        got = config_value(config, path)
        if got is not None and got != value:
            differ.append(f"{path} {got}")
    if not differ:
        return None
    return (f"--preset {train_preset} is the recipe for `geocues extract --preset {want}` cues, and {cues} were "
            f"extracted without it ({', '.join(differ[:3])}{', ...' if len(differ) > 3 else ''}): its measured "
            f"gains need both; extract with `geocues extract SCENE -o CUES --preset {want}`")
