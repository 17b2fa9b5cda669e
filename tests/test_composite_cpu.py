"""The C++ compositing backend (splat.composite_cpu) against the torch reference: values, gradients,
float64 gradcheck, determinism across thread counts, edge cases, and the build's error path."""

from __future__ import annotations

import importlib
import shutil

import pytest
import torch
from torch.autograd import gradcheck

from splat.composite import composite
from splat.composite_torch import composite_torch

pytestmark = pytest.mark.skipif(shutil.which("c++") is None and shutil.which("g++") is None,
                                reason="no C++ compiler: the cpu backend cannot be built here")


@pytest.fixture(scope="session")
def cpu():
    """The built extension module (compiled once into the project cache, ~30 s the first time)."""
    return importlib.import_module("splat.composite_cpu")


def random_scene(n, width, height, nch=9, nmed=3, dtype=torch.float32, seed=0, spread=1.5,
                 opacity=(0.05, 0.95), cluster=False):
    """Random 2D Gaussians over and beyond the image (several tiles); leaves require grad."""
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
    depths[3] = depths[4]  # a tie: broken by index
    bg = torch.rand(nch, generator=gen, dtype=f64)
    medf = torch.rand(n, nmed, generator=gen, dtype=f64)
    leaves = [t.to(dtype).requires_grad_() for t in (means, conics, opac, feats, bg, medf)]
    return leaves, depths.to(dtype), radii


def run(fn, leaves, depths, radii, width, height, seed=1, **kw):
    """Composite with ``fn``, then the gradients of a random weighting of all outputs."""
    means, conics, opac, feats, bg, medf = leaves
    out = fn(means, conics, opac, feats, depths, radii, width, height, background=bg, median_features=medf, **kw)
    gen = torch.Generator().manual_seed(seed)
    w_feat = torch.rand(out.features.shape, generator=gen, dtype=torch.float64).to(feats.dtype)
    w_med = torch.rand(out.median.shape, generator=gen, dtype=torch.float64).to(feats.dtype)
    loss = (out.features * w_feat).sum() + (out.median * w_med).sum() + (out.alpha ** 2).sum()
    return out, torch.autograd.grad(loss, leaves)


NAMES = ("means2d", "conics", "opacities", "features", "background", "median_features")


