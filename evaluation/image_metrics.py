"""Image metrics for held-out views: PSNR, SSIM and (with user-supplied weights) LPIPS.

Images are torch tensors, float, H x W x C (C = 3 for RGB), values in [0, 1]
(docs/conventions.md). SSIM follows 3DGS's ``utils/loss_utils.py`` (the code behind the
published splatting numbers): an 11 x 11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03, each
channel filtered separately with zero padding ("same" size), the SSIM map averaged over all pixels
and channels. ``padding="valid"`` averages only where the window fits inside the image, as
pytorch-msssim and scikit-image do; the two differ in the border pixels only.

LPIPS needs a learned network. Nothing is downloaded: pass a TorchScript file you made yourself
(see ``load_lpips``) or leave it out.
"""

from __future__ import annotations

import json
import logging
import math
import warnings
from pathlib import Path
from typing import Callable, Literal, Sequence

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

log = logging.getLogger(__name__)


def _check_pair(img: torch.Tensor, ref: torch.Tensor) -> None:
    """Both tensors, floating point, the same H x W x C shape."""
    for name, x in (("img", img), ("ref", ref)):
        if not isinstance(x, torch.Tensor):
            raise ValueError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
        if not x.is_floating_point():
            raise ValueError(f"{name}: expected a float image in [0, 1], got dtype {x.dtype}")
        if x.ndim != 3:
            raise ValueError(f"{name}: expected shape [H, W, C], got {tuple(x.shape)}")
    if img.shape != ref.shape:
        raise ValueError(f"img and ref differ in shape: {tuple(img.shape)} vs {tuple(ref.shape)}")


def mse(img: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Mean squared error over all pixels and channels (a 0-dim tensor)."""
    _check_pair(img, ref)
    return torch.mean((img - ref) ** 2)


def psnr(img: torch.Tensor, ref: torch.Tensor, data_range: float = 1.0) -> float:
    """PSNR = 10 log10( data_range^2 / MSE ) in dB; +inf for identical images.

    img, ref: [H, W, C] in [0, data_range].
    """
    _check_pair(img, ref)
    err = float(mse(img.double(), ref.double()))
    if err == 0.0:
        return math.inf
    return 10.0 * math.log10(data_range**2 / err)


def gaussian_window(size: int = 11, sigma: float = 1.5, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Normalised 1D Gaussian g[k] ~ exp(-(k - size//2)^2 / (2 sigma^2)), k = 0..size-1 (shape [size])."""
    if size < 1 or size % 2 == 0:
        raise ValueError(f"window size must be odd and positive, got {size}")
    k = torch.arange(size, dtype=dtype) - size // 2
    g = torch.exp(-(k**2) / (2.0 * sigma**2))
    return g / g.sum()


def ssim_map(img: torch.Tensor, ref: torch.Tensor, window_size: int = 11, sigma: float = 1.5,
             data_range: float = 1.0, padding: Literal["same", "valid"] = "same") -> torch.Tensor:
    """Per-pixel SSIM (Wang et al. 2004), shape [C, H', W'].

    SSIM = ((2 mu_x mu_y + C1)(2 sigma_xy + C2)) / ((mu_x^2 + mu_y^2 + C1)(sigma_x^2 + sigma_y^2 + C2)),
    C1 = (0.01 L)^2, C2 = (0.03 L)^2, local moments from a separable Gaussian window.
    padding "same": zero padding, H' = H (3DGS); "valid": H' = H - window_size + 1 (pytorch-msssim).
    """
    _check_pair(img, ref)
    if padding not in ("same", "valid"):
        raise ValueError(f"padding must be 'same' or 'valid', got {padding!r}")
    h, w, c = img.shape
    if padding == "valid" and min(h, w) < window_size:
        raise ValueError(f"image {h}x{w} is smaller than the {window_size}x{window_size} SSIM window")
    x = img.permute(2, 0, 1).unsqueeze(0)  # [1, C, H, W]
    y = ref.permute(2, 0, 1).unsqueeze(0).to(x.dtype)  # [1, C, H, W]
    g = gaussian_window(window_size, sigma, dtype=x.dtype).to(x.device)
    wy = g.view(1, 1, -1, 1).expand(c, 1, window_size, 1)  # vertical pass
    wx = g.view(1, 1, 1, -1).expand(c, 1, 1, window_size)  # horizontal pass
    pad = window_size // 2 if padding == "same" else 0

    def blur(t: torch.Tensor) -> torch.Tensor:
        t = F.conv2d(t, wy, padding=(pad, 0), groups=c)
        return F.conv2d(t, wx, padding=(0, pad), groups=c)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x**2
    syy = blur(y * y) - mu_y**2
    sxy = blur(x * y) - mu_x * mu_y
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2)
    return (num / den)[0]  # [C, H', W']


