// Binning, depth sorting and per-Gaussian packing for splat/csrc/composite_cpu.cpp.
//
// Gaussians are binned to the 16x16 tiles their pixel radius box touches, after one global
// stable depth sort (LSD radix sort on the float bits), so that every tile's list comes out front
// to back. Each visible Gaussian's parameters are then copied in depth order into one array
// (Packed), with per-Gaussian constants that let the tile loops skip pixels cheaply.

#pragma once

#include <torch/extension.h>

#include "omp_compat.h"

#include <algorithm>
#include <climits>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <type_traits>
#include <vector>

#if defined(__SSE2__)
#include <immintrin.h>
#endif

namespace composite_cpu {

constexpr int64_t kTile = 16;
constexpr int64_t kTilePix = kTile * kTile;

// Threads for a light O(n) pass: one below ~1 ms of work, where a second thread's wake-up and the
// end-of-loop barrier cost more than they save (much more on cores shared with other processes).
inline int threads_for(int64_t n, int nthreads) { return n >= 131072 ? nthreads : 1; }

// Pixel box of a Gaussian (inclusive, clipped to the image): columns j with |j + 0.5 - mx| <= r.
// Returns false when the Gaussian is culled (r <= 0), not finite, or its box misses the image.
template <typename scalar_t>
inline bool pixel_box(scalar_t mx, scalar_t my, int32_t r, int64_t W, int64_t H, int64_t box[4]) {
  if (r <= 0 || !std::isfinite(mx) || !std::isfinite(my)) return false;
  const double x0 = std::max(std::ceil(double(mx) - r - 0.5), 0.0);
  const double x1 = std::min(std::floor(double(mx) + r - 0.5), double(W - 1));
  const double y0 = std::max(std::ceil(double(my) - r - 0.5), 0.0);
  const double y1 = std::min(std::floor(double(my) + r - 0.5), double(H - 1));
  if (x0 > x1 || y0 > y1) return false;
  box[0] = int64_t(x0); box[1] = int64_t(x1); box[2] = int64_t(y0); box[3] = int64_t(y1);
  return true;
}

// Order-preserving unsigned key of a float/double (ascending keys = ascending values).
template <typename scalar_t>
inline auto sort_key(scalar_t v) {
  using U = std::conditional_t<sizeof(scalar_t) == 4, uint32_t, uint64_t>;
  U u;
  std::memcpy(&u, &v, sizeof(U));
  constexpr U sign = U(1) << (8 * sizeof(U) - 1);
  return (u & sign) ? U(~u) : U(u | sign);
}

// Stable LSD radix sort of `ids` by keys (11-bit digits); ties keep their input (index) order.
template <typename U>
void radix_sort(std::vector<U>& keys, std::vector<int32_t>& ids) {
  const size_t n = keys.size();
  std::vector<U> k2(n);
  std::vector<int32_t> i2(n);
  constexpr int kBits = 11, kBuckets = 1 << kBits;
  for (int shift = 0; shift < int(8 * sizeof(U)); shift += kBits) {
    std::vector<size_t> count(kBuckets + 1, 0);
    for (size_t i = 0; i < n; ++i) ++count[((keys[i] >> shift) & (kBuckets - 1)) + 1];
    if (count[1 + ((keys.empty() ? 0 : (keys[0] >> shift)) & (kBuckets - 1))] == n) continue;
    for (int b = 0; b < kBuckets; ++b) count[b + 1] += count[b];
    for (size_t i = 0; i < n; ++i) {
      const size_t dst = count[(keys[i] >> shift) & (kBuckets - 1)]++;
      k2[dst] = keys[i];
      i2[dst] = ids[i];
    }
    keys.swap(k2);
    ids.swap(i2);
  }
}

// Tile lists: slot_rank[tile_offsets[t] .. tile_offsets[t+1]) are the depth ranks k of tile t's
// Gaussians, front to back; the k-th Gaussian in depth order is g_order[k] and its slots are
// g_slots[g_start[k] .. g_start[k+1]).
struct Bins {
  int64_t tiles_x = 0, tiles_y = 0;
  torch::Tensor tile_offsets, slot_rank, g_order, g_start, g_slots;  // int32
};

template <typename scalar_t>
Bins bin_gaussians(const scalar_t* means, const scalar_t* depths, const int32_t* radii, int64_t N,
                   int64_t W, int64_t H, int nthreads) {
  Bins b;
  b.tiles_x = (W + kTile - 1) / kTile;
  b.tiles_y = (H + kTile - 1) / kTile;
  const int64_t n_tiles = b.tiles_x * b.tiles_y;
  std::vector<int64_t> rect(4 * N);  // tile rect [tx0, tx1, ty0, ty1], inclusive
  std::vector<uint8_t> vis(N, 0);
#pragma omp parallel for num_threads(threads_for(N, nthreads)) schedule(static)
  for (int64_t g = 0; g < N; ++g) {
    int64_t box[4];
    if (!std::isfinite(depths[g]) ||
        !pixel_box(means[2 * g], means[2 * g + 1], radii[g], W, H, box)) continue;
    vis[g] = 1;
    rect[4 * g + 0] = box[0] / kTile; rect[4 * g + 1] = box[1] / kTile;
    rect[4 * g + 2] = box[2] / kTile; rect[4 * g + 3] = box[3] / kTile;
  }
  using U = decltype(sort_key(scalar_t(0)));
  std::vector<U> keys;
  std::vector<int32_t> order;
  for (int64_t g = 0; g < N; ++g) {
    if (!vis[g]) continue;
    keys.push_back(sort_key(depths[g]));
    order.push_back(int32_t(g));
  }
  radix_sort(keys, order);
  const int64_t nv = int64_t(order.size());
  b.g_order = torch::from_blob(order.data(), {nv}, torch::kInt32).clone();
  b.g_start = torch::empty({nv + 1}, torch::kInt32);
  int32_t* g_start = b.g_start.data_ptr<int32_t>();
  int64_t total = 0;
  for (int64_t k = 0; k < nv; ++k) {
    const int64_t* r = &rect[4 * int64_t(order[k])];
    g_start[k] = int32_t(total);
    total += (r[1] - r[0] + 1) * (r[3] - r[2] + 1);
    TORCH_CHECK(total < INT_MAX, "composite_cpu: too many (tile, Gaussian) pairs: ", total);
  }
  g_start[nv] = int32_t(total);
  b.tile_offsets = torch::zeros({n_tiles + 1}, torch::kInt32);
  b.slot_rank = torch::empty({total}, torch::kInt32);
  b.g_slots = torch::empty({total}, torch::kInt32);
  int32_t* offs = b.tile_offsets.data_ptr<int32_t>();
  int32_t* slot_rank = b.slot_rank.data_ptr<int32_t>();
  int32_t* g_slots = b.g_slots.data_ptr<int32_t>();
  // Count per tile, then scatter in depth order. Each thread owns a band of tile rows, scans all
  // Gaussians and writes only its band's slots: deterministic and without atomics.
  for (int pass = 0; pass < 2; ++pass) {
    std::vector<int32_t> cursor;
    if (pass == 1) {
      for (int64_t t = 0; t < n_tiles; ++t) offs[t + 1] += offs[t];
      cursor.assign(offs, offs + n_tiles);
    }
#pragma omp parallel num_threads(threads_for(total, nthreads))
    {
      const int64_t nt = omp_get_num_threads(), tid = omp_get_thread_num();
      const int64_t band0 = b.tiles_y * tid / nt, band1 = b.tiles_y * (tid + 1) / nt;
      for (int64_t k = 0; k < nv; ++k) {
        const int64_t* r = &rect[4 * int64_t(order[k])];
        const int64_t ty0 = std::max(r[2], band0), ty1 = std::min(r[3], band1 - 1);
        for (int64_t ty = ty0; ty <= ty1; ++ty) {
          for (int64_t tx = r[0]; tx <= r[1]; ++tx) {
            const int64_t t = ty * b.tiles_x + tx;
            if (pass == 0) { ++offs[t + 1]; continue; }
            const int32_t s = cursor[t]++;
            slot_rank[s] = int32_t(k);
            g_slots[g_start[k] + (ty - r[2]) * (r[1] - r[0] + 1) + (tx - r[0])] = s;
          }
        }
      }
    }
  }
  return b;
}

// Read-only inputs as raw pointers (contiguous, one dtype), plus the image size.
template <typename scalar_t>
struct Splats {
  const scalar_t *mu, *con, *opa, *feat, *bg;  // [N,2] [N,3] [N] [N,C] [C]
  const int32_t* rad;                          // [N]
  int64_t C, W, H;
};

// One visible Gaussian's parameters, copied in depth order so that a tile's loop reads them
// sequentially from one array (instead of five scattered ones), with per-Gaussian constants.
template <typename scalar_t>
struct Packed {
  scalar_t mx, my, a, b, c, op;
  scalar_t skip_below;  // power below which op * exp(power) < 1/255 for sure: no exp needed
  double k, det, inv_a;  // ellipse a dx^2 + 2 b dx dy + c dy^2 <= k holds power >= skip_below
  int32_t g;             // index of the Gaussian in the inputs
  int32_t box[4];        // pixel box [x0, x1, y0, y1], inclusive, clipped to the image
};

// Pack the visible Gaussians in depth order: params [nv] and their features [nv, C].
template <typename scalar_t>
void pack_gaussians(const Splats<scalar_t>& in, const Bins& bins, std::vector<Packed<scalar_t>>& pk,
                    std::vector<scalar_t>& feat, int nthreads) {
  const int64_t nv = bins.g_order.size(0), C = in.C;
  const int32_t* order = bins.g_order.data_ptr<int32_t>();
  pk.resize(nv);
  feat.resize(nv * C);
#pragma omp parallel for num_threads(threads_for(nv, nthreads)) schedule(static)
  for (int64_t r = 0; r < nv; ++r) {
    const int64_t g = order[r];
    Packed<scalar_t>& p = pk[r];
    p.mx = in.mu[2 * g]; p.my = in.mu[2 * g + 1];
    p.a = in.con[3 * g]; p.b = in.con[3 * g + 1]; p.c = in.con[3 * g + 2]; p.op = in.opa[g];
    p.g = int32_t(g);
    // margin 1e-3 in power >> exp rounding: the skipped pixels have alpha < 1/255 for sure
    p.skip_below = p.op > scalar_t(0) ? scalar_t(std::log(1.0 / 255.0 / double(p.op)) - 1e-3)
                                      : std::numeric_limits<scalar_t>::infinity();
    int64_t box[4];
    pixel_box(p.mx, p.my, in.rad[g], in.W, in.H, box);  // non-empty: g was binned
    for (int j = 0; j < 4; ++j) p.box[j] = int32_t(box[j]);
    const double det = double(p.a) * p.c - double(p.b) * p.b, k = -2.0 * double(p.skip_below);
    const bool ellipse = p.a > scalar_t(0) && det > 0 && std::isfinite(det) && std::isfinite(k);
    p.k = ellipse ? k : -1.0;  // -1: not positive definite, evaluate the whole box
    p.det = ellipse ? det : 0.0;
    p.inv_a = ellipse ? 1.0 / double(p.a) : 0.0;
    std::copy(in.feat + g * C, in.feat + (g + 1) * C, feat.begin() + r * C);
  }
}

// A tile reads its Gaussians' packed data in depth order, scattered over the whole array: ask for
// the one kAhead places further down the list while this one is composited.
constexpr int64_t kAhead = 8;
template <typename scalar_t>
inline void prefetch_gaussian(const std::vector<Packed<scalar_t>>& pk, const std::vector<scalar_t>& fs,
                              int64_t C, int64_t r) {
  const char* p = reinterpret_cast<const char*>(&pk[r]);
  __builtin_prefetch(p);
  __builtin_prefetch(p + sizeof(Packed<scalar_t>) - 1);
  __builtin_prefetch(&fs[r * C]);
  __builtin_prefetch(&fs[r * C + C - 1]);
}

// Vectors of L lanes (GCC vector extensions): the tile loops process L neighbouring pixels of a row
// at once. V holds scalar_t lanes, M the matching lane mask (all bits set = true). float has 8 lanes
// where the build targets AVX2 (splat/cpu_ext.py builds the extension with -mavx2 on CPUs that have
// it, the baseline build elsewhere), 4 otherwise; double has 4. Each
// lane evaluates the same operations in the same order, so a pixel's alpha, colour and depth do
// not depend on L; only the order of the per-Gaussian gradient sums over a row's lanes does.
#if defined(__AVX2__)
constexpr int kFloatLanes = 8;
#else
constexpr int kFloatLanes = 4;
#endif
template <typename T>
struct Lanes;
template <>
struct Lanes<float> {
  static constexpr int L = kFloatLanes;
  typedef float V __attribute__((vector_size(4 * kFloatLanes)));
  typedef int32_t M __attribute__((vector_size(4 * kFloatLanes)));
  typedef int32_t MaskInt;
};
template <>
struct Lanes<double> {
  static constexpr int L = 4;
  typedef double V __attribute__((vector_size(32)));
  typedef int64_t M __attribute__((vector_size(32)));
  typedef int64_t MaskInt;
};

template <typename V, typename T>
inline V vload(const T* p) {
  V v;
  std::memcpy(&v, p, sizeof(V));
  return v;
}
template <typename V, typename T>
inline void vstore(T* p, const V& v) {
  std::memcpy(p, &v, sizeof(V));
}
// 0, 1, ..., L-1
template <typename scalar_t>
inline typename Lanes<scalar_t>::V iota() {
  typename Lanes<scalar_t>::V v{};
  for (int l = 0; l < Lanes<scalar_t>::L; ++l) v[l] = scalar_t(l);
  return v;
}
template <typename M>
inline bool any(const M& m) {
#if defined(__AVX__)
  if constexpr (sizeof(M) == 32) {  // one vmovmskps / vmovmskpd instead of a chain of ORs
    __m256 v;
    std::memcpy(&v, &m, sizeof(v));
    return _mm256_movemask_ps(v) != 0;
  }
#endif
#if defined(__SSE2__)
  if constexpr (sizeof(M) == 16) {
    __m128 v;
    std::memcpy(&v, &m, sizeof(v));
    return _mm_movemask_ps(v) != 0;
  }
#endif
  constexpr int n = sizeof(M) / sizeof(m[0]);
  auto acc = m[0];
  for (int l = 1; l < n; ++l) acc |= m[l];
  return acc != 0;
}
// Number of true lanes of a mask (true = -1).
template <typename M>
inline int64_t count(const M& m) {
  constexpr int n = sizeof(M) / sizeof(m[0]);
  int64_t c = 0;
  for (int l = 0; l < n; ++l) c -= int64_t(m[l]);
  return c;
}
// Sum of the lanes as a fixed pairwise tree.
template <typename V>
inline auto hsum(const V& v) {
  constexpr int n = sizeof(V) / sizeof(v[0]);
  if constexpr (n == 8) return ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7]));
  else return (v[0] + v[1]) + (v[2] + v[3]);
}

