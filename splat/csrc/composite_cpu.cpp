// Tile-based front-to-back alpha compositing of projected 2D Gaussians on the CPU.
//
// Forward and analytic backward of the per-pixel rule in splat/composite.py (3DGS forward.cu /
// backward.cu semantics): 16x16 tiles, Gaussians binned to the tiles their pixel radius box
// touches, one global stable depth sort (radix sort on the float bits) so every tile's list is
// already front to back, early termination per pixel, backward back to front recovering T by
// division. OpenMP over tiles. Gradients are written per (tile, Gaussian) entry and then summed
// per Gaussian in a fixed order, so results do not depend on the thread count or schedule.

#include "composite_cpu.h"

#include <ATen/Parallel.h>

namespace {

using namespace composite_cpu;

// Forward outputs and the state the backward needs.
struct ForwardOut {
  torch::Tensor out, alpha, median, n_contrib, final_T, last, median_idx;
};

template <typename scalar_t, int NC>  // NC > 0: channel count known at compile time
void forward_impl(const Splats<scalar_t>& in, const scalar_t* medf, int64_t M, const Bins& bins,
                  ForwardOut& o, int nthreads) {
  const int64_t C = NC > 0 ? NC : in.C, W = in.W, H = in.H, n_tiles = bins.tiles_x * bins.tiles_y;
  constexpr int64_t kPad = NC > 0 ? (NC + 3) / 4 * 4 : 1;  // channels padded to vector width
  const int64_t CS = NC > 0 ? kPad : C;                      // stride of per-pixel channels
  constexpr int64_t kP = NC > 0 ? kPad : 0;                  // compile-time channel loop length
  const int32_t* offs = bins.tile_offsets.data_ptr<int32_t>();
  const int32_t* slot_rank = bins.slot_rank.data_ptr<int32_t>();
  std::vector<Packed<scalar_t>> pk;
  std::vector<scalar_t> fs;
  pack_gaussians(in, bins, pk, fs, nthreads);
  scalar_t* o_out = o.out.data_ptr<scalar_t>();
  scalar_t* o_alpha = o.alpha.data_ptr<scalar_t>();
  scalar_t* o_med = o.median.data_ptr<scalar_t>();
  scalar_t* o_T = o.final_T.data_ptr<scalar_t>();
  int32_t* o_n = o.n_contrib.data_ptr<int32_t>();
  int32_t* o_last = o.last.data_ptr<int32_t>();
  int32_t* o_midx = o.median_idx.data_ptr<int32_t>();
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<scalar_t> T(kTilePix), acc(kTilePix * CS);
    std::vector<int32_t> lastc(kTilePix), ncon(kTilePix), med(kTilePix);
    std::vector<uint8_t> done(kTilePix);
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < n_tiles; ++tile) {
      const int64_t px0 = (tile % bins.tiles_x) * kTile, py0 = (tile / bins.tiles_x) * kTile;
      const int64_t px1 = std::min(px0 + kTile, W) - 1, py1 = std::min(py0 + kTile, H) - 1;
      std::fill(T.begin(), T.end(), scalar_t(1));
      std::fill(acc.begin(), acc.end(), scalar_t(0));
      std::fill(lastc.begin(), lastc.end(), 0);
      std::fill(ncon.begin(), ncon.end(), 0);
      std::fill(med.begin(), med.end(), -1);
      std::fill(done.begin(), done.end(), 0);
      int64_t alive = (px1 - px0 + 1) * (py1 - py0 + 1);
      const int64_t start = offs[tile], end = offs[tile + 1];
      for (int64_t s = start; s < end && alive > 0; ++s) {
        const int64_t r = slot_rank[s];
        const Splat2D<scalar_t> sp(pk[r], &fs[r * C], px0, px1, py0, py1);
        const int32_t q1 = int32_t(s - start + 1);
        scalar_t fl[kPad];  // features in a zero-padded local array: no aliasing, vector loops
        const scalar_t* f = sp.f;
        if (NC > 0) { std::fill(std::copy(sp.f, sp.f + C, fl), fl + kPad, scalar_t(0)); f = fl; }
        for (int64_t y = sp.y0; y <= sp.y1; ++y) {
          int64_t rx0, rx1;
          if (!sp.row(y, rx0, rx1)) continue;
          const scalar_t dy = sp.my - (scalar_t(y) + scalar_t(0.5));
          for (int64_t x = rx0; x <= rx1; ++x) {
            const int64_t i = (y - py0) * kTile + (x - px0);
            if (done[i]) continue;
            scalar_t G, raw;
            const scalar_t al = sp.alpha(sp.mx - (scalar_t(x) + scalar_t(0.5)), dy, G, raw);
            if (al < scalar_t(0)) continue;
            const scalar_t test_T = T[i] * (scalar_t(1) - al);
            if (test_T < scalar_t(1e-4)) { done[i] = 1; --alive; continue; }
            const scalar_t w = al * T[i];
            axpy<scalar_t, kP>(&acc[i * CS], f, w, CS);
            if (T[i] > scalar_t(0.5) && test_T <= scalar_t(0.5)) med[i] = sp.p.g;
            T[i] = test_T;
            lastc[i] = q1;
            ++ncon[i];
          }
        }
      }
      for (int64_t y = py0; y <= py1; ++y) {
        for (int64_t x = px0; x <= px1; ++x) {
          const int64_t i = (y - py0) * kTile + (x - px0), p = y * W + x;
          for (int64_t ch = 0; ch < C; ++ch) o_out[p * C + ch] = acc[i * CS + ch] + T[i] * in.bg[ch];
          o_alpha[p] = scalar_t(1) - T[i];
          o_T[p] = T[i];
          o_n[p] = ncon[i];
          o_last[p] = lastc[i];
          o_midx[p] = med[i];
          if (med[i] >= 0)
            for (int64_t m = 0; m < M; ++m) o_med[p * M + m] = medf[int64_t(med[i]) * M + m];
        }
      }
    }
  }
}

