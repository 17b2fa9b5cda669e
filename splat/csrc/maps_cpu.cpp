// render()'s per-pixel maps from the composited channels, fused (the Python side is
// splat/maps_cpu.py; the torch code, splat.rasterize.pixel_maps, is the oracle):
//
//   depth  = covered ? (f3 + f4 cx + f5 cy) / alpha : 0,   covered = alpha > alpha_eps
//   median = m0 + m1 cx + m2 cy
//   normal = |n|^2 > 1e-12 ? n / |n| : 0,                  n = (f6, f7, f8)
//
// with (cx, cy) the pixel centre (x + 0.5, y + 0.5); features [H, W, C >= 9], median [H, W, 3],
// alpha [H, W]. The backward gives the gradients of features (channels 3..8; the others 0), median
// and alpha, with torch's conventions where the maps are 0 (no gradient). One pass over the pixels
// each way, where autograd runs ~25 operations on full-size temporaries.

#include <torch/extension.h>

#include <cmath>
#include <vector>

namespace maps_cpu {

inline int threads_for(int64_t n) { return n >= 16384 ? at::get_num_threads() : 1; }

constexpr double kNorm2Eps = 1e-12;

// Depth of a blended plane (A, p) at the pixel centre (cx, cy): A + p . c (splat.rasterize.plane_depth).
template <typename T>
inline T plane_depth(const T* plane, T cx, T cy) {
  return plane[0] + (plane[1] * cx + plane[2] * cy);
}

template <typename T>
void forward_impl(const T* f, const T* md, const T* a, int64_t H, int64_t W, int64_t C, T eps,
                  T* depth, T* median, T* normal) {
#pragma omp parallel for num_threads(threads_for(H * W)) schedule(static)
  for (int64_t y = 0; y < H; ++y) {
    const T cy = T(y) + T(0.5);
    for (int64_t x = 0; x < W; ++x) {
      const int64_t p = y * W + x;
      const T cx = T(x) + T(0.5);
      const T* fp = f + p * C;
      depth[p] = a[p] > eps ? plane_depth(fp + 3, cx, cy) / a[p] : T(0);
      median[p] = plane_depth(md + 3 * p, cx, cy);
      const T n2 = fp[6] * fp[6] + fp[7] * fp[7] + fp[8] * fp[8];
      const T r = n2 > T(kNorm2Eps) ? T(1) / std::sqrt(n2) : T(0);
      for (int k = 0; k < 3; ++k) normal[3 * p + k] = n2 > T(kNorm2Eps) ? fp[6 + k] * r : T(0);
    }
  }
}

template <typename T>
void backward_impl(const T* f, const T* a, const T* gd, const T* gm, const T* gn, int64_t H,
                   int64_t W, int64_t C, T eps, T* df, T* dm, T* da) {
#pragma omp parallel for num_threads(threads_for(H * W)) schedule(static)
  for (int64_t y = 0; y < H; ++y) {
    const T cy = T(y) + T(0.5);
    for (int64_t x = 0; x < W; ++x) {
      const int64_t p = y * W + x;
      const T cx = T(x) + T(0.5);
      const T* fp = f + p * C;
      T* dfp = df + p * C;
      for (int64_t k = 0; k < C; ++k) dfp[k] = T(0);
      da[p] = T(0);
      if (a[p] > eps) {
        const T inv = T(1) / a[p], g = gd[p] * inv;
        dfp[3] = g;
        dfp[4] = g * cx;
        dfp[5] = g * cy;
        da[p] = -g * plane_depth(fp + 3, cx, cy) * inv;
      }
      dm[3 * p] = gm[p];
      dm[3 * p + 1] = gm[p] * cx;
      dm[3 * p + 2] = gm[p] * cy;
      const T n2 = fp[6] * fp[6] + fp[7] * fp[7] + fp[8] * fp[8];
      if (n2 > T(kNorm2Eps)) {  // d(n / |n|) = (g - u (u . g)) / |n|,  u = n / |n|
        const T r = T(1) / std::sqrt(n2);
        const T* g = gn + 3 * p;
        const T ug = (fp[6] * g[0] + fp[7] * g[1] + fp[8] * g[2]) * r;
        for (int k = 0; k < 3; ++k) dfp[6 + k] = (g[k] - fp[6 + k] * r * ug) * r;
      }
    }
  }
}

void check(const torch::Tensor& features, const torch::Tensor& median, const torch::Tensor& alpha) {
  TORCH_CHECK(features.dim() == 3 && features.size(2) >= 9, "maps_cpu: features must be [H, W, C >= 9]");
  const int64_t H = features.size(0), W = features.size(1);
  TORCH_CHECK(median.dim() == 3 && median.size(0) == H && median.size(1) == W && median.size(2) == 3,
              "maps_cpu: median must be [H, W, 3]");
  TORCH_CHECK(alpha.dim() == 2 && alpha.size(0) == H && alpha.size(1) == W, "maps_cpu: alpha must be [H, W]");
  for (const auto* t : {&features, &median, &alpha}) {
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous(), "maps_cpu: tensors must be contiguous CPU");
    TORCH_CHECK(t->scalar_type() == features.scalar_type(), "maps_cpu: mixed float dtypes");
  }
}

}  // namespace maps_cpu

