// Fused loss terms of the training step on the CPU (the Python side is splat/losses_cpu.py):
//
// 1. SSIM of L_rgb: mean SSIM of an [H, W, C] image against a reference
// (11x11 separable Gaussian window, zero padding "same", as 3DGS and evaluation/image_metrics.py's
// ssim_map, the torch oracle) and its analytic gradient with respect to the image.
//
// Forward: the five local moments (mu_x, mu_y, E[x^2], E[y^2], E[xy]), each a vertical and a
// horizontal pass per image row, then per pixel
//   S = A1 A2 / (B1 B2),  A1 = 2 mx my + C1,  A2 = 2 (Exy - mx my) + C2,
//                         B1 = mx^2 + my^2 + C1,  B2 = (Exx - mx^2) + (Eyy - my^2) + C2,
// and the partial derivatives of S/N (N = H W C, the mean) with respect to the three moments that
// depend on x:
//   dS/dmx  = 2 my (A2 - A1) / (B1 B2) - 2 mx S (B2 - B1) / (B1 B2),
//   dS/dExx = -S / B2,   dS/dExy = 2 A1 / (B1 B2).
// Backward: the window is symmetric and zero-padded, so the adjoint of each blur is the same blur:
//   dL/dx = g * [blur(dmx) + 2 x blur(dExx) + y blur(dExy)].
// OpenMP over image rows in every pass.

#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace losses_cpu {

inline int threads_for(int64_t n) { return n >= 4096 ? at::get_num_threads() : 1; }

// Separable zero-padded blur of Q planar maps, each [H, W, C] (in[q] -> out[q], out may not alias
// in). Rows are independent in both passes; the horizontal pass runs over a copy of the row with
// r * C zeros on each side, so that every output element is the same K-tap sum (vectorisable).
template <typename T, int Q>
void blur(const T* const* in, const std::vector<T>& g, int64_t H, int64_t W, int64_t C, T* const* out) {
  const int64_t K = static_cast<int64_t>(g.size()), r = K / 2, WC = W * C;
#pragma omp parallel num_threads(threads_for(H * WC))
  {
    std::vector<T> row((W + 2 * r) * C);
    std::fill(row.begin(), row.end(), T(0));
    T* mid = row.data() + r * C;
#pragma omp for schedule(static)
    for (int64_t i = 0; i < H; ++i) {
      const int64_t k0 = std::max<int64_t>(0, r - i), k1 = std::min<int64_t>(K, H + r - i);
      for (int q = 0; q < Q; ++q) {
        for (int64_t e = 0; e < WC; ++e) mid[e] = T(0);  // vertical pass into the padded row
        for (int64_t k = k0; k < k1; ++k) {
          const T w = g[k];
          const T* src = in[q] + (i + k - r) * WC;
          for (int64_t e = 0; e < WC; ++e) mid[e] += w * src[e];
        }
        T* dst = out[q] + i * WC;  // horizontal pass: taps C apart
        for (int64_t e = 0; e < WC; ++e) dst[e] = T(0);
        for (int64_t k = 0; k < K; ++k) {
          const T w = g[k];
          const T* src = row.data() + k * C;
          for (int64_t e = 0; e < WC; ++e) dst[e] += w * src[e];
        }
      }
    }
  }
}

template <typename T>
std::vector<T> window(const torch::Tensor& g) {
  auto gd = g.to(torch::kFloat64).contiguous();
  const double* p = gd.data_ptr<double>();
  return std::vector<T>(p, p + gd.numel());
}

// Mean SSIM; writes the three partial-derivative maps of S / n (see the top of the file).
template <typename T>
double forward_impl(const T* px, const T* py, const std::vector<T>& g, int64_t H, int64_t W, int64_t C,
                    T c1, T c2, T* o_mx, T* o_xx, T* o_xy) {
  const int64_t n = H * W * C;
  std::vector<T> prod(3 * n), mom(5 * n);
  T* xx = prod.data();
  T* yy = xx + n;
  T* xy = yy + n;
#pragma omp parallel for num_threads(threads_for(n)) schedule(static)
  for (int64_t e = 0; e < n; ++e) xx[e] = px[e] * px[e], yy[e] = py[e] * py[e], xy[e] = px[e] * py[e];
  const T* in[5] = {px, py, xx, yy, xy};
  T* m[5] = {mom.data(), mom.data() + n, mom.data() + 2 * n, mom.data() + 3 * n, mom.data() + 4 * n};
  blur<T, 5>(in, g, H, W, C, m);
  const T inv_n = T(1) / static_cast<T>(n);
  double total = 0.0;
#pragma omp parallel for num_threads(threads_for(n)) schedule(static) reduction(+ : total)
  for (int64_t e = 0; e < n; ++e) {
    const T mx = m[0][e], my = m[1][e];
    const T a1 = T(2) * mx * my + c1, a2 = T(2) * (m[4][e] - mx * my) + c2;
    const T b1 = mx * mx + my * my + c1, b2 = (m[2][e] - mx * mx) + (m[3][e] - my * my) + c2;
    const T den = b1 * b2, s = a1 * a2 / den;
    total += static_cast<double>(s);
    o_mx[e] = inv_n * (T(2) * my * (a2 - a1) - T(2) * mx * s * (b2 - b1)) / den;
    o_xx[e] = -inv_n * s / b2;
    o_xy[e] = inv_n * T(2) * a1 / den;
  }
  return total / static_cast<double>(n);
}

