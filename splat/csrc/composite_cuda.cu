// Tile-based front-to-back alpha compositing of projected 2D Gaussians on a CUDA GPU.
//
// Forward and analytic backward of the per-pixel rule in splat/composite.py, 3DGS-style
// (forward.cu / backward.cu), float32 only:
//   1. prepare_kernel: per Gaussian, its pixel box exactly as composite_cpu.h pixel_box (double
//      arithmetic), the 16x16 tiles it touches, and its parameters packed (float2 mean, float4
//      conic + opacity, int4 box).
//   2. emit_kernel + cub radix sort: one (tile << 32 | depth bits) key per (tile, Gaussian) pair,
//      emitted in Gaussian order and sorted stably, so that each tile's list is front to back with
//      depth ties in index order (the rule's order); ranges_kernel finds each tile's slice.
//   3. forward_kernel: one 256-thread block per tile, one thread per pixel; the tile's Gaussians
//      are staged in shared memory 256 at a time; a block stops when all its pixels are done. It
//      saves the final transmittance, the list position of the last blended Gaussian and the
//      median Gaussian per pixel.
//   4. backward_kernel: the same tiles back to front from the block's largest last position, T
//      recovered by division (as backward.cu); each warp sums its pixels' gradients of a Gaussian
//      with shuffles and one lane adds them to the Gaussian's gradients with atomicAdd (the order
//      of the atomics varies: gradients are not bitwise reproducible from run to run).
// The alpha of a (Gaussian, pixel) pair is evaluated by one function (eval_alpha) in both passes,
// with each multiply and add rounded separately (as the CPU kernel built with -ffp-contract=off and
// the torch backend's separate tensor ops), so that both passes and both other backends take the
// same skip / stop decisions.

#include "composite_cuda.h"

#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>
#include <cub/cub.cuh>

#include <climits>
#include <cstdint>

namespace {

constexpr int kTile = 16;
constexpr int kBlock = kTile * kTile;  // threads per block = pixels per tile
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr float kTMin = 1e-4f;
constexpr unsigned kFullMask = 0xffffffffu;

// Order-preserving unsigned key of a float (ascending keys = ascending values), as composite_cpu.h.
__device__ __forceinline__ uint32_t depth_key(float d) {
  const uint32_t u = __float_as_uint(d);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

// Per Gaussian: packed parameters, inclusive pixel box clipped to the image (empty: x0 > x1) and
// the number of tiles it touches (0 when culled, not finite, or off the image).
__global__ void prepare_kernel(int N, const float* __restrict__ means, const float* __restrict__ conics,
                               const float* __restrict__ opac, const float* __restrict__ depths,
                               const int32_t* __restrict__ radii, int W, int H, float2* __restrict__ xy,
                               float4* __restrict__ con_o, int4* __restrict__ box, int4* __restrict__ rect,
                               int32_t* __restrict__ counts, uint32_t* __restrict__ dkey) {
  const int g = blockIdx.x * blockDim.x + threadIdx.x;
  if (g >= N) return;
  const float mx = means[2 * g], my = means[2 * g + 1], d = depths[g];
  const int r = radii[g];
  xy[g] = make_float2(mx, my);
  con_o[g] = make_float4(conics[3 * g], conics[3 * g + 1], conics[3 * g + 2], opac[g]);
  dkey[g] = depth_key(d);
  int4 b = make_int4(0, -1, 0, -1);
  int n = 0;
  if (r > 0 && isfinite(mx) && isfinite(my) && isfinite(d)) {
    // columns j with |j + 0.5 - mx| <= r, rows likewise (composite_cpu.h pixel_box)
    const double x0 = fmax(ceil(double(mx) - r - 0.5), 0.0);
    const double x1 = fmin(floor(double(mx) + r - 0.5), double(W - 1));
    const double y0 = fmax(ceil(double(my) - r - 0.5), 0.0);
    const double y1 = fmin(floor(double(my) + r - 0.5), double(H - 1));
    if (x0 <= x1 && y0 <= y1) {
      b = make_int4(int(x0), int(x1), int(y0), int(y1));
      const int4 t = make_int4(b.x / kTile, b.y / kTile, b.z / kTile, b.w / kTile);
      rect[g] = t;
      n = (t.y - t.x + 1) * (t.w - t.z + 1);
    }
  }
  box[g] = b;
  counts[g] = n;
}

// One key (tile << 32 | depth key) and value (Gaussian index) per (tile, Gaussian) pair, written
// at the Gaussian's slice [offsets[g] - counts[g], offsets[g]) (offsets: inclusive prefix sums).
__global__ void emit_kernel(int N, const int64_t* __restrict__ offsets, const int32_t* __restrict__ counts,
                            const int4* __restrict__ rect, const uint32_t* __restrict__ dkey, int tiles_x,
                            unsigned long long* __restrict__ keys, int32_t* __restrict__ vals) {
  const int g = blockIdx.x * blockDim.x + threadIdx.x;
  if (g >= N) return;
  const int n = counts[g];
  if (n == 0) return;
  int64_t o = offsets[g] - n;
  const int4 t = rect[g];
  const unsigned long long k = dkey[g];
  for (int ty = t.z; ty <= t.w; ++ty) {
    for (int tx = t.x; tx <= t.y; ++tx, ++o) {
      keys[o] = (static_cast<unsigned long long>(ty * tiles_x + tx) << 32) | k;
      vals[o] = g;
    }
  }
}

// ranges[t] = [first, end) of tile t's pairs in the sorted keys (zeros for tiles without any).
__global__ void ranges_kernel(int E, const unsigned long long* __restrict__ keys, int2* __restrict__ ranges) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= E) return;
  const int tile = int(keys[i] >> 32);
  if (i == 0) {
    ranges[tile].x = 0;
  } else {
    const int prev = int(keys[i - 1] >> 32);
    if (prev != tile) {
      ranges[prev].y = i;
      ranges[tile].x = i;
    }
  }
  if (i == E - 1) ranges[tile].y = E;
}