std::vector<torch::Tensor> pixel_maps_forward(torch::Tensor features, torch::Tensor median,
                                              torch::Tensor alpha, double alpha_eps) {
  using namespace maps_cpu;
  check(features, median, alpha);
  const int64_t H = features.size(0), W = features.size(1), C = features.size(2);
  torch::Tensor depth = torch::empty({H, W}, features.options());
  torch::Tensor med = torch::empty({H, W}, features.options());
  torch::Tensor normal = torch::empty({H, W, 3}, features.options());
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "pixel_maps_forward", [&] {
    forward_impl<scalar_t>(features.data_ptr<scalar_t>(), median.data_ptr<scalar_t>(),
                           alpha.data_ptr<scalar_t>(), H, W, C, scalar_t(alpha_eps),
                           depth.data_ptr<scalar_t>(), med.data_ptr<scalar_t>(), normal.data_ptr<scalar_t>());
  });
  return {depth, med, normal};
}

std::vector<torch::Tensor> pixel_maps_backward(torch::Tensor g_depth, torch::Tensor g_median,
                                               torch::Tensor g_normal, torch::Tensor features,
                                               torch::Tensor median, torch::Tensor alpha, double alpha_eps) {
  using namespace maps_cpu;
  check(features, median, alpha);
  const int64_t H = features.size(0), W = features.size(1), C = features.size(2);
  for (const auto* t : {&g_depth, &g_median, &g_normal})
    TORCH_CHECK(t->device().is_cpu() && t->is_contiguous() && t->scalar_type() == features.scalar_type(),
                "maps_cpu: gradients must be contiguous CPU tensors of the features' dtype");
  TORCH_CHECK(g_depth.numel() == H * W && g_median.numel() == H * W && g_normal.numel() == 3 * H * W,
              "maps_cpu: gradient shapes do not match the maps");
  torch::Tensor df = torch::empty_like(features), dm = torch::empty_like(median), da = torch::empty_like(alpha);
  AT_DISPATCH_FLOATING_TYPES(features.scalar_type(), "pixel_maps_backward", [&] {
    backward_impl<scalar_t>(features.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(),
                            g_depth.data_ptr<scalar_t>(), g_median.data_ptr<scalar_t>(),
                            g_normal.data_ptr<scalar_t>(), H, W, C, scalar_t(alpha_eps),
                            df.data_ptr<scalar_t>(), dm.data_ptr<scalar_t>(), da.data_ptr<scalar_t>());
  });
  return {df, dm, da};
}