template <typename T>
void backward_impl(T scale, const T* px, const T* py, const T* d_mx, const T* d_xx, const T* d_xy,
                   const std::vector<T>& g, int64_t H, int64_t W, int64_t C, T* out) {
  const int64_t n = H * W * C;
  const T* in[3] = {d_mx, d_xx, d_xy};
  std::vector<T> bl(3 * n);
  T* b[3] = {bl.data(), bl.data() + n, bl.data() + 2 * n};
  blur<T, 3>(in, g, H, W, C, b);
#pragma omp parallel for num_threads(threads_for(n)) schedule(static)
  for (int64_t e = 0; e < n; ++e) out[e] = scale * (b[0][e] + T(2) * px[e] * b[1][e] + py[e] * b[2][e]);
}

void check(const torch::Tensor& x, const torch::Tensor& y) {
  TORCH_CHECK(x.device().is_cpu() && y.device().is_cpu(), "losses_cpu: tensors must be on the CPU");
  TORCH_CHECK(x.dim() == 3 && x.sizes() == y.sizes(), "losses_cpu: image and reference must be [H, W, C] alike");
  TORCH_CHECK(x.scalar_type() == y.scalar_type(), "losses_cpu: mixed float dtypes");
  TORCH_CHECK(x.is_contiguous() && y.is_contiguous(), "losses_cpu: tensors must be contiguous");
}

}  // namespace losses_cpu

// Returns {mean SSIM (0-dim), dmx, dExx, dExy} (the last three [H, W, C], for ssim_backward).
std::vector<torch::Tensor> ssim_forward(torch::Tensor x, torch::Tensor y, torch::Tensor g, double C1,
                                        double C2) {
  using namespace losses_cpu;
  check(x, y);
  torch::Tensor d_mx = torch::empty_like(x), d_xx = torch::empty_like(x), d_xy = torch::empty_like(x);
  double mean = 0.0;
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_forward", [&] {
    mean = forward_impl<scalar_t>(x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(), window<scalar_t>(g),
                                  x.size(0), x.size(1), x.size(2), static_cast<scalar_t>(C1),
                                  static_cast<scalar_t>(C2), d_mx.data_ptr<scalar_t>(),
                                  d_xx.data_ptr<scalar_t>(), d_xy.data_ptr<scalar_t>());
  });
  return {torch::full({}, mean, x.options()), d_mx, d_xx, d_xy};
}

// grad of the image: grad (0-dim) * [blur(dmx) + 2 x blur(dExx) + y blur(dExy)].
torch::Tensor ssim_backward(torch::Tensor grad, torch::Tensor x, torch::Tensor y, torch::Tensor d_mx,
                            torch::Tensor d_xx, torch::Tensor d_xy, torch::Tensor g) {
  using namespace losses_cpu;
  check(x, y);
  torch::Tensor out = torch::empty_like(x);
  const double s = grad.item<double>();
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "ssim_backward", [&] {
    backward_impl<scalar_t>(static_cast<scalar_t>(s), x.data_ptr<scalar_t>(), y.data_ptr<scalar_t>(),
                            d_mx.data_ptr<scalar_t>(), d_xx.data_ptr<scalar_t>(), d_xy.data_ptr<scalar_t>(),
                            window<scalar_t>(g), x.size(0), x.size(1), x.size(2), out.data_ptr<scalar_t>());
  });
  return out;
}