// The rule at one pixel centre (fx, fy): false when skipped (power > 0 or NaN, alpha < 1/255).
// dx, dy = mean - pixel centre; G = exp(power); raw = opacity G (alpha = min(0.99, raw)).
// Every operation rounded on its own (no fused multiply-add): same decisions as the other backends.
__device__ __forceinline__ bool eval_alpha(float2 m, float4 co, float fx, float fy, float& dx, float& dy,
                                           float& G, float& raw) {
  dx = __fsub_rn(m.x, fx);
  dy = __fsub_rn(m.y, fy);
  // power = -0.5 (a dx^2 + c dy^2) - b dx dy
  const float q = __fadd_rn(__fmul_rn(__fmul_rn(co.x, dx), dx), __fmul_rn(__fmul_rn(co.z, dy), dy));
  const float power = __fsub_rn(__fmul_rn(-0.5f, q), __fmul_rn(__fmul_rn(co.y, dx), dy));
  if (!(power <= 0.0f)) return false;
  G = expf(power);
  raw = __fmul_rn(co.w, G);
  return raw >= kAlphaMin;  // min(0.99, raw) >= 1/255; false for NaN
}

__device__ __forceinline__ bool in_box(int4 b, int px, int py) {
  return px >= b.x && px <= b.y && py >= b.z && py <= b.w;
}

__device__ __forceinline__ float warp_sum(float v) {
#pragma unroll
  for (int o = 16; o > 0; o >>= 1) v += __shfl_down_sync(kFullMask, v, o);
  return v;  // complete in lane 0
}

// Per-pixel channel vector: registers when the channel count NC is known at compile time, else
// a slice of global memory (g, C floats owned by the pixel).
template <int NC>
struct Chan {
  float r[NC > 0 ? NC : 1];
  float* g = nullptr;
  __device__ __forceinline__ float& operator[](int ch) {
    if constexpr (NC > 0) {
      return r[ch];
    } else {
      return g[ch];
    }
  }
};

