// Fused SSIM of the training loss on the CPU: mean SSIM of an [H, W, C] image against a reference
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
#include <vector>

namespace ssim_cpu {

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
  TORCH_CHECK(x.device().is_cpu() && y.device().is_cpu(), "ssim_cpu: tensors must be on the CPU");
  TORCH_CHECK(x.dim() == 3 && x.sizes() == y.sizes(), "ssim_cpu: image and reference must be [H, W, C] alike");
  TORCH_CHECK(x.scalar_type() == y.scalar_type(), "ssim_cpu: mixed float dtypes");
  TORCH_CHECK(x.is_contiguous() && y.is_contiguous(), "ssim_cpu: tensors must be contiguous");
}

}  // namespace ssim_cpu

// Returns {mean SSIM (0-dim), dmx, dExx, dExy} (the last three [H, W, C], for ssim_backward).
std::vector<torch::Tensor> ssim_forward(torch::Tensor x, torch::Tensor y, torch::Tensor g, double C1,
                                        double C2) {
  using namespace ssim_cpu;
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
  using namespace ssim_cpu;
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
