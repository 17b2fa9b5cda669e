// Fused loss terms of the training step on a CUDA GPU (the Python side is splat/losses_cuda.py), the
// same math as losses_cpu.cpp (read its header for the formulas):
//
// 1. L_rgb = (1 - lambda) L1 + lambda (1 - SSIM) of an [H, W, C] image against a reference (11x11
//    separable Gaussian window, zero padding, as 3DGS). Forward: a vertical pass that blurs the five
//    moment inputs (x, y, x^2, y^2, xy) of each pixel, then a horizontal pass that finishes the
//    moments, evaluates S and its three partial-derivative maps and reduces S and |x - y| per block
//    into two float64 accumulators (no host synchronisation: the loss stays on the device). Backward:
//    the three maps blurred the same two ways (the window is symmetric and zero-padded, so the blur is
//    its own adjoint), combined with the L1 sign.
// 2. L_nc, the depth-normal consistency: one thread per pixel forward (per-block sums of the term and
//    of the used pixels), and a backward that writes each pixel's gradients of its central differences
//    and then gathers them from the four neighbours (no scatter, no atomics).
// 3. L_n, the normal-prior L1.
// Every kernel reads the upstream gradient and the pixel count from device memory, so a training
// step launches them without waiting for the GPU. float32 and float64 (the tests' oracle precision).

#include <torch/extension.h>

#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <cub/block/block_reduce.cuh>