@pytest.mark.parametrize("nch,seed,cluster", [(9, 0, False), (4, 1, False), (9, 2, True)])
def test_float32_matches_torch_backend(cpu, nch, seed, cluster):
    """Same values and gradients as the torch reference within float32 tolerance (C = 9 is the
    specialised render() path, C = 4 the generic one); the torch backend's cap is not reached."""
    width, height = 70, 45  # 5 x 3 tiles, partial tiles at the right and bottom
    n = 50 if cluster else 600
    leaves, depths, radii = random_scene(n, width, height, nch=nch, seed=seed, cluster=cluster)
    ref, g_ref = run(composite_torch, leaves, depths, radii, width, height)
    out, g_out = run(cpu.composite, leaves, depths, radii, width, height)
    assert 5 < int(ref.n_contrib.max()) < 64
    assert torch.equal(out.n_contrib, ref.n_contrib)
    torch.testing.assert_close(out.features, ref.features, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(out.alpha, ref.alpha, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(out.median, ref.median, rtol=0, atol=0)
    for name, a, b in zip(NAMES, g_out, g_ref):
        scale = float(b.abs().max())
        assert scale > 0, name
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5 * scale, msg=lambda m: f"{name}: {m}")


@pytest.mark.parametrize("seed,opacity,cluster", [(3, (0.05, 0.95), False), (4, (0.5, 0.99), True)])
def test_float64_equals_torch_backend(cpu, seed, opacity, cluster):
    """In float64 both backends follow the same rule to rounding, saturated pixels included."""
    width, height = 37, 20
    leaves, depths, radii = random_scene(300, width, height, nch=5, dtype=torch.float64, seed=seed,
                                         opacity=opacity, cluster=cluster)
    ref, g_ref = run(composite_torch, leaves, depths, radii, width, height, max_per_pixel=10_000)
    out, g_out = run(cpu.composite, leaves, depths, radii, width, height)
    if cluster:
        assert float(ref.alpha.max()) > 0.999  # saturated pixels: the early-stop rule is exercised
    assert torch.equal(out.n_contrib, ref.n_contrib)
    torch.testing.assert_close(out.features, ref.features, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(out.median, ref.median, rtol=0, atol=0)
    for name, a, b in zip(NAMES, g_out, g_ref):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11, msg=lambda m: f"{name}: {m}")


def test_gradcheck_float64(cpu):
    width, height = 20, 18  # two tiles wide, two high
    leaves, depths, radii = random_scene(30, width, height, nch=4, nmed=2, dtype=torch.float64, seed=5)

    gen = torch.Generator().manual_seed(9)
    w_feat, w_alpha, w_med = (torch.rand(shape, generator=gen, dtype=torch.float64)
                              for shape in ((height, width, 4), (height, width), (height, width, 2)))

    def fn(means, conics, opac, feats, bg, medf):
        # random projections of the outputs: 3 backward passes instead of one per output pixel
        out = cpu.composite(means, conics, opac, feats, depths, radii, width, height,
                            background=bg, median_features=medf)
        return (out.features * w_feat).sum(), (out.alpha * w_alpha).sum(), (out.median * w_med).sum()

    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # ~700 tiny calls: thread wake-ups would dominate
    try:
        assert gradcheck(fn, leaves, eps=1e-6, atol=1e-6, rtol=1e-4)
    finally:
        torch.set_num_threads(threads)


@pytest.mark.parametrize("n", [3000, 150_000])  # 150k: the binning passes run threaded too
def test_deterministic_across_thread_counts(cpu, n):
    """Per-(tile, Gaussian) gradients summed in a fixed order: bitwise equal for 1 and 2 threads."""
    width, height = 100, 70
    leaves, depths, radii = random_scene(n, width, height, seed=6, spread=1.5 if n < 10_000 else 0.3)
    threads = torch.get_num_threads()
    results = []
    try:
        for t in (1, 2, 1):
            torch.set_num_threads(t)
            out, grads = run(cpu.composite, leaves, depths, radii, width, height)
            results.append([out.features, out.alpha, out.median, *grads])
    finally:
        torch.set_num_threads(threads)
    for other in results[1:]:
        assert all(torch.equal(a, b) for a, b in zip(results[0], other))


def test_edge_cases_are_finite(cpu):
    """Empty scene, all culled, 1x1 image, a huge radius far off-image, 3000 Gaussians on a pixel."""
    bg = torch.tensor([0.25, 0.5, 0.75])
    empty = [torch.zeros(0, 2), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0, 3)]
    out = cpu.composite(*empty, torch.zeros(0), torch.zeros(0, dtype=torch.int32), 17, 33, background=bg)
    torch.testing.assert_close(out.features, bg.expand(33, 17, 3))
    assert float(out.alpha.abs().max()) == 0.0 and out.median is None

    # 3000 Gaussians on one pixel, plus one with a huge radius centred far outside the image
    n = 3001
    leaves, depths, radii = random_scene(n, 8, 8, nch=3, nmed=1, seed=7, cluster=True)
    with torch.no_grad():
        leaves[0][0] = torch.tensor([-1e6, 4.0])
        leaves[1][0] = torch.tensor([1e-12, 0.0, 1e-12])
        radii[0] = 100_000_000
    for w, h in ((8, 8), (1, 1)):
        out, grads = run(cpu.composite, leaves, depths, radii, w, h)
        assert torch.isfinite(out.features).all() and torch.isfinite(out.median).all()
        assert float(out.alpha.min()) >= 0.0 and float(out.alpha.max()) <= 1.0
        assert all(torch.isfinite(g).all() for g in grads)
    assert int(out.n_contrib.max()) > 0


def test_dispatch_and_bad_inputs(cpu):
    leaves, depths, radii = random_scene(50, 20, 20, nch=3, seed=8)
    means, conics, opac, feats, bg, medf = leaves
    a = composite(means, conics, opac, feats, depths, radii, 20, 20, background=bg, backend="cpu")
    b = cpu.composite(means, conics, opac, feats, depths, radii, 20, 20, background=bg)
    assert torch.equal(a.features, b.features) and a.median is None
    with pytest.raises(ValueError, match="dtype"):
        cpu.composite(means.double(), conics, opac, feats, depths, radii, 20, 20)
    with pytest.raises(ValueError, match="conics"):
        cpu.composite(means, conics[:, :2], opac, feats, depths, radii, 20, 20)


def test_build_failure_raises_import_error_with_compiler_message(cpu, tmp_path, monkeypatch):
    """A source that does not compile gives ImportError carrying the compiler's message."""
    bad = tmp_path / "bad.cpp"
    bad.write_text("#error deliberate_build_failure_marker\n")
    from splat import cpu_ext

    monkeypatch.setenv("INDOORGS_CACHE", str(tmp_path / "cache"))
    monkeypatch.setattr(cpu_ext, "SOURCES", (bad,))
    assert cpu_ext.build_dir().parent == tmp_path / "cache" / "torch_extensions" / cpu_ext.ext_name()
    with pytest.raises(ImportError, match="deliberate_build_failure_marker"):
        cpu_ext._build()