// 3. L_n, the normal-prior loss (splat/losses.py normal_prior_loss, the torch oracle): the mean
// over pixels (valid, rendered normal N != 0, prior P != 0 and finite) of |N - P|_1; its gradient
// sign(N - P) / count at those pixels (sign(0) = 0, as torch's abs).
//
// 2. L_nc, the depth-normal consistency (splat/losses.py depth_normal_consistency_loss and
// depth_to_normal, the torch oracle): at every interior pixel p with its four neighbours' depths
// and its own > 0, P = d (u, v, 1) back-projects the pixel centre, n = (P[j+1] - P[j-1]) x
// (P[i+1] - P[i-1]) flipped to face the camera (n . P(p) < 0), N_d = n / |n| where |n|^2 > 1e-20.
// L = sum over used pixels (valid, N_d defined, rendered normal N != 0) of (1 - N . N_d) / count.
// Backward: dL/dN = -N_d / count; dL/dN_d = -N / count -> dL/dn = s (G - u (u . G)) / |n| with u the
// unit normal, s = +-1 the flip; dL/ddx = dy x dL/dn, dL/ddy = dL/dn x dx, gathered per pixel from
// its four neighbours (no scatter: no races), dL/dd = ray . dL/dP.
namespace losses_cpu {

constexpr double kNorm2Eps = 1e-20;

template <typename T>
struct NcGeom {
  const T* d;
  int64_t H, W;
  T fx, fy, cx, cy;
  inline void ray(int64_t i, int64_t j, T* r) const {
    r[0] = (T(j) + T(0.5) - cx) / fx, r[1] = (T(i) + T(0.5) - cy) / fy, r[2] = T(1);
  }
  inline void point(int64_t i, int64_t j, T* P) const {
    T r[3];
    ray(i, j, r);
    const T z = d[i * W + j];
    P[0] = r[0] * z, P[1] = r[1] * z, P[2] = z;
  }
  // n (unnormalised, flipped to face the camera), dx, dy at interior pixel (i, j); false if undefined.
  inline bool normal(int64_t i, int64_t j, T* n, T* dx, T* dy, T& sign) const {
    const T* z = d + i * W + j;
    if (!(z[0] > 0 && z[1] > 0 && z[-1] > 0 && z[W] > 0 && z[-W] > 0)) return false;
    T a[3], b[3], c[3], e[3], P[3];
    point(i, j + 1, a), point(i, j - 1, b), point(i + 1, j, c), point(i - 1, j, e), point(i, j, P);
    for (int k = 0; k < 3; ++k) dx[k] = a[k] - b[k], dy[k] = c[k] - e[k];
    n[0] = dx[1] * dy[2] - dx[2] * dy[1];
    n[1] = dx[2] * dy[0] - dx[0] * dy[2];
    n[2] = dx[0] * dy[1] - dx[1] * dy[0];
    sign = (n[0] * P[0] + n[1] * P[1] + n[2] * P[2]) > 0 ? T(-1) : T(1);
    const T norm2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2];
    return norm2 > T(kNorm2Eps);
  }
};

template <typename T>
bool nc_used(const NcGeom<T>& g, const T* N, const bool* valid, int64_t i, int64_t j, T* n, T* dx, T* dy,
             T& sign) {
  const int64_t p = i * g.W + j;
  if (!valid[p] || (N[3 * p] == 0 && N[3 * p + 1] == 0 && N[3 * p + 2] == 0)) return false;
  return g.normal(i, j, n, dx, dy, sign);
}


template <typename T>
double nc_forward_impl(const NcGeom<T>& g, const T* N, const bool* ok, int64_t& count) {
  const int64_t H = g.H, W = g.W;
  double tot = 0.0;
  int64_t cnt = 0;
#pragma omp parallel for num_threads(threads_for(H * W)) schedule(static) reduction(+ : tot, cnt)
  for (int64_t i = 1; i < H - 1; ++i) {
    for (int64_t j = 1; j < W - 1; ++j) {
      T n[3], dx[3], dy[3], s;
      if (!nc_used(g, N, ok, i, j, n, dx, dy, s)) continue;
      const T inv = s / std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
      const T* Np = N + 3 * (i * W + j);
      tot += double(T(1) - (Np[0] * n[0] * inv + Np[1] * n[1] * inv + Np[2] * n[2] * inv));
      ++cnt;
    }
  }
  count = cnt;
  return tot;
}