// exp of L floats (Cephes expf: range reduction by ln 2, degree-6 polynomial; ~1 ulp on
// [-87, 0], exp(0) = 1 exactly); arguments below -87 are clamped (their alpha is skipped anyway).
inline Lanes<float>::V vexp(Lanes<float>::V x) {
  typedef Lanes<float>::V V;
  typedef Lanes<float>::M M;
  x = x < -87.0f ? V{} - 87.0f : x;
  const V t = x * 1.44269504088896341f + 0.5f;
  M n = __builtin_convertvector(t, M);     // truncation towards zero ...
  n += __builtin_convertvector(n, V) > t;  // ... then floor (true = -1)
  const V nf = __builtin_convertvector(n, V);
  const V r = (x - nf * 0.693359375f) - nf * -2.12194440e-4f;
  V p = V{} + 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  const V y = p * (r * r) + r + 1.0f;
  const M bits = (n + 127) << 23;  // 2^n
  V scale;
  std::memcpy(&scale, &bits, sizeof(V));
  return y * scale;
}

// double (tests, gradcheck): exp per lane.
inline Lanes<double>::V vexp(Lanes<double>::V x) {
  return Lanes<double>::V{std::exp(x[0]), std::exp(x[1]), std::exp(x[2]), std::exp(x[3])};
}