// Gradients of the forward rule (see splat/composite.py), back to front per pixel:
//   out = sum_i f_i a_i T_i + T_N bg,  T_i = prod_{j<i} (1 - a_j),  alpha_out = 1 - T_N
//   dout/da_i = f_i T_i - (S_i + T_N bg) / (1 - a_i),  S_i = sum_{j>i} f_j a_j T_j
//   dalpha_out/da_i = T_N / (1 - a_i);  a_i = min(0.99, o_i exp(power_i)).
// Writes per-slot gradients ent [E, 6 + C] (d mean2d, d conic, d opacity, d features) and the
// per-tile background gradients tile_bg [n_tiles, C].
template <typename scalar_t, int NC>  // NC > 0: channel count known at compile time
void backward_tiles(const Splats<scalar_t>& in, const scalar_t* g_out, const scalar_t* g_alpha,
                    const scalar_t* fT, const int32_t* o_last, const Bins& bins, scalar_t* ent,
                    scalar_t* tbg, int nthreads) {
  const int64_t C = NC > 0 ? NC : in.C, W = in.W, H = in.H, D = 6 + C;
  constexpr int64_t kPad = NC > 0 ? (NC + 3) / 4 * 4 : 1;  // channels padded to vector width
  const int64_t CS = NC > 0 ? kPad : C;                      // stride of per-pixel channels
  constexpr int64_t kP = NC > 0 ? kPad : 0;                  // compile-time channel loop length
  const int64_t tiles_x = bins.tiles_x, n_tiles = bins.tiles_x * bins.tiles_y;
  const int32_t* offs = bins.tile_offsets.data_ptr<int32_t>();
  const int32_t* slot_rank = bins.slot_rank.data_ptr<int32_t>();
  std::vector<Packed<scalar_t>> pk;
  std::vector<scalar_t> fs;
  pack_gaussians(in, bins, pk, fs, nthreads);
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<scalar_t> T(kTilePix), extra(kTilePix), gp(kTilePix * CS, 0), S(kTilePix * CS), df(C);
    std::vector<int32_t> lastc(kTilePix);
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < n_tiles; ++tile) {
      const int64_t px0 = (tile % tiles_x) * kTile, py0 = (tile / tiles_x) * kTile;
      const int64_t px1 = std::min(px0 + kTile, W) - 1, py1 = std::min(py0 + kTile, H) - 1;
      std::fill(lastc.begin(), lastc.end(), 0);
      std::fill(S.begin(), S.end(), scalar_t(0));
      scalar_t* tb = tbg + tile * C;
      std::fill(tb, tb + C, scalar_t(0));
      int32_t maxlast = 0;
      for (int64_t y = py0; y <= py1; ++y) {
        for (int64_t x = px0; x <= px1; ++x) {
          const int64_t i = (y - py0) * kTile + (x - px0), p = y * W + x;
          T[i] = fT[p];
          lastc[i] = o_last[p];
          maxlast = std::max(maxlast, lastc[i]);
          scalar_t bg_dot = 0;
          for (int64_t ch = 0; ch < C; ++ch) {
            gp[i * CS + ch] = g_out[p * C + ch];
            bg_dot += in.bg[ch] * g_out[p * C + ch];
            tb[ch] += fT[p] * g_out[p * C + ch];
          }
          extra[i] = fT[p] * (g_alpha[p] - bg_dot);  // T_N (d alpha_out - bg . d out)
        }
      }
      const int64_t start = offs[tile], count = offs[tile + 1] - start;
      std::fill(ent + (start + maxlast) * D, ent + (start + count) * D, scalar_t(0));
      for (int64_t q = int64_t(maxlast) - 1; q >= 0; --q) {
        const int64_t r = slot_rank[start + q];
        const Splat2D<scalar_t> sp(pk[r], &fs[r * C], px0, px1, py0, py1);
        scalar_t dmx = 0, dmy = 0, da = 0, db = 0, dc = 0, dop = 0;
        scalar_t fl[kPad], dfl[kPad];  // zero-padded local arrays: no aliasing, vector loops
        const scalar_t* f = sp.f;
        scalar_t* dfp = df.data();
        if (NC > 0) { std::fill(std::copy(sp.f, sp.f + C, fl), fl + kPad, scalar_t(0)); f = fl; dfp = dfl; }
        std::fill(dfp, dfp + CS, scalar_t(0));
        for (int64_t y = sp.y0; y <= sp.y1; ++y) {
          int64_t rx0, rx1;
          if (!sp.row(y, rx0, rx1)) continue;
          const scalar_t dy = sp.my - (scalar_t(y) + scalar_t(0.5));
          for (int64_t x = rx0; x <= rx1; ++x) {
            const int64_t i = (y - py0) * kTile + (x - px0);
            if (q >= lastc[i]) continue;  // behind this pixel's last blended Gaussian
            const scalar_t dx = sp.mx - (scalar_t(x) + scalar_t(0.5));
            scalar_t G, raw;
            const scalar_t al = sp.alpha(dx, dy, G, raw);
            if (al < scalar_t(0)) continue;
            const scalar_t inv = scalar_t(1) / (scalar_t(1) - al);
            const scalar_t Ti = T[i] * inv;  // transmittance in front of this Gaussian
            const scalar_t w = al * Ti;
            scalar_t* Si = &S[i * CS];
            const scalar_t* gi = &gp[i * CS];
            const scalar_t gf = dot<scalar_t, kP>(gi, f, CS), gs = dot<scalar_t, kP>(gi, Si, CS);
            axpy<scalar_t, kP>(dfp, gi, w, CS);
            axpy<scalar_t, kP>(Si, f, w, CS);
            const scalar_t dL_da = Ti * gf + inv * (extra[i] - gs);
            T[i] = Ti;
            if (raw > scalar_t(0.99)) continue;  // clamped: no gradient into opacity or power
            dop += G * dL_da;
            const scalar_t dL_dpow = sp.op * G * dL_da;
            dmx += dL_dpow * (-sp.a * dx - sp.b * dy);
            dmy += dL_dpow * (-sp.c * dy - sp.b * dx);
            da += dL_dpow * scalar_t(-0.5) * dx * dx;
            db += dL_dpow * (-dx * dy);
            dc += dL_dpow * scalar_t(-0.5) * dy * dy;
          }
        }
        scalar_t* e = ent + (start + q) * D;
        e[0] = dmx; e[1] = dmy; e[2] = da; e[3] = db; e[4] = dc; e[5] = dop;
        std::copy(dfp, dfp + C, e + 6);
      }
    }
  }
}