def ssim(img: torch.Tensor, ref: torch.Tensor, window_size: int = 11, sigma: float = 1.5,
         data_range: float = 1.0, padding: Literal["same", "valid"] = "same") -> float:
    """Mean SSIM over pixels and channels (see ``ssim_map``); 1.0 for identical images."""
    return float(ssim_map(img, ref, window_size, sigma, data_range, padding).mean())


# ----------------------------------------------------------------------------------------------
# LPIPS: a hook, no weights shipped, nothing downloaded.

LPIPS_HELP = (
    "LPIPS needs a learned network and this toolkit downloads no weights. Make a TorchScript file "
    "once, on a machine that has the `lpips` package and its weights, e.g.\n"
    "  import lpips, torch; m = lpips.LPIPS(net='vgg').eval()\n"
    "  x = torch.rand(1, 3, 64, 64) * 2 - 1; torch.jit.trace(m, (x, x)).save('lpips_vgg.pt')\n"
    "then pass that file (inputs [N, 3, H, W] in [-1, 1], output one distance per image). A "
    "torch.export archive (.pt2) works too."
)


def load_lpips(weights: str | Path | None) -> Callable[[torch.Tensor, torch.Tensor], torch.Tensor]:
    """Load a user-supplied TorchScript LPIPS network (see ``LPIPS_HELP``); no download."""
    if weights is None:
        raise ValueError("no LPIPS weights given. " + LPIPS_HELP)
    path = Path(weights)
    if not path.is_file():
        raise FileNotFoundError(f"LPIPS weights not found: {path}. " + LPIPS_HELP)
    try:
        if path.suffix == ".pt2":  # torch.export archive
            return torch.export.load(str(path)).module()
        with warnings.catch_warnings():  # torch.jit is deprecated in torch 2.13 but still loads
            warnings.simplefilter("ignore", DeprecationWarning)
            return torch.jit.load(str(path), map_location="cpu").eval()
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"{path}: not a TorchScript (.pt) or torch.export (.pt2) file ({exc}). "
                         + LPIPS_HELP) from exc


def lpips(img: torch.Tensor, ref: torch.Tensor, model: Callable[[torch.Tensor, torch.Tensor], torch.Tensor]) -> float:
    """LPIPS distance between two [H, W, 3] images in [0, 1] with a model from ``load_lpips``."""
    _check_pair(img, ref)
    to_net = lambda t: (t.permute(2, 0, 1).unsqueeze(0).float() * 2.0 - 1.0)  # [1, 3, H, W] in [-1, 1]
    with torch.no_grad():
        return float(model(to_net(img), to_net(ref)).reshape(-1)[0])


# ----------------------------------------------------------------------------------------------
# Files and averages.

def load_image(path: str | Path) -> torch.Tensor:
    """Read an 8/16-bit image file as a float32 RGB tensor [H, W, 3] in [0, 1]."""
    import cv2  # lazy: only needed for files

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"image not found: {path}")
    arr = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if arr is None:
        raise ValueError(f"{path}: could not be read as an image")
    scale = 65535.0 if arr.dtype == np.uint16 else 255.0
    if arr.ndim == 2:
        arr = np.repeat(arr[:, :, None], 3, axis=2)
    arr = cv2.cvtColor(arr[:, :, :3], cv2.COLOR_BGR2RGB)  # OpenCV reads BGR
    return torch.from_numpy(arr.astype(np.float32) / scale)


