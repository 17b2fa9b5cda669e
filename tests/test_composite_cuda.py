"""The CUDA compositing backend (splat.composite_cuda) against the torch reference: values and
gradients on random scenes (several shared-memory batches per tile, saturated pixels), on the
compositing inputs of the benchmark room and of the hard cases of tests/test_render_hard_cases.py,
render() with both backends on the GPU, dispatch, bad inputs and the build's error path.

CI has no GPU: every test here but the CPU-only dispatch test is skipped without CUDA; they run on a
GPU machine (bench/gpu_check.sh). The reference is the torch backend run on the CPU in float32 on
the same inputs, with the tolerances of tests/test_composite_cpu.py: both it and the kernel compute
each pixel's transmittance as a sequential product and round the alpha arithmetic per operation,
so they take the same skip / stop / median decisions (n_contrib and median compared exactly). On
the GPU the torch backend forms T with a parallel cumprod whose rounding differs in the last bits,
so render() against it on the GPU allows what tests/test_cuda.py allows (n_contrib within 1).
"""

from __future__ import annotations

import importlib
import math
import sys

import pytest
import torch

from splat.composite import composite, resolve_backend
from splat.composite_torch import composite_torch

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device (CI has none)")

NAMES = ("means2d", "conics", "opacities", "features", "background", "median_features")


@pytest.fixture(scope="session")
def cuda():
    """The built extension module (compiled once into the project cache, about a minute the first time)."""
    return importlib.import_module("splat.composite_cuda")


def random_scene(n, width, height, nch=9, nmed=3, seed=0, spread=1.5, opacity=(0.05, 0.95), cluster=False):
    """Random 2D Gaussians over and beyond the image (as tests/test_composite_cpu.py), float32 on the
    GPU; the six differentiable inputs are leaves that require grad."""
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    if cluster:
        means = torch.tensor([width / 2, height / 2], dtype=f64) + 2 * torch.randn(n, 2, generator=gen, dtype=f64)
    else:
        means = torch.rand(n, 2, generator=gen, dtype=f64) * torch.tensor([width + 10.0, height + 10.0]) - 5.0
    lmat = torch.randn(n, 2, 2, generator=gen, dtype=f64) * spread
    cov = lmat @ lmat.transpose(1, 2) + 0.3 * torch.eye(2, dtype=f64)
    inv = torch.linalg.inv(cov)
    conics = torch.stack([inv[:, 0, 0], inv[:, 0, 1], inv[:, 1, 1]], 1)
    radii = torch.ceil(3 * torch.sqrt(torch.linalg.eigvalsh(cov)[:, 1])).to(torch.int32)
    radii[::9] = 0  # some culled
    opac = opacity[0] + torch.rand(n, generator=gen, dtype=f64) * (opacity[1] - opacity[0])
    feats = torch.rand(n, nch, generator=gen, dtype=f64) * 2 - 0.5
    depths = torch.rand(n, generator=gen, dtype=f64) * 4 + 1
    if n > 4:
        depths[3] = depths[4]  # a tie: broken by index
    bg = torch.rand(nch, generator=gen, dtype=f64)
    medf = torch.rand(n, nmed, generator=gen, dtype=f64)
    leaves = [t.to("cuda", torch.float32).requires_grad_() for t in (means, conics, opac, feats, bg, medf)]
    return leaves, depths.to("cuda", torch.float32), radii.cuda()


def run(fn, leaves, depths, radii, width, height, seed=1, **kw):
    """Composite with ``fn``, then the gradients of a random weighting of all outputs."""
    means, conics, opac, feats, bg, medf = leaves
    out = fn(means, conics, opac, feats, depths, radii, width, height, background=bg, median_features=medf, **kw)
    gen = torch.Generator().manual_seed(seed)
    w_feat = torch.rand(out.features.shape, generator=gen).to(feats.device)
    w_med = torch.rand(out.median.shape, generator=gen).to(feats.device)
    loss = (out.features * w_feat).sum() + (out.median * w_med).sum() + (out.alpha ** 2).sum()
    if not loss.requires_grad:  # nothing visible (empty scene)
        return out, [torch.zeros_like(t) for t in leaves]
    return out, [torch.zeros_like(t) if g is None else g
                 for g, t in zip(torch.autograd.grad(loss, leaves, allow_unused=True), leaves)]