// Sum each Gaussian's slot gradients (fixed order: deterministic for any thread count).
template <typename scalar_t>
void reduce_slots(const scalar_t* ent, int64_t C, const Bins& bins, scalar_t* d_means,
                  scalar_t* d_conics, scalar_t* d_opac, scalar_t* d_feat, int nthreads) {
  const int64_t D = 6 + C, nv = bins.g_order.size(0);
  const int32_t* gord = bins.g_order.data_ptr<int32_t>();
  const int32_t* gst = bins.g_start.data_ptr<int32_t>();
  const int32_t* gsl = bins.g_slots.data_ptr<int32_t>();
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t k = 0; k < nv; ++k) {
    const int64_t g = gord[k];
    for (int64_t j = gst[k]; j < gst[k + 1]; ++j) {
      const scalar_t* e = ent + int64_t(gsl[j]) * D;
      d_means[2 * g] += e[0]; d_means[2 * g + 1] += e[1];
      d_conics[3 * g] += e[2]; d_conics[3 * g + 1] += e[3]; d_conics[3 * g + 2] += e[4];
      d_opac[g] += e[5];
      for (int64_t ch = 0; ch < C; ++ch) d_feat[g * C + ch] += e[6 + ch];
    }
  }
}

template <typename scalar_t>
Splats<scalar_t> make_splats(const torch::Tensor& means2d, const torch::Tensor& conics,
                             const torch::Tensor& opacities, const torch::Tensor& features,
                             const torch::Tensor& background, const torch::Tensor& radii,
                             int64_t W, int64_t H) {
  return {means2d.data_ptr<scalar_t>(), conics.data_ptr<scalar_t>(),
          opacities.data_ptr<scalar_t>(), features.data_ptr<scalar_t>(),
          background.data_ptr<scalar_t>(), radii.data_ptr<int32_t>(), features.size(1), W, H};
}