PSNR_MAX = 100.0
"""dB: an image's PSNR is counted at most this (identical images' +inf made the mean +inf and the JSON
invalid; a single 8-bit step in one pixel of 640x480 already reads 108 dB)."""


def _size(x: torch.Tensor) -> str:
    return f"{x.shape[1]}x{x.shape[0]}" + (f"x{x.shape[2]}" if x.ndim == 3 and x.shape[2] != 3 else "")


def evaluate_images(imgs: Sequence[torch.Tensor | str | Path], refs: Sequence[torch.Tensor | str | Path],
                    lpips_weights: str | Path | None = None,
                    padding: Literal["same", "valid"] = "same") -> dict:
    """Mean PSNR / SSIM (and LPIPS when weights are given) over image pairs (tensors or paths).

    Returns ``{"psnr", "ssim", "lpips" (or None), "n_images", "per_image": [...]}``; the mean PSNR is
    the mean of per-image PSNRs (as 3DGS's metrics.py), each at most ``PSNR_MAX``.
    """
    if len(imgs) != len(refs):
        raise ValueError(f"{len(imgs)} images but {len(refs)} references")
    if len(imgs) == 0:
        raise ValueError("no images to evaluate")
    model = load_lpips(lpips_weights) if lpips_weights is not None else None
    rows = []
    for img, ref in tqdm(list(zip(imgs, refs)), desc="image metrics", leave=False):
        name = str(img) if isinstance(img, (str, Path)) else f"#{len(rows)}"
        a = load_image(img) if isinstance(img, (str, Path)) else img
        b = load_image(ref) if isinstance(ref, (str, Path)) else ref
        if a.shape != b.shape:
            named = f"{ref} " if isinstance(ref, (str, Path)) else ""
            raise ValueError(f"{name} is {_size(a)} and its reference {named}{_size(b)}: an image and its "
                             "reference must have one size")
        row = {"name": name, "psnr": min(psnr(a, b), PSNR_MAX), "ssim": ssim(a, b, padding=padding)}
        row["lpips"] = lpips(a, b, model) if model is not None else None
        rows.append(row)
    mean = lambda k: float(np.mean([r[k] for r in rows]))
    return {"psnr": mean("psnr"), "ssim": mean("ssim"),
            "lpips": mean("lpips") if model is not None else None,
            "n_images": len(rows), "ssim_padding": padding, "per_image": rows}


def evaluate_renders(renders_dir: str | Path, scene_dir: str | Path, test_every: int = 8,
                     lpips_weights: str | Path | None = None) -> dict:
    """PSNR / SSIM (LPIPS with weights) of rendered held-out views against the scene's test images.

    ``renders_dir`` holds one image per test view named like its source image (``splat train``
    writes OUT/test_renders/STEM.png); the references are the scene's test views (every
    ``test_every``-th image, as in training), read at the renders' size (a downscaled training run
    renders smaller images; the scene's images are resized with area averaging, as training did).
    """
    from geocues.scene import Scene

    renders_dir = Path(renders_dir)
    if not renders_dir.is_dir():
        raise FileNotFoundError(f"no renders folder at {renders_dir}")
    if test_every < 1:
        raise ValueError(f"--test-every must be >= 1 for --renders (every n-th image is a test view), got {test_every}")
    if (renders_dir / "test_renders").is_dir():
        raise ValueError(f"{renders_dir} is a run folder: its held-out renders are {renders_dir / 'test_renders'}")
    files = {p.stem: p for p in sorted(renders_dir.iterdir()) if p.suffix.lower() in (".png", ".jpg", ".jpeg")}
    if not files:
        raise ValueError(f"{renders_dir} holds no PNG/JPEG renders")
    _warn_other_scene(renders_dir, scene_dir)
    scene = Scene.load(scene_dir, test_every=test_every, check_priors=False)
    first_path = next(iter(files.values()))
    first = load_image(first_path)
    cam0 = scene.cameras[0]
    downscale = render_downscale(cam0.width, cam0.height, first.shape[1], first.shape[0], renders_dir)
    if downscale is None:
        bigger = " (larger: the photos would be enlarged into references)" if first.shape[1] > cam0.width else ""
        raise ValueError(f"render {first_path} is {first.shape[1]}x{first.shape[0]}, not a downscale of the "
                         f"scene's {cam0.width}x{cam0.height}{bigger}")
    scene = Scene.load(scene_dir, downscale=downscale, test_every=test_every, check_priors=False)
    tests = {scene.cameras[i].stem: i for i in scene.test_indices}
    files = _reference_names(files, list(tests), renders_dir)
    missing = sorted(set(tests) - set(files))
    extra = sorted(set(files) - set(tests))
    if extra:
        raise ValueError(f"renders {extra[:5]} are not test views of {scene_dir} (test_every={test_every})")
    if missing:
        log.warning("%d of %d test views have no render (e.g. %s); the means are over the other %d, so they "
                    "compare only with figures over the same views", len(missing), len(tests), missing[:3],
                    len(tests) - len(missing))
    stems = [s for s in tests if s in files]
    refs = [torch.from_numpy(scene.load_image(tests[s])) for s in stems]
    result = evaluate_images([files[s] for s in stems], refs, lpips_weights)
    result["renders"], result["scene"], result["downscale"] = str(renders_dir), str(scene_dir), downscale
    result["n_test_views"], result["missing_views"] = len(tests), missing
    return result