template <int NC>  // NC > 0: channel count known at compile time (9: render()), 0: any (C_)
__global__ void __launch_bounds__(kBlock)
    forward_kernel(const int2* __restrict__ ranges, const int32_t* __restrict__ ids, int W, int H, int tiles_x,
                   const float2* __restrict__ xy, const float4* __restrict__ con_o, const int4* __restrict__ box,
                   const float* __restrict__ feat, const float* __restrict__ bg, const float* __restrict__ medf,
                   int C_, int M, float* __restrict__ out, float* __restrict__ alpha_out,
                   float* __restrict__ final_T, int32_t* __restrict__ n_contrib, int32_t* __restrict__ last,
                   int32_t* __restrict__ med_idx, float* __restrict__ median) {
  const int C = NC > 0 ? NC : C_;
  const int tile = blockIdx.x, tid = threadIdx.x;
  const int px = (tile % tiles_x) * kTile + tid % kTile, py = (tile / tiles_x) * kTile + tid / kTile;
  const bool inside = px < W && py < H;
  const int64_t p = int64_t(py) * W + px;
  const float fx = __fadd_rn(float(px), 0.5f), fy = __fadd_rn(float(py), 0.5f);
  const int2 range = ranges[tile];
  const int n = range.y - range.x;

  __shared__ int s_id[kBlock];
  __shared__ float2 s_xy[kBlock];
  __shared__ float4 s_co[kBlock];
  __shared__ int4 s_box[kBlock];

  Chan<NC> acc;
  if constexpr (NC == 0) acc.g = out + p * C;  // blended in place (background added at the end)
  if (NC > 0 || inside) {
#pragma unroll
    for (int ch = 0; ch < C; ++ch) acc[ch] = 0.0f;
  }
  float T = 1.0f;
  int ncon = 0, lastc = 0, med = -1;
  bool done = !inside;
  for (int b0 = 0; b0 < n; b0 += kBlock) {
    if (__syncthreads_count(done) == kBlock) break;  // also: the previous batch is consumed
    if (b0 + tid < n) {
      const int g = ids[range.x + b0 + tid];
      s_id[tid] = g;
      s_xy[tid] = xy[g];
      s_co[tid] = con_o[g];
      s_box[tid] = box[g];
    }
    __syncthreads();
    const int cnt = min(kBlock, n - b0);
    for (int j = 0; j < cnt && !done; ++j) {
      if (!in_box(s_box[j], px, py)) continue;
      float dx, dy, G, raw;
      if (!eval_alpha(s_xy[j], s_co[j], fx, fy, dx, dy, G, raw)) continue;
      const float al = fminf(raw, kAlphaMax);
      const float test_T = __fmul_rn(T, __fsub_rn(1.0f, al));
      if (test_T < kTMin) {  // this Gaussian is not included; the pixel stops
        done = true;
        continue;
      }
      const int g = s_id[j];
      const float w = __fmul_rn(al, T);
      const float* f = feat + int64_t(g) * C;
#pragma unroll
      for (int ch = 0; ch < C; ++ch) acc[ch] += __ldg(f + ch) * w;
      if (T > 0.5f && test_T <= 0.5f) med = g;
      T = test_T;
      ++ncon;
      lastc = b0 + j + 1;
    }
  }
  if (!inside) return;
#pragma unroll
  for (int ch = 0; ch < C; ++ch) {
    const float v = acc[ch] + T * bg[ch];
    out[p * C + ch] = v;
  }
  alpha_out[p] = 1.0f - T;
  final_T[p] = T;
  n_contrib[p] = ncon;
  last[p] = lastc;
  med_idx[p] = med;
  for (int m = 0; m < M; ++m) median[p * M + m] = med >= 0 ? medf[int64_t(med) * M + m] : 0.0f;
}

