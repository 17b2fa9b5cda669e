// Python bindings of the CUDA extension (splat/cuda_ext.py builds it): the compositing kernels
// (composite_cuda.cu), the fused projection (project_cuda.cu) and the fused loss terms
// (losses_cuda.cu), the last two declared here.

#include "composite_cuda.h"

// Defined in project_cuda.cu; the same arguments and results as project_cpu.cpp's project_forward /
// project_backward (kernels.h), float32 CUDA tensors only.
std::vector<torch::Tensor> project_cuda_forward(torch::Tensor means, torch::Tensor quats,
                                                torch::Tensor log_scales, torch::Tensor opacities,
                                                torch::Tensor sh0, torch::Tensor shN, torch::Tensor R,
                                                torch::Tensor C, torch::Tensor K, int64_t W, int64_t H,
                                                double near, double far, double eps2d, double min_cos,
                                                bool antialiased, int64_t sh_degree);
std::vector<torch::Tensor> project_cuda_backward(
    torch::Tensor means, torch::Tensor quats, torch::Tensor log_scales, torch::Tensor opacities,
    torch::Tensor sh0, torch::Tensor shN, torch::Tensor R, torch::Tensor C, torch::Tensor K,
    torch::Tensor radii, torch::Tensor g_m2, torch::Tensor g_con, torch::Tensor g_z,
    torch::Tensor g_op, torch::Tensor g_col, torch::Tensor g_sl, torch::Tensor g_nrm, int64_t W,
    int64_t H, double near, double far, double eps2d, double min_cos, bool antialiased,
    int64_t sh_degree);

// Defined in losses_cuda.cu (splat/losses_cuda.py wraps them).
std::vector<torch::Tensor> rgb_loss_forward(torch::Tensor x, torch::Tensor y, torch::Tensor g, double C1,
                                            double C2, double lambda);
torch::Tensor rgb_loss_backward(torch::Tensor grad, torch::Tensor x, torch::Tensor y, torch::Tensor d_mx,
                                torch::Tensor d_xx, torch::Tensor d_xy, torch::Tensor g, double lambda);
std::vector<torch::Tensor> nc_loss_forward(torch::Tensor normal, torch::Tensor depth, torch::Tensor valid,
                                           torch::Tensor K);
std::vector<torch::Tensor> nc_loss_backward(torch::Tensor grad, torch::Tensor normal, torch::Tensor depth,
                                            torch::Tensor valid, torch::Tensor acc, torch::Tensor K,
                                            bool detach_depth);
std::vector<torch::Tensor> normal_prior_loss_forward(torch::Tensor normal, torch::Tensor prior, torch::Tensor valid);
torch::Tensor normal_prior_loss_backward(torch::Tensor grad, torch::Tensor normal, torch::Tensor prior,
                                         torch::Tensor valid, torch::Tensor acc);

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "CUDA kernels: tile-based alpha compositing, fused Gaussian projection and fused loss terms "
            "(forward + analytic backward)";
  m.def("forward", &composite_cuda_forward, "composite forward (see splat/composite.py)");
  m.def("backward", &composite_cuda_backward, "composite backward (see splat/composite.py)");
  m.def("project_forward", &project_cuda_forward, "projection forward (see splat/project_cuda.py)");
  m.def("project_backward", &project_cuda_backward, "projection backward (see splat/project_cuda.py)");
  m.def("rgb_loss_forward", &rgb_loss_forward, "L_rgb (L1 + SSIM) forward (see splat/losses_cuda.py)");
  m.def("rgb_loss_backward", &rgb_loss_backward, "L_rgb backward (see splat/losses_cuda.py)");
  m.def("nc_loss_forward", &nc_loss_forward, "L_nc forward (see splat/losses_cuda.py)");
  m.def("nc_loss_backward", &nc_loss_backward, "L_nc backward (see splat/losses_cuda.py)");
  m.def("normal_prior_loss_forward", &normal_prior_loss_forward, "L_n forward (see splat/losses_cuda.py)");
  m.def("normal_prior_loss_backward", &normal_prior_loss_backward, "L_n backward (see splat/losses_cuda.py)");
}
