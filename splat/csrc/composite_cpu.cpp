// Tile-based front-to-back alpha compositing of projected 2D Gaussians on the CPU.
//
// Forward and analytic backward of the per-pixel rule in splat/composite.py (3DGS forward.cu /
// backward.cu semantics): 16x16 tiles with depth-sorted lists (composite_cpu.h), Gaussian-outer
// loops per tile over the rows and columns of each Gaussian's box that can pass the alpha
// threshold, 4 or 8 pixels of a row evaluated and blended at once (composite_cpu.h, Lanes), early
// termination per pixel; the backward runs back to front recovering T by division. OpenMP over
// tiles (dynamic schedule). Gradients are written per (tile, Gaussian) slot and summed per Gaussian
// in a fixed order afterwards, so the results do not depend on the thread count or schedule.

#include "composite_cpu.h"
#include "kernels.h"

#include <ATen/Parallel.h>

namespace {

using namespace composite_cpu;

// Forward outputs and the state the backward needs.
struct ForwardOut {
  torch::Tensor out, alpha, median, n_contrib, final_T, last, median_idx;
};

// The blend weights w = alpha T of the last forward that kept them, for a features-only backward (a
// frozen geometry): for each (Gaussian, L pixels of a row) a tile blended, the Gaussian's position q
// in the tile's list, the first pixel i4 of the L (tile-local) and the L weights (0 in the lanes it did
// not blend), in the forward's order (q ascending, then rows, then columns). Written into one arena
// per thread that keeps its memory from call to call (fresh buffers of tens of MB each step cost more
// in page faults than the backward saves), so a kept set is valid until the next forward that keeps
// one: ``generation`` tells the backward whether its forward's set is still there.
template <typename scalar_t>
struct Arena {
  std::vector<int32_t> qi;  // (q, i4) pairs
  std::vector<scalar_t> w;  // L weights per pair
};
struct TileRef {
  int32_t arena = 0;
  int64_t off = 0, n = 0;  // pairs [off, off + n) of that arena
};
template <typename scalar_t>
struct WeightStore {
  std::vector<Arena<scalar_t>> arenas;
  std::vector<TileRef> tiles;
  int64_t generation = -1;
};
template <typename scalar_t>
WeightStore<scalar_t>& weight_store() {
  static WeightStore<scalar_t> store;
  return store;
}
int64_t g_generation = 0;  // counts the forwards that kept weights (any dtype)

template <typename scalar_t, int NC>  // NC > 0: channel count known at compile time
void forward_impl(const Splats<scalar_t>& in, const scalar_t* medf, int64_t M, const Bins& bins,
                  ForwardOut& o, int nthreads, WeightStore<scalar_t>* ws = nullptr) {
  typedef typename Lanes<scalar_t>::V V;
  typedef typename Lanes<scalar_t>::M Mk;
  typedef typename Lanes<scalar_t>::MaskInt MaskInt;
  const int64_t C = NC > 0 ? NC : in.C, W = in.W, H = in.H, n_tiles = bins.tiles_x * bins.tiles_y;
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
  constexpr int L = Lanes<scalar_t>::L;
  const V lanes = iota<scalar_t>();
#pragma omp parallel num_threads(nthreads)
  {
    // per pixel: transmittance, blended channels (channel-major), and as lane-wide integers the
    // last blended list position, the count, the stopped mask (all bits set) and the median Gaussian
    std::vector<scalar_t> T(kTilePix), acc(kTilePix * C);
    std::vector<MaskInt> lastc(kTilePix), ncon(kTilePix), med(kTilePix), done(kTilePix);
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < n_tiles; ++tile) {
      const int64_t px0 = (tile % bins.tiles_x) * kTile, py0 = (tile / bins.tiles_x) * kTile;
      const int64_t px1 = std::min(px0 + kTile, W) - 1, py1 = std::min(py0 + kTile, H) - 1;
      std::fill(T.begin(), T.end(), scalar_t(1));
      std::fill(acc.begin(), acc.end(), scalar_t(0));
      std::fill(lastc.begin(), lastc.end(), MaskInt(0));
      std::fill(ncon.begin(), ncon.end(), MaskInt(0));
      std::fill(med.begin(), med.end(), MaskInt(-1));
      std::fill(done.begin(), done.end(), MaskInt(0));
      int64_t alive = (px1 - px0 + 1) * (py1 - py0 + 1);
      const int64_t start = offs[tile], end = offs[tile + 1];
      Arena<scalar_t>* ar = ws ? &ws->arenas[omp_get_thread_num()] : nullptr;
      TileRef* ref = ws ? &ws->tiles[tile] : nullptr;
      if (ws) *ref = {int32_t(omp_get_thread_num()), int64_t(ar->qi.size() / 2), 0};
      for (int64_t s = start; s < end && alive > 0; ++s) {
        const int64_t r = slot_rank[s];
        if (s + kAhead < end) prefetch_gaussian(pk, fs, C, slot_rank[s + kAhead]);
        const Splat2D<scalar_t> sp(pk[r], &fs[r * C], px0, px1, py0, py1);
        const MaskInt q1 = MaskInt(s - start + 1), gid = MaskInt(sp.p.g);
        for (int64_t y = sp.y0; y <= sp.y1; ++y) {
          int64_t rx0, rx1;
          if (!sp.row(y, rx0, rx1)) continue;
          const scalar_t dy = sp.my - (scalar_t(y) + scalar_t(0.5));
          const int64_t c0 = rx0 - px0, c1 = rx1 - px0, row = (y - py0) * kTile;
          for (int64_t g4 = c0 & ~int64_t(L - 1); g4 <= c1; g4 += L) {
            const int64_t i4 = row + g4;  // first pixel of the L lanes
            const V col = lanes + scalar_t(g4);
            const Mk stopped = vload<Mk>(&done[i4]);
            Mk m = (col >= scalar_t(c0)) & (col <= scalar_t(c1)) & ~stopped;
            if (!any(m)) continue;
            const V dx = sp.mx - ((lanes + scalar_t(px0 + g4)) + scalar_t(0.5));
            V G, raw, al;
            m = sp.eval_lanes(dx, dy, m, G, raw, al);
            if (!any(m)) continue;
            const V Tv = vload<V>(&T[i4]);
            const V test_T = Tv * (scalar_t(1) - al);
            const Mk stop = m & (test_T < scalar_t(1e-4));
            if (any(stop)) {  // these pixels are full: they blend nothing more
              vstore(&done[i4], stopped | stop);
              alive -= count(stop);
              m &= ~stop;
              if (!any(m)) continue;
            }
            const V w = al * Tv;
            if (ws) {
              ar->qi.push_back(int32_t(s - start));
              ar->qi.push_back(int32_t(i4));
              ar->w.resize(ar->w.size() + L);
              vstore(ar->w.data() + ar->w.size() - L, m ? w : V{});
            }
            scalar_t* a = &acc[i4];
            for (int64_t ch = 0; ch < C; ++ch, a += kTilePix) {
              const V av = vload<V>(a);
              vstore(a, m ? av + sp.f[ch] * w : av);
            }
            const Mk half = m & (Tv > scalar_t(0.5)) & (test_T <= scalar_t(0.5));
            if (any(half)) vstore(&med[i4], half ? Mk{} + gid : vload<Mk>(&med[i4]));
            vstore(&T[i4], m ? test_T : Tv);
            vstore(&lastc[i4], m ? Mk{} + q1 : vload<Mk>(&lastc[i4]));
            vstore(&ncon[i4], vload<Mk>(&ncon[i4]) - m);  // true = -1
          }
        }
      }
      if (ws) ref->n = int64_t(ar->qi.size() / 2) - ref->off;
      for (int64_t y = py0; y <= py1; ++y) {
        for (int64_t x = px0; x <= px1; ++x) {
          const int64_t i = (y - py0) * kTile + (x - px0), p = y * W + x;
          for (int64_t ch = 0; ch < C; ++ch) o_out[p * C + ch] = acc[ch * kTilePix + i] + T[i] * in.bg[ch];
          o_alpha[p] = scalar_t(1) - T[i];
          o_T[p] = T[i];
          o_n[p] = int32_t(ncon[i]);
          o_last[p] = int32_t(lastc[i]);
          o_midx[p] = int32_t(med[i]);
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
// Only d out . S_i enters, so a pixel keeps that one sum, sum_{j>i} (d out . f_j) a_j T_j, not S_i's
// C channels.
// Writes per-slot gradients ent [E, 6 + C] (d mean2d, d conic, d opacity, d features) and the
// per-tile background gradients tile_bg [n_tiles, C].
template <typename scalar_t, int NC>  // NC > 0: channel count known at compile time
void backward_tiles(const Splats<scalar_t>& in, const scalar_t* g_out, const scalar_t* g_alpha,
                    const scalar_t* fT, const int32_t* o_last, const Bins& bins, scalar_t* ent,
                    scalar_t* tbg, int nthreads) {
  typedef typename Lanes<scalar_t>::V V;
  typedef typename Lanes<scalar_t>::M Mk;
  const int64_t C = NC > 0 ? NC : in.C, W = in.W, H = in.H, D = 6 + C;
  const int64_t tiles_x = bins.tiles_x, n_tiles = bins.tiles_x * bins.tiles_y;
  const int32_t* offs = bins.tile_offsets.data_ptr<int32_t>();
  const int32_t* slot_rank = bins.slot_rank.data_ptr<int32_t>();
  std::vector<Packed<scalar_t>> pk;
  std::vector<scalar_t> fs;
  pack_gaussians(in, bins, pk, fs, nthreads);
  constexpr int L = Lanes<scalar_t>::L;
  const V lanes = iota<scalar_t>();
#pragma omp parallel num_threads(nthreads)
  {
    // per pixel: T (recovered back to front), T_N (d alpha_out - bg . d out), last blended list
    // position, d out . S; channel-major: d out
    std::vector<scalar_t> T(kTilePix), extra(kTilePix), lastc(kTilePix), gS(kTilePix);
    std::vector<scalar_t> gp(C * kTilePix);
    std::vector<V> dfeat(C);  // per-channel feature-gradient accumulators of one Gaussian
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < n_tiles; ++tile) {
      const int64_t px0 = (tile % tiles_x) * kTile, py0 = (tile / tiles_x) * kTile;
      const int64_t px1 = std::min(px0 + kTile, W) - 1, py1 = std::min(py0 + kTile, H) - 1;
      std::fill(lastc.begin(), lastc.end(), scalar_t(0));
      std::fill(gS.begin(), gS.end(), scalar_t(0));
      scalar_t* tb = tbg + tile * C;
      std::fill(tb, tb + C, scalar_t(0));
      int32_t maxlast = 0;
      for (int64_t y = py0; y <= py1; ++y) {
        for (int64_t x = px0; x <= px1; ++x) {
          const int64_t i = (y - py0) * kTile + (x - px0), p = y * W + x;
          T[i] = fT[p];
          lastc[i] = scalar_t(o_last[p]);
          maxlast = std::max(maxlast, o_last[p]);
          scalar_t bg_dot = 0;
          for (int64_t ch = 0; ch < C; ++ch) {
            gp[ch * kTilePix + i] = g_out[p * C + ch];
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
        if (q >= kAhead) prefetch_gaussian(pk, fs, C, slot_rank[start + q - kAhead]);
        const Splat2D<scalar_t> sp(pk[r], &fs[r * C], px0, px1, py0, py1);
        const scalar_t qf = scalar_t(q);
        V dmx{}, dmy{}, da{}, db{}, dc{}, dop{};
        std::fill(dfeat.begin(), dfeat.end(), V{});
        for (int64_t y = sp.y0; y <= sp.y1; ++y) {
          int64_t rx0, rx1;
          if (!sp.row(y, rx0, rx1)) continue;
          const scalar_t dy = sp.my - (scalar_t(y) + scalar_t(0.5));
          const int64_t c0 = rx0 - px0, c1 = rx1 - px0, row = (y - py0) * kTile;
          for (int64_t g4 = c0 & ~int64_t(L - 1); g4 <= c1; g4 += L) {
            const int64_t i = row + g4;
            const V col = lanes + scalar_t(g4);
            // lanes in the box whose pixel blended this Gaussian (list position < last)
            Mk m = (col >= scalar_t(c0)) & (col <= scalar_t(c1)) & (qf < vload<V>(&lastc[i]));
            if (!any(m)) continue;
            const V dx = sp.mx - ((lanes + scalar_t(px0 + g4)) + scalar_t(0.5));
            V G, raw, al;
            m = sp.eval_lanes(dx, dy, m, G, raw, al);
            if (!any(m)) continue;
            const V inv = scalar_t(1) / (scalar_t(1) - al);
            const V Tn = vload<V>(&T[i]);
            const V Ti = Tn * inv;  // transmittance in front of this Gaussian
            const V w = al * Ti;
            const V wm = m ? w : V{};
            V gf{};  // d out . f
            for (int64_t ch = 0; ch < C; ++ch) {
              const V g = vload<V>(&gp[ch * kTilePix + i]);
              gf += g * sp.f[ch];
              dfeat[ch] += wm * g;
            }
            const V gs = vload<V>(&gS[i]);  // d out . S
            vstore(&gS[i], m ? gs + gf * w : gs);
            const V dL_da = Ti * gf + inv * (vload<V>(&extra[i]) - gs);
            vstore(&T[i], m ? Ti : Tn);
            const Mk unclamped = m & (raw <= scalar_t(0.99));  // clamped: no grad to op or power
            const V gda = unclamped ? G * dL_da : V{};
            dop += gda;
            const V dL_dpow = sp.op * gda;
            dmx += dL_dpow * (-sp.a * dx - sp.b * dy);
            dmy += dL_dpow * (-sp.c * dy - sp.b * dx);
            da += dL_dpow * scalar_t(-0.5) * dx * dx;
            db += dL_dpow * (-dx * dy);
            dc += dL_dpow * scalar_t(-0.5) * dy * dy;
          }
        }
        scalar_t* e = ent + (start + q) * D;
        e[0] = hsum(dmx); e[1] = hsum(dmy); e[2] = hsum(da); e[3] = hsum(db); e[4] = hsum(dc);
        e[5] = hsum(dop);
        for (int64_t ch = 0; ch < C; ++ch) e[6 + ch] = hsum(dfeat[ch]);
      }
    }
  }
}

// The features' and background's gradients from the forward's stored weights (WeightStore): per
// Gaussian of a tile, d f = sum over its blended pixels of w * d out; no alpha is recomputed. Writes
// ent [E, 6 + C] (the geometry's six 0) and tile_bg as backward_tiles does.
template <typename scalar_t>
void backward_features_stored(const scalar_t* g_out, const scalar_t* fT, int64_t C, int64_t W, int64_t H,
                              const Bins& bins, const WeightStore<scalar_t>& ws, scalar_t* ent,
                              scalar_t* tbg, int nthreads) {
  typedef typename Lanes<scalar_t>::V V;
  constexpr int L = Lanes<scalar_t>::L;
  const int64_t tiles_x = bins.tiles_x, n_tiles = bins.tiles_x * bins.tiles_y, D = 6 + C;
  const int32_t* offs = bins.tile_offsets.data_ptr<int32_t>();
#pragma omp parallel num_threads(nthreads)
  {
    std::vector<scalar_t> gp(C * kTilePix + L, scalar_t(0));  // channel-major d out (+L: a row's last lanes)
    std::vector<V> dfeat(C);
#pragma omp for schedule(dynamic, 1)
    for (int64_t tile = 0; tile < n_tiles; ++tile) {
      const int64_t px0 = (tile % tiles_x) * kTile, py0 = (tile / tiles_x) * kTile;
      const int64_t px1 = std::min(px0 + kTile, W) - 1, py1 = std::min(py0 + kTile, H) - 1;
      scalar_t* tb = tbg + tile * C;
      std::fill(tb, tb + C, scalar_t(0));
      std::fill(gp.begin(), gp.end(), scalar_t(0));  // a partial tile's lanes outside the image: 0 (w is 0 there)
      for (int64_t y = py0; y <= py1; ++y)
        for (int64_t x = px0; x <= px1; ++x) {
          const int64_t i = (y - py0) * kTile + (x - px0), p = y * W + x;
          for (int64_t ch = 0; ch < C; ++ch) {
            gp[ch * kTilePix + i] = g_out[p * C + ch];
            tb[ch] += fT[p] * g_out[p * C + ch];
          }
        }
      const int64_t start = offs[tile], count = offs[tile + 1] - start;
      std::fill(ent + start * D, ent + (start + count) * D, scalar_t(0));
      const TileRef& ref = ws.tiles[tile];
      const int32_t* qi = ws.arenas[ref.arena].qi.data() + 2 * ref.off;
      const scalar_t* wts = ws.arenas[ref.arena].w.data() + L * ref.off;
      int64_t q = -1;
      for (int64_t e = 0; e <= ref.n; ++e) {
        const int64_t qe = e < ref.n ? qi[2 * e] : -2;
        if (qe != q) {  // the previous Gaussian's sums are complete
          if (q >= 0)
            for (int64_t ch = 0; ch < C; ++ch) ent[(start + q) * D + 6 + ch] = hsum(dfeat[ch]);
          std::fill(dfeat.begin(), dfeat.end(), V{});
          q = qe;
        }
        if (qe < 0) break;
        const int64_t i4 = qi[2 * e + 1];
        const V w = vload<V>(wts + e * L);
        for (int64_t ch = 0; ch < C; ++ch) dfeat[ch] += w * vload<V>(&gp[ch * kTilePix + i4]);
      }
    }
  }
}

// Sum each Gaussian's slot gradients (fixed order: deterministic for any thread count); d_means null:
// the features' alone (the stored-weights backward, whose slots hold no geometry gradient).
template <typename scalar_t>
void reduce_slots(const scalar_t* ent, int64_t C, const Bins& bins, scalar_t* d_means,
                  scalar_t* d_conics, scalar_t* d_opac, scalar_t* d_feat, int nthreads) {
  const int64_t D = 6 + C, nv = bins.g_order.size(0);
  const int32_t* gord = bins.g_order.data_ptr<int32_t>();
  const int32_t* gst = bins.g_start.data_ptr<int32_t>();
  const int32_t* gsl = bins.g_slots.data_ptr<int32_t>();
#pragma omp parallel for num_threads(threads_for(nv, nthreads)) schedule(static)
  for (int64_t k = 0; k < nv; ++k) {
    const int64_t g = gord[k];
    for (int64_t j = gst[k]; j < gst[k + 1]; ++j) {
      const scalar_t* e = ent + int64_t(gsl[j]) * D;
      if (d_means) {
        d_means[2 * g] += e[0]; d_means[2 * g + 1] += e[1];
        d_conics[3 * g] += e[2]; d_conics[3 * g + 1] += e[3]; d_conics[3 * g + 2] += e[4];
        d_opac[g] += e[5];
      }
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
                                             int64_t W, int64_t H, bool store_weights) {
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
  int64_t generation = -1;
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "composite_forward", [&] {
    auto in = make_splats<scalar_t>(means2d, conics, opacities, features, background, radii, W, H);
    bins = bin_gaussians(in.mu, depths.data_ptr<scalar_t>(), in.rad, N, W, H, nthreads);
    WeightStore<scalar_t>* ws = nullptr;
    if (store_weights) {
      ws = &weight_store<scalar_t>();
      ws->generation = generation = ++g_generation;
      ws->tiles.assign(bins.tiles_x * bins.tiles_y, TileRef{});
      const size_t n_arenas = size_t(std::max(nthreads, omp_get_max_threads()));
      if (ws->arenas.size() < n_arenas) ws->arenas.resize(n_arenas);
      for (auto& a : ws->arenas) {
        a.qi.clear();  // keeps the capacity
        a.w.clear();
      }
    }
    if (C == 9)  // render(): RGB, depth plane (3), normal (3)
      forward_impl<scalar_t, 9>(in, median_features.data_ptr<scalar_t>(), M, bins, o, nthreads, ws);
    else if (C == 3)  // render(maps=False): RGB only
      forward_impl<scalar_t, 3>(in, median_features.data_ptr<scalar_t>(), M, bins, o, nthreads, ws);
    else
      forward_impl<scalar_t, 0>(in, median_features.data_ptr<scalar_t>(), M, bins, o, nthreads, ws);
  });
  return {o.out, o.alpha, o.median, o.n_contrib, o.final_T, o.last, o.median_idx,
          bins.tile_offsets, bins.slot_rank, bins.g_order, bins.g_start, bins.g_slots,
          torch::full({1}, generation, torch::TensorOptions().dtype(torch::kInt64))};
}

std::vector<torch::Tensor> composite_backward_stored(
    torch::Tensor grad_out, torch::Tensor features, torch::Tensor final_T, torch::Tensor tile_offsets,
    torch::Tensor slot_rank, torch::Tensor g_order, torch::Tensor g_start, torch::Tensor g_slots,
    int64_t generation, int64_t W, int64_t H) {
  check_inputs({grad_out, features, final_T}, slot_rank);
  const int64_t N = features.size(0), C = features.size(1);
  const int nthreads = num_threads(W, H);
  const int64_t tiles_x = (W + kTile - 1) / kTile, n_tiles = tile_offsets.size(0) - 1;
  const bool current = features.scalar_type() == torch::kDouble ? weight_store<double>().generation == generation
                                                                 : weight_store<float>().generation == generation;
  if (!current) return {};  // a later forward kept its own weights: the caller takes the full backward
  Bins bins{tiles_x, n_tiles / tiles_x, tile_offsets, slot_rank, g_order, g_start, g_slots};
  auto opts = features.options();
  torch::Tensor d_feat = torch::zeros({N, C}, opts);
  torch::Tensor ent = torch::empty({slot_rank.size(0), 6 + C}, opts);
  torch::Tensor tile_bg = torch::empty({n_tiles, C}, opts);
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "composite_backward_stored", [&] {
    const WeightStore<scalar_t>& ws = weight_store<scalar_t>();
    TORCH_CHECK(int64_t(ws.tiles.size()) == n_tiles, "composite_backward_stored: the weights are not this image's");
    backward_features_stored<scalar_t>(grad_out.data_ptr<scalar_t>(), final_T.data_ptr<scalar_t>(), C, W, H, bins,
                                       ws, ent.data_ptr<scalar_t>(), tile_bg.data_ptr<scalar_t>(), nthreads);
    reduce_slots<scalar_t>(ent.data_ptr<scalar_t>(), C, bins, nullptr, nullptr, nullptr,
                           d_feat.data_ptr<scalar_t>(), nthreads);
  });
  return {d_feat, tile_bg.sum(0)};
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
    auto tiles_fn = C == 9 ? backward_tiles<scalar_t, 9> : C == 3 ? backward_tiles<scalar_t, 3> : backward_tiles<scalar_t, 0>;
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
