// Python bindings of the CPU rasterizer extension (splat/cpu_ext.py builds it).

#include "kernels.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "CPU rasterizer kernels: tile-based alpha compositing and fused Gaussian projection "
            "and the training loss's SSIM, L_n and L_nc (forward + analytic backward)";
  m.def("forward", &composite_forward, "composite forward (see splat/composite.py)");
  m.def("backward", &composite_backward, "composite backward (see splat/composite.py)");
  m.def("backward_stored", &composite_backward_stored,
        "composite backward of the features alone from the forward's stored weights (see splat/composite_cpu.py)");
  m.def("project_forward", &project_forward, "projection forward (see splat/project_cpu.py)");
  m.def("project_backward", &project_backward, "projection backward (see splat/project_cpu.py)");
  m.def("ssim_forward", &ssim_forward, "fused SSIM forward (see splat/losses_cpu.py)");
  m.def("ssim_backward", &ssim_backward, "fused SSIM backward (see splat/losses_cpu.py)");
  m.def("normal_prior_forward", &normal_prior_forward, "fused normal-prior loss forward (see splat/losses_cpu.py)");
  m.def("normal_prior_backward", &normal_prior_backward, "fused normal-prior loss backward (see splat/losses_cpu.py)");
  m.def("nc_forward", &nc_forward, "fused depth-normal consistency forward (see splat/losses_cpu.py)");
  m.def("pixel_maps_forward", &pixel_maps_forward, "render's depth/median/normal maps forward (see splat/maps_cpu.py)");
  m.def("pixel_maps_backward", &pixel_maps_backward, "render's depth/median/normal maps backward (see splat/maps_cpu.py)");
  m.def("nc_backward", &nc_backward, "fused depth-normal consistency backward (see splat/losses_cpu.py)");
}
