// Entry points of the CPU rasterizer extension (defined in composite_cpu.cpp, project_cpu.cpp,
// maps_cpu.cpp and losses_cpu.cpp,
// bound to Python in bindings.cpp; the Python wrappers are splat/composite_cpu.py and
// splat/project_cpu.py).

#pragma once

#include <torch/extension.h>

#include <vector>

std::vector<torch::Tensor> composite_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor opacities, torch::Tensor features,
                                             torch::Tensor depths, torch::Tensor radii,
                                             torch::Tensor background, torch::Tensor median_features,
                                             int64_t W, int64_t H, bool store_weights);
std::vector<torch::Tensor> composite_backward_stored(
    torch::Tensor grad_out, torch::Tensor features, torch::Tensor final_T, torch::Tensor tile_offsets,
    torch::Tensor slot_rank, torch::Tensor g_order, torch::Tensor g_start, torch::Tensor g_slots,
    int64_t generation, int64_t W, int64_t H);
std::vector<torch::Tensor> composite_backward(
    torch::Tensor grad_out, torch::Tensor grad_alpha, torch::Tensor grad_median,
    torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities, torch::Tensor features,
    torch::Tensor radii, torch::Tensor background, torch::Tensor median_features,
    torch::Tensor final_T, torch::Tensor last, torch::Tensor median_idx, torch::Tensor tile_offsets,
    torch::Tensor slot_rank, torch::Tensor g_order, torch::Tensor g_start, torch::Tensor g_slots,
    int64_t W, int64_t H);
std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats,
                                           torch::Tensor log_scales, torch::Tensor opacities,
                                           torch::Tensor sh0, torch::Tensor shN, torch::Tensor R,
                                           torch::Tensor C, torch::Tensor K, int64_t W, int64_t H,
                                           double near, double far, double eps2d, double min_cos,
                                           bool antialiased, int64_t sh_degree);
std::vector<torch::Tensor> project_backward(
    torch::Tensor means, torch::Tensor quats, torch::Tensor log_scales, torch::Tensor opacities,
    torch::Tensor sh0, torch::Tensor shN, torch::Tensor R, torch::Tensor C, torch::Tensor K,
    torch::Tensor radii, torch::Tensor g_m2, torch::Tensor g_con, torch::Tensor g_z,
    torch::Tensor g_op, torch::Tensor g_col, torch::Tensor g_sl, torch::Tensor g_nrm, int64_t W,
    int64_t H, double near, double far, double eps2d, double min_cos, bool antialiased,
    int64_t sh_degree, bool geometry);
std::vector<torch::Tensor> ssim_forward(torch::Tensor x, torch::Tensor y, torch::Tensor g, double C1,
                                        double C2);
torch::Tensor ssim_backward(torch::Tensor grad, torch::Tensor x, torch::Tensor y, torch::Tensor d_mx,
                            torch::Tensor d_xx, torch::Tensor d_xy, torch::Tensor g);
std::vector<torch::Tensor> nc_forward(torch::Tensor normal, torch::Tensor depth, torch::Tensor valid,
                                      double fx, double fy, double cx, double cy);
std::vector<torch::Tensor> nc_backward(torch::Tensor grad, torch::Tensor normal, torch::Tensor depth,
                                       torch::Tensor valid, double fx, double fy, double cx, double cy,
                                       int64_t count, bool detach_depth);
std::vector<torch::Tensor> normal_prior_forward(torch::Tensor normal, torch::Tensor prior, torch::Tensor valid);
torch::Tensor normal_prior_backward(torch::Tensor grad, torch::Tensor normal, torch::Tensor prior,
                                    torch::Tensor valid, int64_t count);
std::vector<torch::Tensor> pixel_maps_forward(torch::Tensor features, torch::Tensor median,
                                              torch::Tensor alpha, double alpha_eps);
std::vector<torch::Tensor> pixel_maps_backward(torch::Tensor g_depth, torch::Tensor g_median,
                                               torch::Tensor g_normal, torch::Tensor features,
                                               torch::Tensor median, torch::Tensor alpha, double alpha_eps);