// Threads for one call: one for small images, where waking a second thread costs more than it saves.
int num_threads(int64_t W, int64_t H) { return W * H >= 64 * 64 ? at::get_num_threads() : 1; }

void check_inputs(const std::vector<torch::Tensor>& floats, const torch::Tensor& radii) {
  for (const auto& t : floats) {
    TORCH_CHECK(t.device().is_cpu() && t.is_contiguous(), "composite_cpu: tensors must be contiguous CPU");
    TORCH_CHECK(t.scalar_type() == floats[0].scalar_type(), "composite_cpu: mixed float dtypes");
  }
  TORCH_CHECK(radii.scalar_type() == torch::kInt32 && radii.is_contiguous(), "radii must be int32");
}

}  // namespace

std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor opacities, torch::Tensor features,
                                             torch::Tensor depths, torch::Tensor radii,
                                             torch::Tensor background, torch::Tensor median_features,
                                             int64_t W, int64_t H) {
  check_inputs({means2d, conics, opacities, features, depths, background, median_features}, radii);
  const int64_t N = features.size(0), C = features.size(1), M = median_features.size(1);
  const int nthreads = num_threads(W, H);
  auto opts = features.options();
  auto iopts = torch::TensorOptions().dtype(torch::kInt32);
  ForwardOut o{torch::empty({H, W, C}, opts), torch::empty({H, W}, opts),
               torch::zeros({H, W, M}, opts),  torch::empty({H, W}, iopts),
               torch::empty({H, W}, opts),     torch::empty({H, W}, iopts),
               torch::empty({H, W}, iopts)};
  Bins bins;
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "composite_forward", [&] {
    auto in = make_splats<scalar_t>(means2d, conics, opacities, features, background, radii, W, H);
    bins = bin_gaussians(in.mu, depths.data_ptr<scalar_t>(), in.rad, N, W, H, nthreads);
    if (C == 9)  // render(): RGB, depth plane (3), normal (3)
      forward_impl<scalar_t, 9>(in, median_features.data_ptr<scalar_t>(), M, bins, o, nthreads);
    else
      forward_impl<scalar_t, 0>(in, median_features.data_ptr<scalar_t>(), M, bins, o, nthreads);
  });
  return {o.out, o.alpha, o.median, o.n_contrib, o.final_T, o.last, o.median_idx,
          bins.tile_offsets, bins.slot_rank, bins.g_order, bins.g_start, bins.g_slots};
}