// Gradients of the forward rule, back to front per pixel (as composite_cpu.cpp backward_tiles):
//   dout/da_i = f_i T_i - (S_i + T_N bg) / (1 - a_i),  S_i = sum_{j>i} f_j a_j T_j
//   dalpha_out/da_i = T_N / (1 - a_i);  a_i = min(0.99, o_i exp(power_i))  (no gradient where clamped)
template <int NC>
__global__ void __launch_bounds__(kBlock)
    backward_kernel(const int2* __restrict__ ranges, const int32_t* __restrict__ ids, int W, int H, int tiles_x,
                    const float2* __restrict__ xy, const float4* __restrict__ con_o, const int4* __restrict__ box,
                    const float* __restrict__ feat, const float* __restrict__ bg, int C_, int M,
                    const float* __restrict__ final_T, const int32_t* __restrict__ last,
                    const int32_t* __restrict__ med_idx, const float* __restrict__ grad_out,
                    const float* __restrict__ grad_alpha, const float* __restrict__ grad_median,
                    float* __restrict__ scratch, float* __restrict__ d_means, float* __restrict__ d_conics,
                    float* __restrict__ d_opac, float* __restrict__ d_feat, float* __restrict__ d_medf) {
  const int C = NC > 0 ? NC : C_;
  const int tile = blockIdx.x, tid = threadIdx.x, lane = tid & 31;
  const int px = (tile % tiles_x) * kTile + tid % kTile, py = (tile / tiles_x) * kTile + tid / kTile;
  const bool inside = px < W && py < H;
  const int64_t p = int64_t(py) * W + px;
  const float fx = __fadd_rn(float(px), 0.5f), fy = __fadd_rn(float(py), 0.5f);
  const int2 range = ranges[tile];

  __shared__ int s_id[kBlock];
  __shared__ float2 s_xy[kBlock];
  __shared__ float4 s_co[kBlock];
  __shared__ int4 s_box[kBlock];
  __shared__ int s_maxlast;

  // per pixel: d out (gout), suffix sums S, T (recovered back to front), T_N (d alpha_out - bg . d out)
  Chan<NC> gout, S;
  if constexpr (NC == 0) {
    gout.g = const_cast<float*>(grad_out) + p * C;  // read only
    S.g = scratch + p * C;
  }
  float T = 1.0f, extra = 0.0f;
  int lastp = 0;
  if (inside) {
    T = final_T[p];
    lastp = last[p];
    float bg_dot = 0.0f;
#pragma unroll
    for (int ch = 0; ch < C; ++ch) {
      const float g = grad_out[p * C + ch];
      if constexpr (NC > 0) gout[ch] = g;
      S[ch] = 0.0f;
      bg_dot += bg[ch] * g;
    }
    extra = T * (grad_alpha[p] - bg_dot);
    // the median is a selection: its gradient goes to the chosen Gaussian's median_features only
    const int mi = med_idx[p];
    if (mi >= 0)
      for (int m = 0; m < M; ++m) atomicAdd(d_medf + int64_t(mi) * M + m, grad_median[p * M + m]);
  } else if constexpr (NC > 0) {
#pragma unroll
    for (int ch = 0; ch < NC; ++ch) gout[ch] = S[ch] = 0.0f;
  }
  if (tid == 0) s_maxlast = 0;
  __syncthreads();
  if (lastp > 0) atomicMax(&s_maxlast, lastp);
  __syncthreads();
  const int n = s_maxlast;  // list positions [0, n) were blended by some pixel of the tile

  for (int b0 = 0; b0 < n; b0 += kBlock) {
    __syncthreads();  // the previous batch is consumed
    const int k = n - 1 - b0 - tid;  // this thread stages list position k
    if (k >= 0) {
      const int g = ids[range.x + k];
      s_id[tid] = g;
      s_xy[tid] = xy[g];
      s_co[tid] = con_o[g];
      s_box[tid] = box[g];
    }
    __syncthreads();
    const int cnt = min(kBlock, n - b0);
    for (int j = 0; j < cnt; ++j) {
      const int q = n - 1 - b0 - j;  // list position
      const float4 co = s_co[j];
      float dx = 0.0f, dy = 0.0f, G = 0.0f, raw = 0.0f;
      bool valid = inside && q < lastp && in_box(s_box[j], px, py);
      if (valid) valid = eval_alpha(s_xy[j], co, fx, fy, dx, dy, G, raw);
      if (!__any_sync(kFullMask, valid)) continue;  // warp-uniform
      const int g = s_id[j];
      const float* f = feat + int64_t(g) * C;
      float w = 0.0f, dmx = 0.0f, dmy = 0.0f, da = 0.0f, db = 0.0f, dc = 0.0f, dop = 0.0f;
      if (valid) {
        const float al = fminf(raw, kAlphaMax);
        const float inv = 1.0f / (1.0f - al);
        const float Ti = T * inv;  // transmittance in front of this Gaussian
        w = al * Ti;
        float gf = 0.0f, gs = 0.0f;  // d out . f and d out . S
#pragma unroll
        for (int ch = 0; ch < C; ++ch) {
          const float fc = __ldg(f + ch), gc = gout[ch];
          gf += gc * fc;
          gs += gc * S[ch];
          S[ch] += fc * w;
        }
        const float dL_da = Ti * gf + inv * (extra - gs);
        T = Ti;
        if (raw <= kAlphaMax) {  // clamped: no gradient to opacity or power
          const float gda = G * dL_da;
          dop = gda;
          const float dpow = co.w * gda;
          dmx = dpow * (-co.x * dx - co.y * dy);
          dmy = dpow * (-co.z * dy - co.y * dx);
          da = -0.5f * dpow * dx * dx;
          db = -dpow * dx * dy;
          dc = -0.5f * dpow * dy * dy;
        }
      }
      dmx = warp_sum(dmx);
      dmy = warp_sum(dmy);
      da = warp_sum(da);
      db = warp_sum(db);
      dc = warp_sum(dc);
      dop = warp_sum(dop);
      if (lane == 0) {
        atomicAdd(d_means + 2 * int64_t(g), dmx);
        atomicAdd(d_means + 2 * int64_t(g) + 1, dmy);
        atomicAdd(d_conics + 3 * int64_t(g), da);
        atomicAdd(d_conics + 3 * int64_t(g) + 1, db);
        atomicAdd(d_conics + 3 * int64_t(g) + 2, dc);
        atomicAdd(d_opac + g, dop);
      }
#pragma unroll
      for (int ch = 0; ch < C; ++ch) {
        const float v = warp_sum(valid ? w * gout[ch] : 0.0f);
        if (lane == 0) atomicAdd(d_feat + int64_t(g) * C + ch, v);
      }
    }
  }
}