template <typename T>
void nc_backward_impl(const NcGeom<T>& g, const T* N, const bool* ok, T c, bool detach_depth, T* oN, T* oD) {
  const int64_t H = g.H, W = g.W;
  std::vector<T> gdx(detach_depth ? 0 : 3 * H * W, T(0)), gdy(detach_depth ? 0 : 3 * H * W, T(0));
#pragma omp parallel for num_threads(threads_for(H * W)) schedule(static)
  for (int64_t i = 1; i < H - 1; ++i) {
    for (int64_t j = 1; j < W - 1; ++j) {
      T n[3], dx[3], dy[3], s;
      if (!nc_used(g, N, ok, i, j, n, dx, dy, s)) continue;
      const int64_t p = i * W + j;
      const T len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
      const T u[3] = {n[0] / len, n[1] / len, n[2] / len};
      for (int k = 0; k < 3; ++k) oN[3 * p + k] = -c * s * u[k];  // dL/dN = -N_d / count
      if (detach_depth) continue;
      const T G[3] = {-c * N[3 * p], -c * N[3 * p + 1], -c * N[3 * p + 2]};  // dL/dN_d
      const T uG = u[0] * G[0] + u[1] * G[1] + u[2] * G[2];
      T gn[3];
      for (int k = 0; k < 3; ++k) gn[k] = s * (G[k] - u[k] * uG) / len;
      T* ax = gdx.data() + 3 * p;  // dL/ddx = dy x gn; dL/ddy = gn x dx
      T* ay = gdy.data() + 3 * p;
      ax[0] = dy[1] * gn[2] - dy[2] * gn[1], ax[1] = dy[2] * gn[0] - dy[0] * gn[2], ax[2] = dy[0] * gn[1] - dy[1] * gn[0];
      ay[0] = gn[1] * dx[2] - gn[2] * dx[1], ay[1] = gn[2] * dx[0] - gn[0] * dx[2], ay[2] = gn[0] * dx[1] - gn[1] * dx[0];
    }
  }
  if (detach_depth) return;
#pragma omp parallel for num_threads(threads_for(H * W)) schedule(static)
  for (int64_t i = 0; i < H; ++i) {  // gather: dx of (i, j-1) and (i, j+1), dy of (i-1, j) and (i+1, j)
    for (int64_t j = 0; j < W; ++j) {
      T gP[3] = {0, 0, 0};
      for (int k = 0; k < 3; ++k) {
        if (j > 0) gP[k] += gdx[3 * (i * W + j - 1) + k];
        if (j < W - 1) gP[k] -= gdx[3 * (i * W + j + 1) + k];
        if (i > 0) gP[k] += gdy[3 * ((i - 1) * W + j) + k];
        if (i < H - 1) gP[k] -= gdy[3 * ((i + 1) * W + j) + k];
      }
      T r[3];
      g.ray(i, j, r);
      oD[i * W + j] = r[0] * gP[0] + r[1] * gP[1] + r[2] * gP[2];
    }
  }
}

}  // namespace losses_cpu

// Returns {L_nc (0-dim), count of used pixels (0-dim int64)}.
std::vector<torch::Tensor> nc_forward(torch::Tensor normal, torch::Tensor depth, torch::Tensor valid,
                                      double fx, double fy, double cx, double cy) {
  using namespace losses_cpu;
  TORCH_CHECK(normal.device().is_cpu() && normal.is_contiguous() && depth.is_contiguous() &&
                  valid.is_contiguous() && valid.scalar_type() == torch::kBool,
              "losses_cpu: contiguous CPU normal, depth and bool valid expected");
  TORCH_CHECK(normal.scalar_type() == depth.scalar_type(), "losses_cpu: mixed float dtypes");
  const int64_t H = depth.size(0), W = depth.size(1);
  double total = 0.0;
  int64_t count = 0;
  AT_DISPATCH_FLOATING_TYPES(depth.scalar_type(), "nc_forward", [&] {
    const NcGeom<scalar_t> g{depth.data_ptr<scalar_t>(), H, W, scalar_t(fx), scalar_t(fy), scalar_t(cx), scalar_t(cy)};
    total = nc_forward_impl<scalar_t>(g, normal.data_ptr<scalar_t>(), valid.data_ptr<bool>(), count);
  });
  const double mean = count > 0 ? total / double(count) : 0.0;
  return {torch::full({}, mean, depth.options()), torch::full({}, count, depth.options().dtype(torch::kInt64))};
}