def reference(leaves, depths, radii, width, height, seed=1):
    """The torch backend on the CPU (float32, no cap reached) on copies of the inputs; results on the GPU."""
    cpu_leaves = [t.detach().cpu().requires_grad_() for t in leaves]
    out, grads = run(composite_torch, cpu_leaves, depths.cpu(), radii.cpu(), width, height, seed,
                     max_per_pixel=100_000)
    return type(out)(*(None if t is None else t.cuda() for t in out)), [g.cuda() for g in grads]


def assert_matches_torch(out, grads, ref, g_ref, need_grads=True):
    """The tolerances of tests/test_composite_cpu.py (float32); ``need_grads``: every gradient non-zero."""
    assert torch.equal(out.n_contrib, ref.n_contrib)
    torch.testing.assert_close(out.features, ref.features, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out.alpha, ref.alpha, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out.median, ref.median, rtol=0, atol=0)
    assert float(out.alpha.min()) >= 0.0 and float(out.alpha.max()) <= 1.0
    for name, a, b in zip(NAMES, grads, g_ref):
        assert torch.isfinite(a).all(), name
        scale = float(b.abs().max()) if b.numel() else 0.0
        assert scale > 0 or not need_grads, name
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * scale, msg=lambda m: f"{name}: {m}")


def composite_inputs(params: dict, camera, **kw):
    """The six differentiable compositing inputs (as fresh leaves) and depths, radii, width, height
    that render() passes to composite() for these Gaussians (projection in torch on their device)."""
    import splat.rasterize as rasterize

    captured = {}
    real = rasterize.composite

    def spy(*args, **kwargs):
        captured["args"], captured["kwargs"] = args, kwargs
        return real(*args, **kwargs)

    rasterize.composite = spy
    try:
        with torch.no_grad():
            rasterize.render(params, camera, backend="torch", **kw)
    finally:
        rasterize.composite = real
    args, kwargs = captured["args"], captured["kwargs"]
    leaves = [t.detach().clone().requires_grad_()
              for t in (*args[:4], kwargs["background"], kwargs["median_features"])]
    return leaves, *args[4:]


@needs_cuda
@pytest.mark.parametrize("nch,seed,cluster", [(9, 0, False), (4, 1, False), (9, 2, True)])
def test_float32_matches_torch_backend(cuda, nch, seed, cluster):
    """C = 9 is the specialised render() kernel, C = 4 the generic one; 5 x 3 tiles with partial tiles
    at the right and bottom; the torch backend's cap is not reached."""
    width, height = 70, 45
    n = 50 if cluster else 600
    leaves, depths, radii = random_scene(n, width, height, nch=nch, seed=seed, cluster=cluster)
    ref, g_ref = reference(leaves, depths, radii, width, height)
    out, g_out = run(cuda.composite, leaves, depths, radii, width, height)
    assert 5 < int(ref.n_contrib.max()) < 64
    assert_matches_torch(out, g_out, ref, g_ref)


@needs_cuda
@pytest.mark.parametrize("nch", [9, 5])
def test_long_tile_lists_and_saturation(cuda, nch):
    """Thousands of faint Gaussians per tile: lists span many 256-Gaussian shared-memory batches
    and pixels blend hundreds each; opaque clusters saturate (the 1e-4 stop and block exit)."""
    width, height = 40, 35
    leaves, depths, radii = random_scene(10_000, width, height, nch=nch, seed=10, spread=3.0,
                                         opacity=(0.004, 0.03))
    ref, g_ref = reference(leaves, depths, radii, width, height)
    out, g_out = run(cuda.composite, leaves, depths, radii, width, height)
    assert int(ref.n_contrib.max()) > 300  # 380 (C = 9)
    assert_matches_torch(out, g_out, ref, g_ref)

    leaves, depths, radii = random_scene(600, 20, 20, nch=nch, seed=11, opacity=(0.5, 0.99), cluster=True)
    ref, g_ref = reference(leaves, depths, radii, 20, 20)
    out, g_out = run(cuda.composite, leaves, depths, radii, 20, 20)
    assert float(ref.alpha.max()) > 0.999  # saturated: the early-stop rule is exercised
    assert_matches_torch(out, g_out, ref, g_ref)


