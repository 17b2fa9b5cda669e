// Python bindings of the CPU rasterizer extension (splat/cpu_ext.py builds it).

#include "kernels.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "CPU rasterizer kernels: tile-based alpha compositing and fused Gaussian projection "
            "(forward + analytic backward)";
  m.def("forward", &composite_forward, "composite forward (see splat/composite.py)");
  m.def("backward", &composite_backward, "composite backward (see splat/composite.py)");
  m.def("project_forward", &project_forward, "projection forward (see splat/project_cpu.py)");
  m.def("project_backward", &project_backward, "projection backward (see splat/project_cpu.py)");
}