namespace losses_cuda {

constexpr int kThreads = 256;
constexpr int kMaxTaps = 31;
constexpr double kNorm2Eps = 1e-20;

template <typename T>
struct Window {
  T w[kMaxTaps];
  int K;
};

template <typename T>
Window<T> make_window(const torch::Tensor& g) {
  auto gd = g.detach().to(torch::kCPU, torch::kFloat64).contiguous();
  TORCH_CHECK(gd.dim() == 1 && gd.numel() % 2 == 1 && gd.numel() <= kMaxTaps,
              "losses_cuda: the SSIM window must be 1-D with an odd length <= ", kMaxTaps);
  Window<T> win{};
  win.K = static_cast<int>(gd.numel());
  const double* p = gd.data_ptr<double>();
  for (int k = 0; k < win.K; ++k) win.w[k] = static_cast<T>(p[k]);
  return win;
}

inline int blocks_for(int64_t n) { return static_cast<int>((n + kThreads - 1) / kThreads); }

template <typename T>
__device__ inline T abs_of(T v) {
  return v < T(0) ? -v : v;
}

// Adds a and b of every thread of the block into acc[0] and acc[1] (one atomicAdd each per block).
__device__ inline void block_add2(double a, double b, double* acc) {
  using Reduce = cub::BlockReduce<double, kThreads>;
  __shared__ typename Reduce::TempStorage tmp;
  const double sa = Reduce(tmp).Sum(a);
  __syncthreads();
  const double sb = Reduce(tmp).Sum(b);
  if (threadIdx.x == 0) {
    atomicAdd(acc, sa);
    atomicAdd(acc + 1, sb);
  }
}

// ---- 1. L_rgb ----------------------------------------------------------------------------------

// Vertical pass of the forward: v[q][i, e] = sum_k g[k] f_q(x, y)[i + k - r, e] (e over W * C).
template <typename T>
__global__ void rgb_vertical(const T* __restrict__ x, const T* __restrict__ y, Window<T> g, int H, int WC,
                             T* __restrict__ v) {
  const int64_t n = static_cast<int64_t>(H) * WC;
  const int64_t idx = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (idx >= n) return;
  const int i = static_cast<int>(idx / WC), e = static_cast<int>(idx % WC), r = g.K / 2;
  T s0 = 0, s1 = 0, s2 = 0, s3 = 0, s4 = 0;
  for (int k = 0; k < g.K; ++k) {
    const int ii = i + k - r;
    if (ii < 0 || ii >= H) continue;
    const T a = x[static_cast<int64_t>(ii) * WC + e], b = y[static_cast<int64_t>(ii) * WC + e], w = g.w[k];
    s0 += w * a, s1 += w * b, s2 += w * (a * a), s3 += w * (b * b), s4 += w * (a * b);
  }
  v[idx] = s0, v[n + idx] = s1, v[2 * n + idx] = s2, v[3 * n + idx] = s3, v[4 * n + idx] = s4;
}

// Horizontal pass: the five moments, S, the partial derivatives of S / n, and the block sums of S and
// |x - y| added into acc[0], acc[1].
template <typename T>
__global__ void rgb_horizontal(const T* __restrict__ v, const T* __restrict__ x, const T* __restrict__ y,
                               Window<T> g, int H, int W, int C, T c1, T c2, T* __restrict__ d_mx,
                               T* __restrict__ d_xx, T* __restrict__ d_xy, double* __restrict__ acc) {
  const int64_t n = static_cast<int64_t>(H) * W * C;
  const int64_t idx = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  double s_sum = 0.0, l1_sum = 0.0;
  if (idx < n) {
    const int64_t WC = static_cast<int64_t>(W) * C;
    const int64_t row = (idx / WC) * WC;
    const int e = static_cast<int>(idx % WC), j = e / C, c = e % C, r = g.K / 2;
    T m[5] = {0, 0, 0, 0, 0};
    for (int k = 0; k < g.K; ++k) {
      const int jj = j + k - r;
      if (jj < 0 || jj >= W) continue;
      const int64_t src = row + static_cast<int64_t>(jj) * C + c;
      const T w = g.w[k];
#pragma unroll
      for (int q = 0; q < 5; ++q) m[q] += w * v[q * n + src];
    }
    const T inv_n = T(1) / static_cast<T>(n);
    const T mx = m[0], my = m[1];
    const T a1 = T(2) * mx * my + c1, a2 = T(2) * (m[4] - mx * my) + c2;
    const T b1 = mx * mx + my * my + c1, b2 = (m[2] - mx * mx) + (m[3] - my * my) + c2;
    const T den = b1 * b2, s = a1 * a2 / den;
    d_mx[idx] = inv_n * (T(2) * my * (a2 - a1) - T(2) * mx * s * (b2 - b1)) / den;
    d_xx[idx] = -inv_n * s / b2;
    d_xy[idx] = inv_n * T(2) * a1 / den;
    s_sum = static_cast<double>(s);
    l1_sum = static_cast<double>(abs_of(x[idx] - y[idx]));
  }
  block_add2(s_sum, l1_sum, acc);
}

// out = (1 - lambda) mean |x - y| + lambda (1 - mean S).
template <typename T>
__global__ void rgb_finish(const double* __restrict__ acc, double inv_n, double lambda, T* __restrict__ out) {
  out[0] = static_cast<T>((1.0 - lambda) * acc[1] * inv_n + lambda * (1.0 - acc[0] * inv_n));
}

// Vertical pass of the backward: the three derivative maps blurred down the columns.
template <typename T>
__global__ void blur3_vertical(const T* __restrict__ a, const T* __restrict__ b, const T* __restrict__ c,
                               Window<T> g, int H, int WC, T* __restrict__ v) {
  const int64_t n = static_cast<int64_t>(H) * WC;
  const int64_t idx = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (idx >= n) return;
  const int i = static_cast<int>(idx / WC), e = static_cast<int>(idx % WC), r = g.K / 2;
  T s0 = 0, s1 = 0, s2 = 0;
  for (int k = 0; k < g.K; ++k) {
    const int ii = i + k - r;
    if (ii < 0 || ii >= H) continue;
    const int64_t src = static_cast<int64_t>(ii) * WC + e;
    const T w = g.w[k];
    s0 += w * a[src], s1 += w * b[src], s2 += w * c[src];
  }
  v[idx] = s0, v[n + idx] = s1, v[2 * n + idx] = s2;
}

// dL/dx = grad [(1 - lambda) sign(x - y) / n - lambda (blur(dmx) + 2 x blur(dExx) + y blur(dExy))].
template <typename T>
__global__ void rgb_backward_horizontal(const T* __restrict__ v, const T* __restrict__ x, const T* __restrict__ y,
                                        const T* __restrict__ grad, Window<T> g, int H, int W, int C, T lambda,
                                        T* __restrict__ out) {
  const int64_t n = static_cast<int64_t>(H) * W * C;
  const int64_t idx = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (idx >= n) return;
  const int64_t WC = static_cast<int64_t>(W) * C;
  const int64_t row = (idx / WC) * WC;
  const int e = static_cast<int>(idx % WC), j = e / C, c = e % C, r = g.K / 2;
  T b0 = 0, b1 = 0, b2 = 0;
  for (int k = 0; k < g.K; ++k) {
    const int jj = j + k - r;
    if (jj < 0 || jj >= W) continue;
    const int64_t src = row + static_cast<int64_t>(jj) * C + c;
    const T w = g.w[k];
    b0 += w * v[src], b1 += w * v[n + src], b2 += w * v[2 * n + src];
  }
  const T xv = x[idx], yv = y[idx], d = xv - yv;
  const T sgn = d > T(0) ? T(1) : (d < T(0) ? T(-1) : T(0));
  const T inv_n = T(1) / static_cast<T>(n);
  out[idx] = grad[0] * ((T(1) - lambda) * sgn * inv_n - lambda * (b0 + T(2) * xv * b1 + yv * b2));
}

// ---- 2. L_nc -----------------------------------------------------------------------------------

template <typename T>
struct NcGeom {
  const T* d;
  int H, W;
  T fx, fy, cx, cy;
  __device__ void ray(int i, int j, T* r) const {
    r[0] = (T(j) + T(0.5) - cx) / fx, r[1] = (T(i) + T(0.5) - cy) / fy, r[2] = T(1);
  }
  __device__ void point(int i, int j, T* P) const {
    T r[3];
    ray(i, j, r);
    const T z = d[static_cast<int64_t>(i) * W + j];
    P[0] = r[0] * z, P[1] = r[1] * z, P[2] = z;
  }
  // n (unnormalised, flipped to face the camera), dx, dy at interior pixel (i, j); false if undefined.
  __device__ bool normal(int i, int j, T* n, T* dx, T* dy, T& sign) const {
    const T* z = d + static_cast<int64_t>(i) * W + j;
    if (!(z[0] > 0 && z[1] > 0 && z[-1] > 0 && z[W] > 0 && z[-W] > 0)) return false;
    T a[3], b[3], c[3], e[3], P[3];
    point(i, j + 1, a), point(i, j - 1, b), point(i + 1, j, c), point(i - 1, j, e), point(i, j, P);
    for (int k = 0; k < 3; ++k) dx[k] = a[k] - b[k], dy[k] = c[k] - e[k];
    n[0] = dx[1] * dy[2] - dx[2] * dy[1];
    n[1] = dx[2] * dy[0] - dx[0] * dy[2];
    n[2] = dx[0] * dy[1] - dx[1] * dy[0];
    sign = (n[0] * P[0] + n[1] * P[1] + n[2] * P[2]) > 0 ? T(-1) : T(1);
    return n[0] * n[0] + n[1] * n[1] + n[2] * n[2] > T(kNorm2Eps);
  }
  // Whether pixel (i, j) counts: interior, valid, rendered normal N != 0, depth normal defined.
  __device__ bool used(const T* N, const bool* valid, int i, int j, T* n, T* dx, T* dy, T& sign) const {
    if (i < 1 || j < 1 || i >= H - 1 || j >= W - 1) return false;
    const int64_t p = static_cast<int64_t>(i) * W + j;
    if (!valid[p] || (N[3 * p] == 0 && N[3 * p + 1] == 0 && N[3 * p + 2] == 0)) return false;
    return normal(i, j, n, dx, dy, sign);
  }
};

// The geometry of a depth map d [H, W] under intrinsics K (a 3x3 device tensor, read by every thread).
template <typename T>
__device__ inline NcGeom<T> geom_of(const T* d, const T* K, int H, int W) {
  return NcGeom<T>{d, H, W, K[0], K[4], K[2], K[5]};
}

template <typename T>
__global__ void nc_forward_kernel(const T* __restrict__ d, const T* __restrict__ K, int H, int W,
                                  const T* __restrict__ N, const bool* __restrict__ valid, double* __restrict__ acc) {
  const NcGeom<T> g = geom_of(d, K, H, W);
  const int64_t idx = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  double term = 0.0, used = 0.0;
  if (idx < static_cast<int64_t>(g.H) * g.W) {
    const int i = static_cast<int>(idx / g.W), j = static_cast<int>(idx % g.W);
    T n[3], dx[3], dy[3], s;
    if (g.used(N, valid, i, j, n, dx, dy, s)) {
      const T inv = s / sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
      const T* Np = N + 3 * idx;
      term = static_cast<double>(T(1) - (Np[0] * n[0] * inv + Np[1] * n[1] * inv + Np[2] * n[2] * inv));
      used = 1.0;
    }
  }
  block_add2(term, used, acc);
}

// out = acc[0] / acc[1] (0 when no pixel counts).
template <typename T>
__global__ void masked_mean_finish(const double* __restrict__ acc, T* __restrict__ out) {
  out[0] = acc[1] > 0 ? static_cast<T>(acc[0] / acc[1]) : T(0);
}

// Per used pixel: dL/dN, and (unless detach_depth) dL/d(dx), dL/d(dy) into gdx, gdy (zero elsewhere).
template <typename T>
__global__ void nc_backward_pixels(const T* __restrict__ d, const T* __restrict__ K, int H, int W,
                                   const T* __restrict__ N, const bool* __restrict__ valid,
                                   const T* __restrict__ grad, const double* __restrict__ acc, bool detach_depth,
                                   T* __restrict__ oN, T* __restrict__ gdx, T* __restrict__ gdy) {
  const NcGeom<T> g = geom_of(d, K, H, W);
  const int64_t idx = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (idx >= static_cast<int64_t>(g.H) * g.W || !(acc[1] > 0)) return;
  const int i = static_cast<int>(idx / g.W), j = static_cast<int>(idx % g.W);
  T n[3], dx[3], dy[3], s;
  if (!g.used(N, valid, i, j, n, dx, dy, s)) return;
  const T c = grad[0] / static_cast<T>(acc[1]);
  const T len = sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
  const T u[3] = {n[0] / len, n[1] / len, n[2] / len};
  for (int k = 0; k < 3; ++k) oN[3 * idx + k] = -c * s * u[k];  // dL/dN = -N_d / count
  if (detach_depth) return;
  const T G[3] = {-c * N[3 * idx], -c * N[3 * idx + 1], -c * N[3 * idx + 2]};  // dL/dN_d
  const T uG = u[0] * G[0] + u[1] * G[1] + u[2] * G[2];
  T gn[3];
  for (int k = 0; k < 3; ++k) gn[k] = s * (G[k] - u[k] * uG) / len;
  T* ax = gdx + 3 * idx;  // dL/ddx = dy x gn; dL/ddy = gn x dx
  T* ay = gdy + 3 * idx;
  ax[0] = dy[1] * gn[2] - dy[2] * gn[1], ax[1] = dy[2] * gn[0] - dy[0] * gn[2], ax[2] = dy[0] * gn[1] - dy[1] * gn[0];
  ay[0] = gn[1] * dx[2] - gn[2] * dx[1], ay[1] = gn[2] * dx[0] - gn[0] * dx[2], ay[2] = gn[0] * dx[1] - gn[1] * dx[0];
}

// dL/dd per pixel: dx of (i, j-1) and (i, j+1), dy of (i-1, j) and (i+1, j) gathered, along the ray.
template <typename T>
__global__ void nc_backward_gather(const T* __restrict__ d, const T* __restrict__ K, int H, int W,
                                   const T* __restrict__ gdx, const T* __restrict__ gdy, T* __restrict__ oD) {
  const NcGeom<T> g = geom_of(d, K, H, W);
  const int64_t idx = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (idx >= static_cast<int64_t>(g.H) * g.W) return;
  const int i = static_cast<int>(idx / W), j = static_cast<int>(idx % W);
  T gP[3] = {0, 0, 0};
  for (int k = 0; k < 3; ++k) {
    if (j > 0) gP[k] += gdx[3 * (idx - 1) + k];
    if (j < W - 1) gP[k] -= gdx[3 * (idx + 1) + k];
    if (i > 0) gP[k] += gdy[3 * (idx - W) + k];
    if (i < g.H - 1) gP[k] -= gdy[3 * (idx + W) + k];
  }
  T r[3];
  g.ray(i, j, r);
  oD[idx] = r[0] * gP[0] + r[1] * gP[1] + r[2] * gP[2];
}

// ---- 3. L_n ------------------------------------------------------------------------------------

template <typename T>
__device__ inline bool np_used(const T* N, const T* P, const bool* ok, int64_t p) {
  const T* n = N + 3 * p;
  const T* q = P + 3 * p;
  return ok[p] && (n[0] != 0 || n[1] != 0 || n[2] != 0) && (q[0] != 0 || q[1] != 0 || q[2] != 0) &&
         isfinite(q[0]) && isfinite(q[1]) && isfinite(q[2]);
}

template <typename T>
__global__ void np_forward_kernel(const T* __restrict__ N, const T* __restrict__ P, const bool* __restrict__ ok,
                                  int64_t n_pix, double* __restrict__ acc) {
  const int64_t p = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  double term = 0.0, used = 0.0;
  if (p < n_pix && np_used(N, P, ok, p)) {
    term = static_cast<double>(abs_of(N[3 * p] - P[3 * p]) + abs_of(N[3 * p + 1] - P[3 * p + 1]) +
                               abs_of(N[3 * p + 2] - P[3 * p + 2]));
    used = 1.0;
  }
  block_add2(term, used, acc);
}

template <typename T>
__global__ void np_backward_kernel(const T* __restrict__ N, const T* __restrict__ P, const bool* __restrict__ ok,
                                   int64_t n_pix, const T* __restrict__ grad, const double* __restrict__ acc,
                                   T* __restrict__ out) {
  const int64_t p = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (p >= n_pix || !(acc[1] > 0) || !np_used(N, P, ok, p)) return;
  const T c = grad[0] / static_cast<T>(acc[1]);
  for (int k = 0; k < 3; ++k) {
    const T e = N[3 * p + k] - P[3 * p + k];
    out[3 * p + k] = e > 0 ? c : (e < 0 ? -c : T(0));
  }
}

void check_tensors(std::initializer_list<torch::Tensor> ts, const char* what) {
  const auto dev = ts.begin()->device();
  for (const auto& t : ts) {
    TORCH_CHECK(t.is_cuda() && t.device() == dev && t.is_contiguous(), "losses_cuda (", what,
                "): contiguous tensors on one CUDA device expected");
  }
}

void check_floats(const torch::Tensor& a, const torch::Tensor& b, const char* what) {
  TORCH_CHECK(a.scalar_type() == b.scalar_type() &&
                  (a.scalar_type() == torch::kFloat32 || a.scalar_type() == torch::kFloat64),
              "losses_cuda (", what, "): float32 or float64 tensors of one dtype expected");
}

}  // namespace losses_cuda