// One Gaussian's box clipped to one tile, and the rows / columns worth evaluating.
template <typename scalar_t>
struct Splat2D {
  const Packed<scalar_t>& p;
  const scalar_t *f;
  scalar_t mx, my, a, b, c, op, skip_below;
  int64_t x0, x1, y0, y1;  // pixel box clipped to the tile (and to the ellipse's rows)

  Splat2D(const Packed<scalar_t>& p_, const scalar_t* f_, int64_t px0, int64_t px1, int64_t py0,
          int64_t py1)
      : p(p_), f(f_), mx(p_.mx), my(p_.my), a(p_.a), b(p_.b), c(p_.c), op(p_.op),
        skip_below(p_.skip_below) {
    x0 = std::max(int64_t(p.box[0]), px0); x1 = std::min(int64_t(p.box[1]), px1);
    y0 = std::max(int64_t(p.box[2]), py0); y1 = std::min(int64_t(p.box[3]), py1);
    // Rows and per-row columns outside the ellipse power >= skip_below are skipped without
    // evaluation (pure speed; a 1-pixel margin covers rounding, the exact test runs per pixel).
    if (!(skip_below <= scalar_t(0))) { y1 = y0 - 1; return; }  // op < 1/255: nothing passes
    if (p.k >= 0) {
      const double hy = std::sqrt(p.k * p.a / p.det);
      y0 = std::max(y0, int64_t(std::max(std::ceil(double(my) - hy - 0.5) - 1, double(y0))));
      y1 = std::min(y1, int64_t(std::min(std::floor(double(my) + hy - 0.5) + 1, double(y1))));
    }
  }