@needs_cuda
def test_edge_cases_are_finite(cuda):
    """Empty scene, all culled, 1x1 image, a huge radius far off-image, 3000 Gaussians on a pixel."""
    bg = torch.tensor([0.25, 0.5, 0.75], device="cuda")
    empty = [torch.zeros(0, 2, device="cuda"), torch.zeros(0, 3, device="cuda"), torch.zeros(0, device="cuda"),
             torch.zeros(0, 3, device="cuda")]
    out = cuda.composite(*empty, torch.zeros(0, device="cuda"), torch.zeros(0, dtype=torch.int32, device="cuda"),
                         17, 33, background=bg)
    torch.testing.assert_close(out.features, bg.expand(33, 17, 3))
    assert float(out.alpha.abs().max()) == 0.0 and out.median is None and int(out.n_contrib.max()) == 0

    leaves, depths, radii = random_scene(50, 20, 20, nch=3, seed=12)
    radii.zero_()  # all culled
    out, grads = run(cuda.composite, leaves, depths, radii, 20, 20)
    torch.testing.assert_close(out.features, leaves[4].detach().expand(20, 20, 3))
    assert all(float(g.abs().max()) == 0.0 for g in grads[:4])

    n = 3001
    leaves, depths, radii = random_scene(n, 8, 8, nch=3, nmed=1, seed=7, cluster=True)
    with torch.no_grad():
        leaves[0][0] = torch.tensor([-1e6, 4.0])
        leaves[1][0] = torch.tensor([1e-12, 0.0, 1e-12])
        radii[0] = 100_000_000
    for w, h in ((8, 8), (1, 1)):
        ref, g_ref = reference(leaves, depths, radii, w, h)
        out, grads = run(cuda.composite, leaves, depths, radii, w, h)
        assert torch.isfinite(out.features).all() and torch.isfinite(out.median).all()
        assert all(torch.isfinite(g).all() for g in grads)
        assert_matches_torch(out, grads, ref, g_ref)
    assert int(out.n_contrib.max()) > 0


KEYS = ("rgb", "depth", "median_depth", "normal", "alpha")


def render_both(params: dict, camera, **kw):
    """render() with backend "torch" and "cuda" on the GPU, and "torch" in float64: (outputs,
    gradients of every parameter) of each, for a loss on every map but the median depth (whose
    gradient is exact but goes to whichever Gaussian crosses T = 0.5, which the two can choose
    differently where T rounds to 0.5)."""
    from splat.rasterize import render

    results = []
    for backend, dtype in (("torch", torch.float32), ("cuda", torch.float32), ("torch", torch.float64)):
        leaves = {k: v.detach().to("cuda", dtype).clone().requires_grad_() for k, v in params.items()}
        opts = {k: v.to(dtype) if isinstance(v, torch.Tensor) else v for k, v in kw.items()}
        out = render(leaves, camera, backend=backend, max_per_pixel=100_000, **opts)
        for k in (*KEYS, "means2d"):
            assert torch.isfinite(out[k]).all(), f"{backend}: non-finite {k}"
        assert float(out["alpha"].min()) >= 0.0 and float(out["alpha"].max()) <= 1.0
        loss = sum((out[k] * (i + 1)).sum() for i, k in enumerate(KEYS) if k != "median_depth")
        grads = [torch.zeros_like(v) for v in leaves.values()]
        if loss.requires_grad:
            grads = [torch.zeros_like(v) if g is None else g
                     for g, v in zip(torch.autograd.grad(loss, list(leaves.values()), allow_unused=True),
                                     leaves.values())]
        assert all(torch.isfinite(g).all() for g in grads), backend
        results.append((out, grads))
    return results