def render_downscale(width: int, height: int, rw: int, rh: int, renders_dir: Path | None = None) -> float | None:
    """The ``--downscale`` that makes a ``width`` x ``height`` photo the ``rw`` x ``rh`` render, as training
    rounds each side (geocues.scene.downscaled_size), or None. Tried: the run's own (RUN/report.json beside
    RUN/test_renders), the whole factor, then each side's ratio: 321x239 at --downscale 2 is 160x120, whose
    width ratio 2.006 gives 160x119. A guess under 1 (renders larger than the photos) is none: the photos
    would be enlarged into references."""
    from geocues.scene import downscaled_size

    tries = []
    try:  # a run trained with --downscale below 1 (upsampled photos) rendered larger: its own factor
        tries.append(float(json.loads((Path(renders_dir).parent / "report.json").read_text())["config"]["downscale"]))
    except (OSError, ValueError, KeyError, TypeError):
        pass
    guesses = [d for d in (float(round(width / rw)), width / rw, height / rh) if d >= 1]  # else photos enlarged
    return next((d for d in tries + guesses if d > 0 and downscaled_size(width, height, d) == (rw, rh)), None)


def _reference_names(files: dict[str, Path], test_stems: list[str], renders_dir: Path) -> dict[str, Path]:
    """Renders named as the 3DGS reference ``render.py`` names them (``00000.png`` ... : the index in its
    test list, which is the test views in name order) keyed by the test views' stems instead; ``files``
    unchanged when they are named like the views (or are not exactly indices 0..T-1 of T test views)."""
    if set(files) <= set(test_stems) or set(files) != {f"{k:05d}" for k in range(len(test_stems))}:
        return files
    log.info("the renders in %s are named 00000..%05d as the reference render.py names them: matched to the "
             "%d test views in name order", renders_dir, len(test_stems) - 1, len(test_stems))
    return {stem: files[f"{k:05d}"] for k, stem in enumerate(sorted(test_stems))}


def _warn_other_scene(renders_dir: Path, scene_dir: str | Path) -> None:
    """One warning when the run the renders come from (RUN/test_renders, RUN/report.json) was trained
    on another scene: renders are matched to test views by name alone, and two scenes share names
    (a room's renders scored against ICL: 8.6 dB, without a word)."""
    from splat.run_paths import recorded_path

    try:
        report = json.loads((renders_dir.parent / "report.json").read_text())
        trained = recorded_path(renders_dir.parent, report, "scene")  # the run may have moved with its scene
    except (OSError, ValueError, AttributeError, TypeError):
        return
    if trained is not None and trained.resolve() != Path(scene_dir).resolve():
        log.warning("the renders in %s come from a run trained on %s, not %s: is SCENE the run's scene?",
                    renders_dir, trained, scene_dir)