  // Columns [rx0, rx1] of row y worth evaluating; false if none.
  inline bool row(int64_t y, int64_t& rx0, int64_t& rx1) const {
    rx0 = x0; rx1 = x1;
    if (p.k < 0) return x0 <= x1;
    const double dy = double(my) - (double(y) + 0.5), disc = p.k * a - p.det * dy * dy;
    if (disc < 0) return false;
    const double sq = std::sqrt(disc), mid = double(mx) + double(b) * dy * p.inv_a;
    // dx = mx - px in [(-b dy - sq) / a, (-b dy + sq) / a]  =>  px = j + 0.5 in [mid - sq/a, mid + sq/a]
    rx0 = int64_t(std::max(std::ceil(mid - sq * p.inv_a - 0.5) - 1, double(x0)));
    rx1 = int64_t(std::min(std::floor(mid + sq * p.inv_a - 0.5) + 1, double(x1)));
    return rx0 <= rx1;
  }

  // The rule at L pixels: offsets dx (lanes) and dy = mean - pixel centre; m = lanes to evaluate.
  // Returns m without the skipped lanes (power > 0, alpha < 1/255); G = exp(power),
  // raw = op G, al = min(0.99, raw). Forward and backward call this same code.
  typedef typename Lanes<scalar_t>::V V;
  typedef typename Lanes<scalar_t>::M M;
  inline M eval_lanes(const V& dx, scalar_t dy, M m, V& G, V& raw, V& al) const {
    const V power = scalar_t(-0.5) * (a * dx * dx + c * dy * dy) - b * dx * dy;
    m &= (power <= scalar_t(0)) & (power >= skip_below);  // NaN fails both: skipped
    G = vexp(power);
    raw = op * G;
    al = raw < scalar_t(0.99) ? raw : V{} + scalar_t(0.99);
    return m & (al >= scalar_t(1.0 / 255.0));
  }
};

}  // namespace composite_cpu