std::vector<torch::Tensor> composite_backward(
    torch::Tensor grad_out, torch::Tensor grad_alpha, torch::Tensor grad_median,
    torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities, torch::Tensor features,
    torch::Tensor radii, torch::Tensor background, torch::Tensor median_features,
    torch::Tensor final_T, torch::Tensor last, torch::Tensor median_idx, torch::Tensor tile_offsets,
    torch::Tensor slot_rank, torch::Tensor g_order, torch::Tensor g_start, torch::Tensor g_slots,
    int64_t W, int64_t H) {
  check_inputs({grad_out, grad_alpha, grad_median, means2d, conics, opacities, features,
                background, median_features, final_T}, radii);
  const int64_t N = features.size(0), C = features.size(1), M = median_features.size(1);
  const int nthreads = num_threads(W, H);
  const int64_t tiles_x = (W + kTile - 1) / kTile, n_tiles = tile_offsets.size(0) - 1;
  Bins bins{tiles_x, n_tiles / tiles_x, tile_offsets, slot_rank, g_order, g_start, g_slots};
  auto opts = features.options();
  torch::Tensor d_means = torch::zeros({N, 2}, opts), d_conics = torch::zeros({N, 3}, opts);
  torch::Tensor d_opac = torch::zeros({N}, opts), d_feat = torch::zeros({N, C}, opts);
  torch::Tensor d_medf = torch::zeros({N, M}, opts);
  torch::Tensor ent = torch::empty({slot_rank.size(0), 6 + C}, opts);
  torch::Tensor tile_bg = torch::empty({n_tiles, C}, opts);
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "composite_backward", [&] {
    auto in = make_splats<scalar_t>(means2d, conics, opacities, features, background, radii, W, H);
    auto tiles_fn = C == 9 ? backward_tiles<scalar_t, 9> : backward_tiles<scalar_t, 0>;
    tiles_fn(in, grad_out.data_ptr<scalar_t>(), grad_alpha.data_ptr<scalar_t>(),
                             final_T.data_ptr<scalar_t>(), last.data_ptr<int32_t>(), bins,
                             ent.data_ptr<scalar_t>(), tile_bg.data_ptr<scalar_t>(), nthreads);
    reduce_slots<scalar_t>(ent.data_ptr<scalar_t>(), C, bins, d_means.data_ptr<scalar_t>(),
                           d_conics.data_ptr<scalar_t>(), d_opac.data_ptr<scalar_t>(),
                           d_feat.data_ptr<scalar_t>(), nthreads);
    // Median is a selection: its gradient goes to the chosen Gaussian's median_features only.
    const scalar_t* g_med = grad_median.data_ptr<scalar_t>();
    const int32_t* midx = median_idx.data_ptr<int32_t>();
    scalar_t* o_dmf = d_medf.data_ptr<scalar_t>();
    for (int64_t p = 0; M > 0 && p < H * W; ++p)
      if (midx[p] >= 0)
        for (int64_t m = 0; m < M; ++m) o_dmf[int64_t(midx[p]) * M + m] += g_med[p * M + m];
  });
  torch::Tensor d_bg = tile_bg.sum(0);  // [C]
  return {d_means, d_conics, d_opac, d_feat, d_bg, d_medf};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "Tile-based CPU alpha compositing of 2D Gaussians (forward + analytic backward)";
  m.def("forward", &composite_forward, "composite forward (see splat/composite.py)");
  m.def("backward", &composite_backward, "composite backward (see splat/composite.py)");
}