def test_render_matches_torch_backend_on_room_surfaces(cpu):
    """render() with either backend on the benchmark room: same maps and parameter gradients."""
    from splat.bench import bench_camera, surface_gaussians
    from splat.rasterize import render

    params = surface_gaussians(3000, sh_degree=1, seed=2)
    camera = bench_camera(64, 48)
    keys = ("rgb", "depth", "median_depth", "normal", "alpha")
    outs, grads = [], []
    for backend in ("torch", "cpu"):
        leaves = {k: v.clone().requires_grad_() for k, v in params.items()}
        out = render(leaves, camera, backend=backend, max_per_pixel=256)
        loss = sum((out[k] * (i + 1)).sum() for i, k in enumerate(keys))
        grads.append(torch.autograd.grad(loss, list(leaves.values())))
        outs.append(out)
    assert 3 < int(outs[0]["n_contrib"].max()) < 256 and float(outs[0]["alpha"].mean()) > 0.5
    for k in keys:
        torch.testing.assert_close(outs[1][k], outs[0][k], rtol=1e-4, atol=1e-4, msg=lambda m: f"{k}: {m}")
    for name, a, b in zip(params, grads[1], grads[0]):
        scale = float(b.abs().max())
        assert scale > 0, name
        torch.testing.assert_close(a, b, rtol=1e-3, atol=1e-4 * scale, msg=lambda m: f"{name}: {m}")


@pytest.mark.parametrize("nch,dtype", [(3, torch.float32), (9, torch.float32), (4, torch.float32),
                                       (3, torch.float64)])
def test_frozen_geometry_backward_from_the_stored_weights(cpu, nch, dtype):
    """With means2d, conics and opacities not requiring grad (a frozen geometry) the forward keeps its
    blend weights and the backward sums them against d out: the same image as the full pass (bit for
    bit), the features' and background's gradients of the full backward and of the torch reference
    to float rounding (C = 3: render(maps=False), 9: render(), 4: generic), none to the geometry."""
    width, height = 70, 45  # partial tiles at the right and bottom
    leaves, depths, radii = random_scene(600, width, height, nch=nch, nmed=0, seed=5, dtype=dtype)
    means, conics, opac, feats, bg, _ = leaves
    gen = torch.Generator().manual_seed(3)
    weight = torch.rand(height, width, nch, generator=gen, dtype=torch.float64).to(dtype)
    outs, grads = {}, {}
    for name, fn, geometry in (("full", cpu.composite, True), ("stored", cpu.composite, False),
                               ("torch", composite_torch, False)):
        geo = [t if geometry else t.detach() for t in (means, conics, opac)]
        outs[name] = fn(*geo, feats, depths, radii, width, height, background=bg)
        grads[name] = torch.autograd.grad((outs[name].features * weight).sum(), [feats, bg])
    assert torch.equal(outs["stored"].features, outs["full"].features)
    assert float(grads["full"][0].abs().max()) > 0 and int(outs["full"].n_contrib.max()) > 5
    tol = 1e-12 if dtype == torch.float64 else 1e-5
    for ref in ("full", "torch"):
        for a, b in zip(grads["stored"], grads[ref]):
            torch.testing.assert_close(a, b, rtol=tol, atol=tol * float(b.abs().max()), msg=lambda m: f"{ref}: {m}")


def test_render_colour_only_equals_the_full_render(cpu):
    """render(maps=False): the colour and alpha of render(), bit for bit, with either backend; its
    colour gradient with the geometry detached equals the full render's colour gradient."""
    from splat.bench import bench_camera, surface_gaussians
    from splat.rasterize import render

    params = surface_gaussians(3000, sh_degree=1, seed=2)
    camera = bench_camera(64, 48)
    background = torch.tensor([0.2, 0.5, 0.9])
    for backend in ("torch", "cpu"):
        runs = []
        for maps in (True, False):
            leaves = {k: v.clone().requires_grad_(maps or k in ("sh0", "shN")) for k, v in params.items()}
            out = render(leaves, camera, backend=backend, background=background, maps=maps)
            assert ("depth" in out) == maps
            grads = torch.autograd.grad((out["rgb"] ** 2).sum(), [leaves["sh0"], leaves["shN"]])
            runs.append((out["rgb"], out["alpha"], grads))
        (rgb, alpha, g), (rgb2, alpha2, g2) = runs
        assert torch.equal(rgb, rgb2) and torch.equal(alpha, alpha2), backend
        assert float(g[0].abs().max()) > 0
        for a, b in zip(g, g2):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7, msg=lambda m: f"{backend}: {m}")


def test_stored_weights_replaced_by_a_later_forward_fall_back_to_the_full_backward(cpu):
    """The kept blend weights live in reused buffers: two frozen-geometry forwards before the first
    one's backward (two views, one loss) still give each its own gradient, the first by the full pass."""
    width, height = 70, 45
    leaves, depths, radii = random_scene(600, width, height, nch=3, nmed=0, seed=6)
    means, conics, opac, feats, bg, _ = leaves
    geo = [t.detach() for t in (means, conics, opac)]
    first = cpu.composite(*geo, feats, depths, radii, width, height, background=bg)
    second = cpu.composite(geo[0] + 3.0, *geo[1:], feats, depths, radii, width, height, background=bg)
    both = torch.autograd.grad(first.features.sum() + 2 * second.features.sum(), feats)[0]
    alone = [torch.autograd.grad(cpu.composite(g0, *geo[1:], feats, depths, radii, width, height,
                                               background=bg).features.sum(), feats)[0]
             for g0 in (geo[0], geo[0] + 3.0)]
    torch.testing.assert_close(both, alone[0] + 2 * alone[1], rtol=1e-5, atol=1e-5)
