// Python bindings of the compositing kernels alone: the AVX2 build of composite_cpu.cpp
// (splat/cpu_ext.py builds it with -mavx2 on CPUs that have AVX2 and uses it instead of the
// baseline build's compositing).

#include "kernels.h"

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "CPU compositing kernels built for AVX2 (8 float lanes)";
  m.def("forward", &composite_forward, "composite forward (see splat/composite.py)");
  m.def("backward", &composite_backward, "composite backward (see splat/composite.py)");
}
