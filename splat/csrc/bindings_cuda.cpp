// Python bindings of the CUDA compositing extension (splat/cuda_ext.py builds it).

#include "composite_cuda.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "CUDA rasterizer kernels: tile-based alpha compositing (forward + analytic backward)";
  m.def("forward", &composite_cuda_forward, "composite forward (see splat/composite.py)");
  m.def("backward", &composite_cuda_backward, "composite backward (see splat/composite.py)");
}