// Returns {L_rgb (0-dim), dmx, dExx, dExy} (the last three [H, W, C], for rgb_loss_backward).
std::vector<torch::Tensor> rgb_loss_forward(torch::Tensor x, torch::Tensor y, torch::Tensor g, double C1,
                                            double C2, double lambda) {
  using namespace losses_cuda;
  check_tensors({x, y}, "rgb");
  check_floats(x, y, "rgb");
  TORCH_CHECK(x.dim() == 3 && x.sizes() == y.sizes(), "losses_cuda: image and reference must be [H, W, C] alike");
  const c10::cuda::CUDAGuard guard(x.device());
  const int H = static_cast<int>(x.size(0)), W = static_cast<int>(x.size(1)), C = static_cast<int>(x.size(2));
  const int64_t n = x.numel();
  torch::Tensor d_mx = torch::empty_like(x), d_xx = torch::empty_like(x), d_xy = torch::empty_like(x);
  torch::Tensor v = torch::empty({5, n}, x.options());
  torch::Tensor acc = torch::zeros({2}, x.options().dtype(torch::kFloat64));
  torch::Tensor out = torch::empty({}, x.options());
  if (n == 0) return {out.fill_(0), d_mx, d_xx, d_xy};
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "rgb_loss_forward", [&] {
    const Window<scalar_t> win = make_window<scalar_t>(g);
    rgb_vertical<scalar_t><<<blocks_for(n), kThreads, 0, stream>>>(x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(),
                                                                   win, H, W * C, v.data_ptr<scalar_t>());
    rgb_horizontal<scalar_t><<<blocks_for(n), kThreads, 0, stream>>>(
        v.data_ptr<scalar_t>(), x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), win, H, W, C,
        static_cast<scalar_t>(C1), static_cast<scalar_t>(C2), d_mx.data_ptr<scalar_t>(), d_xx.data_ptr<scalar_t>(),
        d_xy.data_ptr<scalar_t>(), acc.data_ptr<double>());
    rgb_finish<scalar_t><<<1, 1, 0, stream>>>(acc.data_ptr<double>(), 1.0 / static_cast<double>(n), lambda,
                                              out.data_ptr<scalar_t>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {out, d_mx, d_xx, d_xy};
}

// dL/dx for L = grad (a 0-dim device tensor of x's dtype) * L_rgb.
torch::Tensor rgb_loss_backward(torch::Tensor grad, torch::Tensor x, torch::Tensor y, torch::Tensor d_mx,
                                torch::Tensor d_xx, torch::Tensor d_xy, torch::Tensor g, double lambda) {
  using namespace losses_cuda;
  check_tensors({grad, x, y, d_mx, d_xx, d_xy}, "rgb backward");
  check_floats(x, grad, "rgb backward");
  const c10::cuda::CUDAGuard guard(x.device());
  const int H = static_cast<int>(x.size(0)), W = static_cast<int>(x.size(1)), C = static_cast<int>(x.size(2));
  const int64_t n = x.numel();
  torch::Tensor out = torch::empty_like(x);
  if (n == 0) return out;
  torch::Tensor v = torch::empty({3, n}, x.options());
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "rgb_loss_backward", [&] {
    const Window<scalar_t> win = make_window<scalar_t>(g);
    blur3_vertical<scalar_t><<<blocks_for(n), kThreads, 0, stream>>>(
        d_mx.data_ptr<scalar_t>(), d_xx.data_ptr<scalar_t>(), d_xy.data_ptr<scalar_t>(), win, H, W * C,
        v.data_ptr<scalar_t>());
    rgb_backward_horizontal<scalar_t><<<blocks_for(n), kThreads, 0, stream>>>(
        v.data_ptr<scalar_t>(), x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), grad.data_ptr<scalar_t>(), win, H,
        W, C, static_cast<scalar_t>(lambda), out.data_ptr<scalar_t>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}

// K: the 3x3 intrinsics, a device tensor of depth's dtype. Returns {L_nc (0-dim), acc (float64 [2]: the sum of the terms and the count of used pixels)}.
std::vector<torch::Tensor> nc_loss_forward(torch::Tensor normal, torch::Tensor depth, torch::Tensor valid,
                                           torch::Tensor K) {
  using namespace losses_cuda;
  check_tensors({normal, depth, valid, K}, "nc");
  check_floats(normal, depth, "nc");
  check_floats(K, depth, "nc");
  TORCH_CHECK(K.numel() == 9, "losses_cuda (nc): K must be 3x3");
  TORCH_CHECK(valid.scalar_type() == torch::kBool, "losses_cuda (nc): valid must be bool");
  const c10::cuda::CUDAGuard guard(depth.device());
  const int H = static_cast<int>(depth.size(0)), W = static_cast<int>(depth.size(1));
  torch::Tensor acc = torch::zeros({2}, depth.options().dtype(torch::kFloat64));
  torch::Tensor out = torch::empty({}, depth.options());
  const int64_t n = static_cast<int64_t>(H) * W;
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(depth.scalar_type(), "nc_loss_forward", [&] {
    if (n > 0) {
      nc_forward_kernel<scalar_t><<<blocks_for(n), kThreads, 0, stream>>>(
          depth.data_ptr<scalar_t>(), K.data_ptr<scalar_t>(), H, W, normal.data_ptr<scalar_t>(),
          valid.data_ptr<bool>(), acc.data_ptr<double>());
    }
    masked_mean_finish<scalar_t><<<1, 1, 0, stream>>>(acc.data_ptr<double>(), out.data_ptr<scalar_t>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {out, acc};
}

// Returns {dL/dnormal [H, W, 3], dL/ddepth [H, W] (zeros when detach_depth)} for L = grad * L_nc.
std::vector<torch::Tensor> nc_loss_backward(torch::Tensor grad, torch::Tensor normal, torch::Tensor depth,
                                            torch::Tensor valid, torch::Tensor acc, torch::Tensor K,
                                            bool detach_depth) {
  using namespace losses_cuda;
  check_tensors({grad, normal, depth, valid, acc, K}, "nc backward");
  check_floats(normal, grad, "nc backward");
  const c10::cuda::CUDAGuard guard(depth.device());
  const int H = static_cast<int>(depth.size(0)), W = static_cast<int>(depth.size(1));
  const int64_t n = static_cast<int64_t>(H) * W;
  torch::Tensor gN = torch::zeros_like(normal), gD = torch::zeros_like(depth);
  if (n == 0) return {gN, gD};
  torch::Tensor gdx = detach_depth ? torch::empty({0}, normal.options()) : torch::zeros_like(normal);
  torch::Tensor gdy = detach_depth ? torch::empty({0}, normal.options()) : torch::zeros_like(normal);
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(depth.scalar_type(), "nc_loss_backward", [&] {
    const scalar_t* d = depth.data_ptr<scalar_t>();
    const scalar_t* k = K.data_ptr<scalar_t>();
    nc_backward_pixels<scalar_t><<<blocks_for(n), kThreads, 0, stream>>>(
        d, k, H, W, normal.data_ptr<scalar_t>(), valid.data_ptr<bool>(), grad.data_ptr<scalar_t>(), acc.data_ptr<double>(),
        detach_depth, gN.data_ptr<scalar_t>(), gdx.data_ptr<scalar_t>(), gdy.data_ptr<scalar_t>());
    if (!detach_depth) {
      nc_backward_gather<scalar_t><<<blocks_for(n), kThreads, 0, stream>>>(
          d, k, H, W, gdx.data_ptr<scalar_t>(), gdy.data_ptr<scalar_t>(), gD.data_ptr<scalar_t>());
    }
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {gN, gD};
}

// Returns {L_n (0-dim), acc (float64 [2]: the sum and the count of used pixels)}.
std::vector<torch::Tensor> normal_prior_loss_forward(torch::Tensor normal, torch::Tensor prior, torch::Tensor valid) {
  using namespace losses_cuda;
  check_tensors({normal, prior, valid}, "normal prior");
  check_floats(normal, prior, "normal prior");
  TORCH_CHECK(valid.scalar_type() == torch::kBool, "losses_cuda (normal prior): valid must be bool");
  const c10::cuda::CUDAGuard guard(normal.device());
  const int64_t n_pix = valid.numel();
  torch::Tensor acc = torch::zeros({2}, normal.options().dtype(torch::kFloat64));
  torch::Tensor out = torch::empty({}, normal.options());
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(normal.scalar_type(), "normal_prior_loss_forward", [&] {
    if (n_pix > 0) {
      np_forward_kernel<scalar_t><<<blocks_for(n_pix), kThreads, 0, stream>>>(
          normal.data_ptr<scalar_t>(), prior.data_ptr<scalar_t>(), valid.data_ptr<bool>(), n_pix,
          acc.data_ptr<double>());
    }
    masked_mean_finish<scalar_t><<<1, 1, 0, stream>>>(acc.data_ptr<double>(), out.data_ptr<scalar_t>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return {out, acc};
}

torch::Tensor normal_prior_loss_backward(torch::Tensor grad, torch::Tensor normal, torch::Tensor prior,
                                         torch::Tensor valid, torch::Tensor acc) {
  using namespace losses_cuda;
  check_tensors({grad, normal, prior, valid, acc}, "normal prior backward");
  check_floats(normal, grad, "normal prior backward");
  const c10::cuda::CUDAGuard guard(normal.device());
  const int64_t n_pix = valid.numel();
  torch::Tensor out = torch::zeros_like(normal);
  if (n_pix == 0) return out;
  auto stream = c10::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(normal.scalar_type(), "normal_prior_loss_backward", [&] {
    np_backward_kernel<scalar_t><<<blocks_for(n_pix), kThreads, 0, stream>>>(
        normal.data_ptr<scalar_t>(), prior.data_ptr<scalar_t>(), valid.data_ptr<bool>(), n_pix,
        grad.data_ptr<scalar_t>(), acc.data_ptr<double>(), out.data_ptr<scalar_t>());
  });
  C10_CUDA_KERNEL_LAUNCH_CHECK();
  return out;
}