def assert_render_close(results, names):
    """Maps within 1e-4, n_contrib within 1 and the median depth within 1e-4 on all but 0.1% of the
    pixels (the GPU torch backend's cumprod rounds T differently, so the two can pick different
    Gaussians where T rounds to 0.5; not equal bit for bit: the "cuda" render projects with the
    CUDA kernels, whose depth planes differ from torch's by float32 rounding), gradients within
    1e-3 / 1e-4 of scale; or, where float32 rounding decides (depth planes of Gaussians 1e7 m away
    blend channels of 1e7 whose contributions cancel; discs seen exactly edge-on, whose facing side
    and plane slope's sign float32 rounding picks), maps, median depth and gradients no further from
    the float64 render's than twice the torch backend's."""
    (ref, g_ref), (out, g_out), (out_64, g_64) = results
    torch.testing.assert_close(out["n_contrib"], ref["n_contrib"], rtol=0, atol=1)
    med_close = torch.isclose(out["median_depth"], ref["median_depth"], rtol=1e-4, atol=1e-4)
    if float((~med_close).float().mean()) > 1e-3:  # discs seen exactly edge-on: float32 rounding picks
        # the side their plane faces (its slope's sign), as the maps below
        err_cuda = float((out["median_depth"].double() - out_64["median_depth"]).abs().max())
        err_torch = float((ref["median_depth"].double() - out_64["median_depth"]).abs().max())
        assert err_cuda <= 2 * err_torch + 1e-4, ("median_depth", err_cuda, err_torch)
    for k in KEYS:
        if k == "median_depth":
            continue
        if not torch.allclose(out[k], ref[k], rtol=1e-4, atol=1e-4):  # as the gradients below
            err_cuda = float((out[k].double() - out_64[k]).abs().max())
            err_torch = float((ref[k].double() - out_64[k]).abs().max())
            assert err_cuda <= 2 * err_torch + 1e-4, (k, err_cuda, err_torch)
    for name, a, b, c in zip(names, g_out, g_ref, g_64):
        scale = float(b.abs().max()) if b.numel() else 0.0
        if not torch.allclose(a, b, rtol=1e-3, atol=1e-4 * scale):
            err_cuda, err_torch = float((a - c).abs().max()), float((b - c).abs().max())
            assert err_cuda <= 2 * err_torch + 1e-4 * scale, (name, err_cuda, err_torch, scale)


@needs_cuda
def test_room_surfaces_match_torch_backend(cuda):
    """The benchmark room (20k flat Gaussians, 128x96): the compositing inputs render() makes, exactly
    as the torch reference (C = 9, M = 3); then render() with either backend on the GPU."""
    from splat.bench import bench_camera, surface_gaussians

    params = {k: v.cuda() for k, v in surface_gaussians(20_000, sh_degree=1, seed=2).items()}
    camera = bench_camera(128, 96).to("cuda")
    leaves, depths, radii, width, height = composite_inputs(params, camera)
    ref, g_ref = reference(leaves, depths, radii, width, height)
    out, g_out = run(cuda.composite, leaves, depths, radii, width, height)
    assert 20 < int(ref.n_contrib.max()) and float(ref.alpha.mean()) > 0.5
    assert_matches_torch(out, g_out, ref, g_ref)
    assert_render_close(render_both(params, camera), list(params))


def _hard_cases() -> dict:
    """The troublesome inputs of tests/test_render_hard_cases.py, by name."""
    from test_render_hard_cases import make_params

    cases = {}
    p = make_params(40, seed=1)
    p["means"][:, 2] = torch.linspace(-2.0, 0.3, 40)  # behind, at and past the near plane
    p["means"][:, :2] *= 0.2
    p["scales"][:20] = math.log(0.5)
    cases["near_plane"] = p
    for name, log_scale in (("scale_1e-7", math.log(1e-7)), ("scale_1e3", math.log(1e3))):
        p = make_params(30, seed=2)
        p["scales"][:] = log_scale
        p["scales"][::3, 0] = math.log(0.05)
        cases[name] = p
    p = make_params(20, seed=3)
    p["quats"][:10] = 0.0
    cases["zero_quats"] = p
    p = make_params(30, seed=4)
    p["opacities"][:15], p["opacities"][15:] = 40.0, -40.0
    cases["logits_40"] = p
    p = make_params(60, seed=5)
    p["scales"][:30] = torch.log(torch.tensor([0.5, 1e-4, 1e-4]))  # needles
    p["scales"][30:] = torch.log(torch.tensor([0.4, 0.4, 1e-6]))  # discs, some edge-on
    p["quats"][30:40] = torch.tensor([math.cos(math.pi / 4), math.sin(math.pi / 4), 0.0, 0.0])
    p["means"][30:40, 1] = 0.0
    cases["needles_discs"] = p
    p = make_params(20, seed=6)
    p["means"][:5, 0] = 1e4
    p["means"][5:10, 1] = -1e5
    p["means"][10:15, 2] = 1e7
    p["means"][15:, 0] = 0.5 * p["means"][15:, 2]  # just outside the frustum
    cases["far_outside"] = p
    p = make_params(3000, seed=7, spread=1e-4, log_scale=math.log(0.01))
    p["opacities"][:] = -1.0
    cases["thousands_on_one_pixel"] = p
    cases["empty"] = make_params(0)
    p = make_params(5)
    p["means"][:, 2] = -1.0
    cases["all_behind"] = p
    return cases