// Returns {dL/dnormal [H, W, 3], dL/ddepth [H, W] (zeros when detach_depth)} for L = grad * L_nc.
std::vector<torch::Tensor> nc_backward(torch::Tensor grad, torch::Tensor normal, torch::Tensor depth,
                                       torch::Tensor valid, double fx, double fy, double cx, double cy,
                                       int64_t count, bool detach_depth) {
  using namespace losses_cpu;
  const int64_t H = depth.size(0), W = depth.size(1);
  torch::Tensor gN = torch::zeros_like(normal), gD = torch::zeros_like(depth);
  if (count == 0) return {gN, gD};
  const double scale = grad.item<double>() / double(count);
  AT_DISPATCH_FLOATING_TYPES(depth.scalar_type(), "nc_backward", [&] {
    const NcGeom<scalar_t> g{depth.data_ptr<scalar_t>(), H, W, scalar_t(fx), scalar_t(fy), scalar_t(cx), scalar_t(cy)};
    nc_backward_impl<scalar_t>(g, normal.data_ptr<scalar_t>(), valid.data_ptr<bool>(), scalar_t(scale), detach_depth,
                               gN.data_ptr<scalar_t>(), gD.data_ptr<scalar_t>());
  });
  return {gN, gD};
}

namespace losses_cpu {

template <typename T>
inline bool np_used(const T* N, const T* P, const bool* ok, int64_t p) {
  const T* n = N + 3 * p;
  const T* q = P + 3 * p;
  return ok[p] && (n[0] != 0 || n[1] != 0 || n[2] != 0) && (q[0] != 0 || q[1] != 0 || q[2] != 0) &&
         std::isfinite(q[0]) && std::isfinite(q[1]) && std::isfinite(q[2]);
}

template <typename T>
double np_forward_impl(const T* N, const T* P, const bool* ok, int64_t n_pix, int64_t& count) {
  double tot = 0.0;
  int64_t cnt = 0;
#pragma omp parallel for num_threads(threads_for(n_pix)) schedule(static) reduction(+ : tot, cnt)
  for (int64_t p = 0; p < n_pix; ++p) {
    if (!np_used(N, P, ok, p)) continue;
    tot += double(std::abs(N[3 * p] - P[3 * p]) + std::abs(N[3 * p + 1] - P[3 * p + 1]) +
                  std::abs(N[3 * p + 2] - P[3 * p + 2]));
    ++cnt;
  }
  count = cnt;
  return tot;
}

template <typename T>
void np_backward_impl(const T* N, const T* P, const bool* ok, int64_t n_pix, T c, T* out) {
#pragma omp parallel for num_threads(threads_for(n_pix)) schedule(static)
  for (int64_t p = 0; p < n_pix; ++p) {
    if (!np_used(N, P, ok, p)) continue;
    for (int k = 0; k < 3; ++k) {
      const T e = N[3 * p + k] - P[3 * p + k];
      out[3 * p + k] = e > 0 ? c : (e < 0 ? -c : T(0));
    }
  }
}

}  // namespace losses_cpu

// Returns {L_n (0-dim), count (0-dim int64)}.
std::vector<torch::Tensor> normal_prior_forward(torch::Tensor normal, torch::Tensor prior, torch::Tensor valid) {
  using namespace losses_cpu;
  TORCH_CHECK(normal.device().is_cpu() && normal.is_contiguous() && prior.is_contiguous() &&
                  valid.is_contiguous() && valid.scalar_type() == torch::kBool,
              "losses_cpu: contiguous CPU normal, prior and bool valid expected");
  TORCH_CHECK(normal.scalar_type() == prior.scalar_type(), "losses_cpu: mixed float dtypes");
  const int64_t n_pix = valid.numel();
  double total = 0.0;
  int64_t count = 0;
  AT_DISPATCH_FLOATING_TYPES(normal.scalar_type(), "normal_prior_forward", [&] {
    total = np_forward_impl<scalar_t>(normal.data_ptr<scalar_t>(), prior.data_ptr<scalar_t>(),
                                      valid.data_ptr<bool>(), n_pix, count);
  });
  const double mean = count > 0 ? total / double(count) : 0.0;
  return {torch::full({}, mean, normal.options()), torch::full({}, count, normal.options().dtype(torch::kInt64))};
}

torch::Tensor normal_prior_backward(torch::Tensor grad, torch::Tensor normal, torch::Tensor prior,
                                    torch::Tensor valid, int64_t count) {
  using namespace losses_cpu;
  torch::Tensor out = torch::zeros_like(normal);
  if (count == 0) return out;
  const double c = grad.item<double>() / double(count);
  AT_DISPATCH_FLOATING_TYPES(normal.scalar_type(), "normal_prior_backward", [&] {
    np_backward_impl<scalar_t>(normal.data_ptr<scalar_t>(), prior.data_ptr<scalar_t>(), valid.data_ptr<bool>(),
                               valid.numel(), scalar_t(c), out.data_ptr<scalar_t>());
  });
  return out;
}
