// Entry points of the CUDA compositing extension (defined in composite_cuda.cu, bound to Python in
// bindings_cuda.cpp; built by splat/cuda_ext.py, wrapped by splat/composite_cuda.py).

#pragma once

#include <torch/extension.h>

#include <vector>

// Returns {out [H,W,C], alpha [H,W], median [H,W,M], n_contrib [H,W] int32,
//          final_T [H,W], last [H,W] int32, median_idx [H,W] int32,
//          tile_ranges [n_tiles,2] int32, ids [E] int32, xy [N,2], con_o [N,4], box [N,4] int32};
// the last eight are the state the backward needs.
std::vector<torch::Tensor> composite_cuda_forward(torch::Tensor means2d, torch::Tensor conics,
                                                  torch::Tensor opacities, torch::Tensor features,
                                                  torch::Tensor depths, torch::Tensor radii,
                                                  torch::Tensor background,
                                                  torch::Tensor median_features, int64_t W, int64_t H);

// Returns {d_means2d [N,2], d_conics [N,3], d_opacities [N], d_features [N,C], d_background [C],
//          d_median_features [N,M]}.
std::vector<torch::Tensor> composite_cuda_backward(
    torch::Tensor grad_out, torch::Tensor grad_alpha, torch::Tensor grad_median,
    torch::Tensor features, torch::Tensor background, torch::Tensor median_features,
    torch::Tensor final_T, torch::Tensor last, torch::Tensor median_idx, torch::Tensor tile_ranges,
    torch::Tensor ids, torch::Tensor xy, torch::Tensor con_o, torch::Tensor box, int64_t W,
    int64_t H);