HARD_CASES = ["near_plane", "scale_1e-7", "scale_1e3", "zero_quats", "logits_40", "needles_discs",
              "far_outside", "thousands_on_one_pixel", "empty", "all_behind"]


@needs_cuda
@pytest.mark.parametrize("case", HARD_CASES)
def test_hard_cases_match_torch_backend(cuda, case):
    """The hard cases: their compositing inputs exactly as the torch reference (finite, alpha in
    [0, 1], same n_contrib and median), and render() with either backend on the GPU."""
    from test_render_hard_cases import make_camera

    params = {k: v.cuda() for k, v in _hard_cases()[case].items()}
    camera = make_camera().to("cuda")
    bg = torch.tensor([0.2, 0.3, 0.4], device="cuda")
    leaves, depths, radii, width, height = composite_inputs(params, camera, background=bg)
    ref, g_ref = reference(leaves, depths, radii, width, height)
    out, g_out = run(cuda.composite, leaves, depths, radii, width, height)
    assert_matches_torch(out, g_out, ref, g_ref, need_grads=False)
    if case == "thousands_on_one_pixel":
        assert float(out.alpha[height // 2, width // 2]) > 0.99 and int(out.n_contrib.max()) >= 20
    if case == "empty":
        assert float(out.alpha.abs().max()) == 0.0
    assert_render_close(render_both(params, camera, background=bg), list(params))


@needs_cuda
def test_dispatch_and_bad_inputs(cuda):
    """"auto" and "cuda" pick the kernels for float32 CUDA tensors; float64 goes to torch; bad inputs raise."""
    dev = torch.device("cuda")
    assert resolve_backend("auto", dev, torch.float32) == "cuda"
    assert resolve_backend("cuda", dev) == "cuda"
    assert resolve_backend("auto", dev, torch.float64) == "torch"
    assert resolve_backend("cuda", torch.device("cpu")) == "torch"
    leaves, depths, radii = random_scene(50, 20, 20, nch=3, seed=8)
    means, conics, opac, feats, bg, medf = leaves
    a = composite(means, conics, opac, feats, depths, radii, 20, 20, background=bg, backend="auto")
    b = cuda.composite(means, conics, opac, feats, depths, radii, 20, 20, background=bg)
    assert torch.equal(a.features, b.features) and a.median is None
    d = [t.detach().double() for t in (means, conics, opac, feats, bg)]
    c64 = composite(*d[:4], depths.double(), radii, 20, 20, background=d[4], backend="cuda")
    r64 = composite_torch(*d[:4], depths.double(), radii, 20, 20, background=d[4])
    torch.testing.assert_close(c64.features, r64.features, rtol=1e-12, atol=1e-12)  # fell back to torch
    with pytest.raises(ValueError, match="float32"):
        cuda.composite(means.double(), conics, opac, feats.double(), depths, radii, 20, 20)
    with pytest.raises(ValueError, match="dtype"):
        cuda.composite(means.double(), conics, opac, feats, depths, radii, 20, 20)
    with pytest.raises(ValueError, match="CUDA tensor"):
        cuda.composite(means.cpu(), conics, opac, feats, depths, radii, 20, 20)
    with pytest.raises(ValueError, match="conics"):
        cuda.composite(means, conics[:, :2], opac, feats, depths, radii, 20, 20)


@needs_cuda
def test_build_failure_raises_import_error_with_compiler_message(cuda, tmp_path, monkeypatch):
    """A source that does not compile gives ImportError carrying the compiler's message."""
    bad = tmp_path / "bad.cu"
    bad.write_text("#error deliberate_build_failure_marker\n")
    from splat import cuda_ext

    monkeypatch.setenv("INDOORGS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(cuda_ext, "SOURCES", (bad,))
    assert cuda_ext.build_dir().parent == tmp_path / "cache" / "torch_extensions" / cuda_ext.EXT_NAME
    with pytest.raises(ImportError, match="deliberate_build_failure_marker"):
        cuda_ext._build()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the CPU-only path")
def test_cpu_only_machine_never_builds_cuda_backend():
    """Without CUDA, "cuda" falls back to torch and the CUDA extension is never imported."""
    from splat.composite import available_backends, cuda_backend_available

    assert not cuda_backend_available() and "cuda" not in available_backends()
    assert resolve_backend("cuda", torch.device("cpu")) == "torch"
    assert "splat.cuda_ext" not in sys.modules and "splat.composite_cuda" not in sys.modules