void check_tensor(const torch::Tensor& t, const char* name, at::ScalarType dtype) {
  TORCH_CHECK(t.is_cuda(), "composite_cuda: ", name, " must be a CUDA tensor");
  TORCH_CHECK(t.is_contiguous(), "composite_cuda: ", name, " must be contiguous");
  TORCH_CHECK(t.scalar_type() == dtype, "composite_cuda: ", name, " must be ", dtype, ", got ",
              t.scalar_type());
}

int blocks_for(int64_t n, int threads) { return int((n + threads - 1) / threads); }

}  // namespace

std::vector<torch::Tensor> composite_cuda_forward(torch::Tensor means2d, torch::Tensor conics,
                                                  torch::Tensor opacities, torch::Tensor features,
                                                  torch::Tensor depths, torch::Tensor radii,
                                                  torch::Tensor background,
                                                  torch::Tensor median_features, int64_t W, int64_t H) {
  const auto f32 = at::kFloat;
  check_tensor(means2d, "means2d", f32);
  check_tensor(conics, "conics", f32);
  check_tensor(opacities, "opacities", f32);
  check_tensor(features, "features", f32);
  check_tensor(depths, "depths", f32);
  check_tensor(radii, "radii", at::kInt);
  check_tensor(background, "background", f32);
  check_tensor(median_features, "median_features", f32);
  TORCH_CHECK(W > 0 && H > 0 && W * H < INT_MAX, "composite_cuda: bad image size ", W, "x", H);
  const c10::cuda::OptionalCUDAGuard guard(device_of(features));
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  const int64_t N = features.size(0), C = features.size(1), M = median_features.size(1);
  TORCH_CHECK(N < INT_MAX, "composite_cuda: too many Gaussians: ", N);
  const int tiles_x = int((W + kTile - 1) / kTile), tiles_y = int((H + kTile - 1) / kTile);
  const int n_tiles = tiles_x * tiles_y;
  auto fopts = features.options();
  auto iopts = fopts.dtype(at::kInt);

  torch::Tensor xy = torch::empty({N, 2}, fopts), con_o = torch::empty({N, 4}, fopts);
  torch::Tensor box = torch::empty({N, 4}, iopts), rect = torch::empty({N, 4}, iopts);
  torch::Tensor counts = torch::empty({N}, iopts), dkey = torch::empty({N}, iopts);
  constexpr int kThreads = 256;
  int64_t E = 0;
  torch::Tensor offsets;
  if (N > 0) {
    prepare_kernel<<<blocks_for(N, kThreads), kThreads, 0, stream>>>(
        int(N), means2d.data_ptr<float>(), conics.data_ptr<float>(), opacities.data_ptr<float>(),
        depths.data_ptr<float>(), radii.data_ptr<int32_t>(), int(W), int(H),
        reinterpret_cast<float2*>(xy.data_ptr<float>()), reinterpret_cast<float4*>(con_o.data_ptr<float>()),
        reinterpret_cast<int4*>(box.data_ptr<int32_t>()), reinterpret_cast<int4*>(rect.data_ptr<int32_t>()),
        counts.data_ptr<int32_t>(), reinterpret_cast<uint32_t*>(dkey.data_ptr<int32_t>()));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    offsets = torch::cumsum(counts, 0, at::kLong);
    E = offsets[N - 1].item<int64_t>();  // one device-to-host copy per call (as 3DGS)
  }
  TORCH_CHECK(E < INT_MAX, "composite_cuda: too many (tile, Gaussian) pairs: ", E);
  torch::Tensor ranges = torch::zeros({n_tiles, 2}, iopts);
  torch::Tensor ids = torch::empty({E}, iopts);
  if (E > 0) {
    torch::Tensor keys = torch::empty({E}, fopts.dtype(at::kLong)), keys_sorted = torch::empty_like(keys);
    torch::Tensor vals = torch::empty({E}, iopts);
    emit_kernel<<<blocks_for(N, kThreads), kThreads, 0, stream>>>(
        int(N), offsets.data_ptr<int64_t>(), counts.data_ptr<int32_t>(),
        reinterpret_cast<const int4*>(rect.data_ptr<int32_t>()),
        reinterpret_cast<const uint32_t*>(dkey.data_ptr<int32_t>()), tiles_x,
        reinterpret_cast<unsigned long long*>(keys.data_ptr<int64_t>()), vals.data_ptr<int32_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
    int tile_bits = 0;
    while ((int64_t(n_tiles) - 1) >> tile_bits) ++tile_bits;
    auto* k_in = reinterpret_cast<unsigned long long*>(keys.data_ptr<int64_t>());
    auto* k_out = reinterpret_cast<unsigned long long*>(keys_sorted.data_ptr<int64_t>());
    size_t temp_bytes = 0;
    // LSD radix sort: stable, so equal keys (same tile and depth) keep the index order
    C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(nullptr, temp_bytes, k_in, k_out, vals.data_ptr<int32_t>(),
                                                   ids.data_ptr<int32_t>(), int(E), 0, 32 + tile_bits, stream));
    torch::Tensor temp = torch::empty({int64_t(temp_bytes)}, fopts.dtype(at::kByte));
    C10_CUDA_CHECK(cub::DeviceRadixSort::SortPairs(temp.data_ptr(), temp_bytes, k_in, k_out,
                                                   vals.data_ptr<int32_t>(), ids.data_ptr<int32_t>(), int(E),
                                                   0, 32 + tile_bits, stream));
    ranges_kernel<<<blocks_for(E, kThreads), kThreads, 0, stream>>>(int(E), k_out,
                                                                     reinterpret_cast<int2*>(ranges.data_ptr<int32_t>()));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }

  torch::Tensor out = torch::empty({H, W, C}, fopts), alpha = torch::empty({H, W}, fopts);
  torch::Tensor median = torch::empty({H, W, M}, fopts), n_contrib = torch::empty({H, W}, iopts);
  torch::Tensor final_T = torch::empty({H, W}, fopts), last = torch::empty({H, W}, iopts);
  torch::Tensor med_idx = torch::empty({H, W}, iopts);
  auto launch = [&](auto kernel) {
    kernel<<<n_tiles, kBlock, 0, stream>>>(
        reinterpret_cast<const int2*>(ranges.data_ptr<int32_t>()), ids.data_ptr<int32_t>(), int(W), int(H),
        tiles_x, reinterpret_cast<const float2*>(xy.data_ptr<float>()),
        reinterpret_cast<const float4*>(con_o.data_ptr<float>()),
        reinterpret_cast<const int4*>(box.data_ptr<int32_t>()), features.data_ptr<float>(),
        background.data_ptr<float>(), median_features.data_ptr<float>(), int(C), int(M), out.data_ptr<float>(),
        alpha.data_ptr<float>(), final_T.data_ptr<float>(), n_contrib.data_ptr<int32_t>(),
        last.data_ptr<int32_t>(), med_idx.data_ptr<int32_t>(), median.data_ptr<float>());
  };
  if (C == 9)  // render(): RGB, depth plane (3), normal (3)
    launch(forward_kernel<9>);
  else
    launch(forward_kernel<0>);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {out, alpha, median, n_contrib, final_T, last, med_idx, ranges, ids, xy, con_o, box};
}

