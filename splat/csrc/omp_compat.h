// OpenMP where the compiler has it (-fopenmp defines _OPENMP); otherwise one thread: the pragmas are
// ignored and these stand-ins say "thread 0 of 1" (Apple's clang, for one, has no -fopenmp; see
// splat/cpu_ext.py, which then builds the kernels without it).

#pragma once

#ifdef _OPENMP
#include <omp.h>
#else
inline int omp_get_thread_num() { return 0; }
inline int omp_get_num_threads() { return 1; }
inline int omp_get_max_threads() { return 1; }
#endif
