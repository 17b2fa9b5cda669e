// Python bindings of the CUDA rasterizer extension (splat/cuda_ext.py builds it): the compositing
// kernels (composite_cuda.cu) and the fused projection (project_cuda.cu, declared here).

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

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "CUDA rasterizer kernels: tile-based alpha compositing and fused Gaussian projection "
            "(forward + analytic backward)";
  m.def("forward", &composite_cuda_forward, "composite forward (see splat/composite.py)");
  m.def("backward", &composite_cuda_backward, "composite backward (see splat/composite.py)");
  m.def("project_forward", &project_cuda_forward, "projection forward (see splat/project_cuda.py)");
  m.def("project_backward", &project_cuda_backward, "projection backward (see splat/project_cuda.py)");
}