std::vector<torch::Tensor> composite_cuda_backward(
    torch::Tensor grad_out, torch::Tensor grad_alpha, torch::Tensor grad_median,
    torch::Tensor features, torch::Tensor background, torch::Tensor median_features,
    torch::Tensor final_T, torch::Tensor last, torch::Tensor median_idx, torch::Tensor tile_ranges,
    torch::Tensor ids, torch::Tensor xy, torch::Tensor con_o, torch::Tensor box, int64_t W,
    int64_t H) {
  const auto f32 = at::kFloat;
  check_tensor(grad_out, "grad_out", f32);
  check_tensor(grad_alpha, "grad_alpha", f32);
  check_tensor(grad_median, "grad_median", f32);
  check_tensor(features, "features", f32);
  check_tensor(background, "background", f32);
  check_tensor(median_features, "median_features", f32);
  check_tensor(final_T, "final_T", f32);
  const c10::cuda::OptionalCUDAGuard guard(device_of(features));
  cudaStream_t stream = c10::cuda::getCurrentCUDAStream();
  const int64_t N = features.size(0), C = features.size(1), M = median_features.size(1);
  const int tiles_x = int((W + kTile - 1) / kTile);
  const int n_tiles = int(tile_ranges.size(0));
  auto fopts = features.options();
  torch::Tensor d_means = torch::zeros({N, 2}, fopts), d_conics = torch::zeros({N, 3}, fopts);
  torch::Tensor d_opac = torch::zeros({N}, fopts), d_feat = torch::zeros({N, C}, fopts);
  torch::Tensor d_medf = torch::zeros({N, M}, fopts);
  // per-pixel suffix sums S of the generic-C kernel (the C = 9 kernel keeps them in registers)
  torch::Tensor scratch = torch::empty({C == 9 ? 0 : H * W * C}, fopts);
  auto launch = [&](auto kernel) {
    kernel<<<n_tiles, kBlock, 0, stream>>>(
        reinterpret_cast<const int2*>(tile_ranges.data_ptr<int32_t>()), ids.data_ptr<int32_t>(), int(W), int(H),
        tiles_x, reinterpret_cast<const float2*>(xy.data_ptr<float>()),
        reinterpret_cast<const float4*>(con_o.data_ptr<float>()),
        reinterpret_cast<const int4*>(box.data_ptr<int32_t>()), features.data_ptr<float>(),
        background.data_ptr<float>(), int(C), int(M), final_T.data_ptr<float>(), last.data_ptr<int32_t>(),
        median_idx.data_ptr<int32_t>(), grad_out.data_ptr<float>(), grad_alpha.data_ptr<float>(),
        grad_median.data_ptr<float>(), scratch.data_ptr<float>(), d_means.data_ptr<float>(),
        d_conics.data_ptr<float>(), d_opac.data_ptr<float>(), d_feat.data_ptr<float>(), d_medf.data_ptr<float>());
  };
  if (C == 9)
    launch(backward_kernel<9>);
  else
    launch(backward_kernel<0>);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  torch::Tensor d_bg = (final_T.unsqueeze(-1) * grad_out).view({H * W, C}).sum(0);  // [C]
  return {d_means, d_conics, d_opac, d_feat, d_bg, d_medf};
}
