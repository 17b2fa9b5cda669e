// Fused CPU projection of 3D Gaussians: EWA 2D covariance, conic, radius, SH colour and the RaDe-GS
// depth plane and normal, forward and analytic backward, one pass over the Gaussians.
//
// It computes exactly what splat/projection.py computes (the torch reference and oracle; its
// docstrings give the equations), in the same order of operations and the same scalar type, so the
// two agree to rounding. The backward is the hand-written chain rule of that forward, including
// torch's conventions where a function is not differentiable: clamp passes the gradient on its
// closed interval, maximum splits it on ties, min over the scales sends it to the first minimum.
// Culled Gaussians (depth range, radius box off the image, non-finite) get radius 0, zeros (depth
// 1) and no gradient. Camera gradients are not computed (splat/project_cpu.py falls back to torch
// when the camera requires grad).

#include <torch/extension.h>
#include "kernels.h"

#include "omp_compat.h"

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

namespace project_cpu {

constexpr double kFlatVariance = 1e-8;  // splat.projection.FLAT_VARIANCE
constexpr double kMaxRadius = 1e8;      // splat.projection.MAX_RADIUS
constexpr double kClampM = 1e9;         // clamp of J W R S (float32 overflow guard)

constexpr double SH_C0 = 0.28209479177387814;
constexpr double SH_C1 = 0.4886025119029199;
constexpr double SH_C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                             -1.0925484305920792, 0.5462742152960396};
constexpr double SH_C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                             0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                             -0.5900435899266435};

template <typename T>
struct Cam {
  T R[9], C[3], fx, fy, cx, cy;
  int64_t W, H;
  T near, far, eps2d, min_cos;
  bool antialiased;
  int sh_degree;
  int64_t sh_rest;  // shN.size(1)
};

// Everything the forward computes for one Gaussian that the backward needs again.
template <typename T>
struct Geo {
  T rel[3], p[3];           // world offset from the camera centre; camera-frame mean
  T qn[4], q_inv;           // normalised quaternion and 1 / max(|q|, 1e-6)
  bool q_big;               // |q|^2 >= 1e-12 (the clamp passes the gradient)
  T A[9], s[3], RS[9];      // A = R Rot (row-major), s = exp(log-scales), RS = A diag(s)
  T xz, yz, clx, cly;       // x/z, y/z and their clamped values
  bool x_in, y_in;          // the clamp passes the gradient
  T tx, ty, inv_z;
  T M[6];                   // J W R S, clamped; rows M[0..2], M[3..5]
  bool M_in[6];
  T a, b, c, mn[3], det, Dlp, conic[3], lam, m2[2];
};

template <typename T>
inline T clampv(T v, T lo, T hi) { return std::min(std::max(v, lo), hi); }

template <typename T>
inline void quat_to_rot(const T q[4], T R[9]) {
  const T w = q[0], x = q[1], y = q[2], z = q[3];
  R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z); R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z); R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y); R[7] = 2 * (y * z + w * x); R[8] = 1 - 2 * (x * x + y * y);
}

// Camera-frame mean; false when the Gaussian is outside the depth range or not finite.
template <typename T>
inline bool to_camera(const Cam<T>& cam, const T* mean, Geo<T>& g) {
  for (int k = 0; k < 3; ++k) g.rel[k] = mean[k] - cam.C[k];
  for (int k = 0; k < 3; ++k)
    g.p[k] = g.rel[0] * cam.R[3 * k] + g.rel[1] * cam.R[3 * k + 1] + g.rel[2] * cam.R[3 * k + 2];
  const T z = g.p[2];
  return z > cam.near && z < cam.far && std::isfinite(g.p[0]) && std::isfinite(g.p[1]) &&
         std::isfinite(z);
}

// EWA stage of splat.projection._ewa_stage for a Gaussian already in the depth range.
template <typename T>
inline void ewa(const Cam<T>& cam, const T* quat, const T* log_scale, Geo<T>& g) {
  const T qq = quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3];
  g.q_big = qq >= T(1e-12);
  g.q_inv = T(1) / std::sqrt(std::max(qq, T(1e-12)));
  for (int k = 0; k < 4; ++k) g.qn[k] = quat[k] * g.q_inv;
  T rot[9];
  quat_to_rot(g.qn, rot);
  for (int k = 0; k < 3; ++k)
    for (int j = 0; j < 3; ++j)
      g.A[3 * k + j] = cam.R[3 * k] * rot[j] + cam.R[3 * k + 1] * rot[3 + j] + cam.R[3 * k + 2] * rot[6 + j];
  for (int j = 0; j < 3; ++j) g.s[j] = std::exp(log_scale[j]);
  for (int k = 0; k < 3; ++k)
    for (int j = 0; j < 3; ++j) g.RS[3 * k + j] = g.A[3 * k + j] * g.s[j];
  const T x = g.p[0], y = g.p[1], z = g.p[2];
  const T tan_x = T(0.5) * T(cam.W) / cam.fx, tan_y = T(0.5) * T(cam.H) / cam.fy;
  const T lo_x = -(cam.cx / cam.fx + T(0.3) * tan_x), hi_x = (T(cam.W) - cam.cx) / cam.fx + T(0.3) * tan_x;
  const T lo_y = -(cam.cy / cam.fy + T(0.3) * tan_y), hi_y = (T(cam.H) - cam.cy) / cam.fy + T(0.3) * tan_y;
  g.xz = x / z;
  g.yz = y / z;
  g.x_in = g.xz >= lo_x && g.xz <= hi_x;
  g.y_in = g.yz >= lo_y && g.yz <= hi_y;
  g.clx = clampv(g.xz, lo_x, hi_x);
  g.cly = clampv(g.yz, lo_y, hi_y);
  g.tx = z * g.clx;
  g.ty = z * g.cly;
  g.inv_z = T(1) / z;
  const T ux = cam.fx * g.inv_z, vx = cam.fx * g.tx * g.inv_z * g.inv_z;
  const T uy = cam.fy * g.inv_z, vy = cam.fy * g.ty * g.inv_z * g.inv_z;
  for (int j = 0; j < 3; ++j) {
    const T m0 = ux * g.RS[j] - vx * g.RS[6 + j], m1 = uy * g.RS[3 + j] - vy * g.RS[6 + j];
    g.M_in[j] = m0 >= T(-kClampM) && m0 <= T(kClampM);
    g.M_in[3 + j] = m1 >= T(-kClampM) && m1 <= T(kClampM);
    g.M[j] = clampv(m0, T(-kClampM), T(kClampM));
    g.M[3 + j] = clampv(m1, T(-kClampM), T(kClampM));
  }
  const T* M = g.M;
  g.a = M[0] * M[0] + M[1] * M[1] + M[2] * M[2];
  g.b = M[0] * M[3] + M[1] * M[4] + M[2] * M[5];
  g.c = M[3] * M[3] + M[4] * M[4] + M[5] * M[5];
  g.mn[0] = M[0] * M[4] - M[1] * M[3];
  g.mn[1] = M[0] * M[5] - M[2] * M[3];
  g.mn[2] = M[1] * M[5] - M[2] * M[4];
  g.det = g.mn[0] * g.mn[0] + g.mn[1] * g.mn[1] + g.mn[2] * g.mn[2];
  const T e = cam.eps2d, al = g.a + e, cl = g.c + e;
  g.Dlp = g.det + e * (g.a + g.c) + e * e;
  g.conic[0] = cl / g.Dlp;
  g.conic[1] = -g.b / g.Dlp;
  g.conic[2] = al / g.Dlp;
  const T hd = T(0.5) * (al - cl);
  g.lam = T(0.5) * (al + cl) + std::sqrt(std::max(hd * hd + g.b * g.b, T(0.1)));
  g.m2[0] = cam.fx * x / z + cam.cx;
  g.m2[1] = cam.fy * y / z + cam.cy;
}

// Radius (0 = culled) of a Gaussian after ewa(), as splat.projection.project_gaussians.
template <typename T>
inline int32_t radius_of(const Cam<T>& cam, const Geo<T>& g) {
  const T r = std::min(std::ceil(T(3) * std::sqrt(g.lam)), T(kMaxRadius));
  const T mx = g.m2[0], my = g.m2[1];
  const bool on_image = mx + r >= T(0.5) && mx - r <= T(cam.W) - T(0.5) && my + r >= T(0.5) &&
                        my - r <= T(cam.H) - T(0.5);
  const bool finite = std::isfinite(mx) && std::isfinite(my) && std::isfinite(g.conic[0]) &&
                      std::isfinite(g.conic[1]) && std::isfinite(g.conic[2]);
  return on_image && finite ? int32_t(r) : 0;
}

// RaDe-GS depth plane and normal (splat.projection.depth_plane_and_normal) and its intermediates.
template <typename T>
struct Plane {
  int jmin;
  bool wkeep[3];
  T w[3], r0[3], local[3], t[3], n[3], inv_n, nh[3], r0n, r0norm, absr, mc, denom, sgn;
  bool n_big;
  T slope[2], normal[3];
};

template <typename T>
inline void plane_of(const Cam<T>& cam, const T* ls, const Geo<T>& g, Plane<T>& P) {
  P.jmin = 0;
  for (int j = 1; j < 3; ++j)
    if (ls[j] < ls[P.jmin]) P.jmin = j;  // first minimum, as torch.min(dim) / argmin
  const T ls_min = ls[P.jmin];
  const bool flat = T(2) * ls_min < T(std::log(kFlatVariance));
  for (int j = 0; j < 3; ++j) {
    P.wkeep[j] = !(flat && j != P.jmin);
    P.w[j] = P.wkeep[j] ? std::exp(T(2) * (ls_min - ls[j])) : T(0);
  }
  const T z = g.p[2];
  P.r0[0] = g.p[0] / z; P.r0[1] = g.p[1] / z; P.r0[2] = T(1);
  for (int j = 0; j < 3; ++j)
    P.local[j] = g.A[j] * P.r0[0] + g.A[3 + j] * P.r0[1] + g.A[6 + j] * P.r0[2];
  for (int j = 0; j < 3; ++j) P.t[j] = P.w[j] * P.local[j];
  for (int k = 0; k < 3; ++k)
    P.n[k] = g.A[3 * k] * P.t[0] + g.A[3 * k + 1] * P.t[1] + g.A[3 * k + 2] * P.t[2];
  const T nn2 = P.n[0] * P.n[0] + P.n[1] * P.n[1] + P.n[2] * P.n[2];
  P.n_big = nn2 >= T(1e-30);
  P.inv_n = T(1) / std::sqrt(std::max(nn2, T(1e-30)));
  for (int k = 0; k < 3; ++k) P.nh[k] = P.n[k] * P.inv_n;
  P.r0n = P.r0[0] * P.nh[0] + P.r0[1] * P.nh[1] + P.r0[2] * P.nh[2];
  P.r0norm = std::sqrt(P.r0[0] * P.r0[0] + P.r0[1] * P.r0[1] + P.r0[2] * P.r0[2]);
  P.absr = std::abs(P.r0n);
  P.mc = cam.min_cos * P.r0norm;
  P.sgn = P.r0n < 0 ? T(-1) : T(1);
  P.denom = std::max(P.absr, P.mc) * P.sgn;
  P.slope[0] = -z * P.nh[0] / P.denom / cam.fx;
  P.slope[1] = -z * P.nh[1] / P.denom / cam.fy;
  for (int k = 0; k < 3; ++k) P.normal[k] = P.r0n < 0 ? P.nh[k] : -P.nh[k];
}

// Real SH basis (splat.sh.sh_basis ordering and signs) at a unit direction, and its gradient.
template <typename T>
inline void sh_basis(int degree, const T d[3], T Y[16]) {
  const T x = d[0], y = d[1], z = d[2];
  Y[0] = T(SH_C0);
  if (degree < 1) return;
  Y[1] = -T(SH_C1) * y; Y[2] = T(SH_C1) * z; Y[3] = -T(SH_C1) * x;
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  Y[4] = T(SH_C2[0]) * xy; Y[5] = T(SH_C2[1]) * yz; Y[6] = T(SH_C2[2]) * (T(2) * zz - xx - yy);
  Y[7] = T(SH_C2[3]) * xz; Y[8] = T(SH_C2[4]) * (xx - yy);
  if (degree < 3) return;
  Y[9] = T(SH_C3[0]) * y * (T(3) * xx - yy); Y[10] = T(SH_C3[1]) * xy * z;
  Y[11] = T(SH_C3[2]) * y * (T(4) * zz - xx - yy);
  Y[12] = T(SH_C3[3]) * z * (T(2) * zz - T(3) * xx - T(3) * yy);
  Y[13] = T(SH_C3[4]) * x * (T(4) * zz - xx - yy); Y[14] = T(SH_C3[5]) * z * (xx - yy);
  Y[15] = T(SH_C3[6]) * x * (xx - T(3) * yy);
}

// sum_k v[k] * grad Y_k(d), added to out[3].
template <typename T>
inline void sh_basis_vjp(int degree, const T d[3], const T v[16], T out[3]) {
  if (degree < 1) return;
  const T x = d[0], y = d[1], z = d[2];
  out[0] += -T(SH_C1) * v[3]; out[1] += -T(SH_C1) * v[1]; out[2] += T(SH_C1) * v[2];
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z;
  const T c0 = T(SH_C2[0]) * v[4], c1 = T(SH_C2[1]) * v[5], c2 = T(SH_C2[2]) * v[6];
  const T c3 = T(SH_C2[3]) * v[7], c4 = T(SH_C2[4]) * v[8];
  out[0] += c0 * y - T(2) * c2 * x + c3 * z + T(2) * c4 * x;
  out[1] += c0 * x + c1 * z - T(2) * c2 * y - T(2) * c4 * y;
  out[2] += c1 * y + T(4) * c2 * z + c3 * x;
  if (degree < 3) return;
  const T e0 = T(SH_C3[0]) * v[9], e1 = T(SH_C3[1]) * v[10], e2 = T(SH_C3[2]) * v[11];
  const T e3 = T(SH_C3[3]) * v[12], e4 = T(SH_C3[4]) * v[13], e5 = T(SH_C3[5]) * v[14];
  const T e6 = T(SH_C3[6]) * v[15];
  out[0] += e0 * T(6) * x * y + e1 * y * z - e2 * T(2) * x * y - e3 * T(6) * x * z +
            e4 * (T(4) * zz - T(3) * xx - yy) + e5 * T(2) * x * z + e6 * (T(3) * xx - T(3) * yy);
  out[1] += e0 * (T(3) * xx - T(3) * yy) + e1 * x * z + e2 * (T(4) * zz - xx - T(3) * yy) -
            e3 * T(6) * y * z - e4 * T(2) * x * y - e5 * T(2) * y * z - e6 * T(6) * x * y;
  out[2] += e1 * x * y + e2 * T(8) * y * z + e3 * (T(6) * zz - T(3) * xx - T(3) * yy) +
            e4 * T(8) * x * z + e5 * (xx - yy);
}

// Unit view direction rel / |rel| (the norm clamped at 1e-12, as splat.projection).
template <typename T>
inline T view_dir(const T rel[3], T d[3]) {
  const T rr = rel[0] * rel[0] + rel[1] * rel[1] + rel[2] * rel[2];
  const T inv = T(1) / std::sqrt(std::max(rr, T(1e-24)));
  for (int k = 0; k < 3; ++k) d[k] = rel[k] * inv;
  return inv;
}

template <typename T>
inline T coeff(const T* sh0, const T* shN, const Cam<T>& cam, int64_t i, int k, int ch) {
  return k == 0 ? sh0[3 * i + ch] : shN[(i * cam.sh_rest + (k - 1)) * 3 + ch];
}

inline int threads_for(int64_t n) { return n >= 4096 ? at::get_num_threads() : 1; }

template <typename T>
Cam<T> make_cam(const torch::Tensor& R, const torch::Tensor& C, const torch::Tensor& K, int64_t W,
                int64_t H, double near, double far, double eps2d, double min_cos, bool aa,
                int64_t sh_degree, int64_t sh_rest) {
  Cam<T> cam;
  auto r = R.accessor<T, 2>();
  auto c = C.accessor<T, 1>();
  auto k = K.accessor<T, 2>();
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) cam.R[3 * i + j] = r[i][j];
  for (int i = 0; i < 3; ++i) cam.C[i] = c[i];
  cam.fx = k[0][0]; cam.fy = k[1][1]; cam.cx = k[0][2]; cam.cy = k[1][2];
  cam.W = W; cam.H = H;
  cam.near = T(near); cam.far = T(far); cam.eps2d = T(eps2d); cam.min_cos = T(min_cos);
  cam.antialiased = aa; cam.sh_degree = int(sh_degree); cam.sh_rest = sh_rest;
  return cam;
}

template <typename T>
void forward_impl(const Cam<T>& cam, int64_t N, const T* means, const T* quats, const T* lsc,
                  const T* opac, const T* sh0, const T* shN, T* o_m2, T* o_con, T* o_z,
                  int32_t* o_rad, T* o_op, T* o_col, T* o_sl, T* o_nrm) {
  const int nb = (cam.sh_degree + 1) * (cam.sh_degree + 1);
#pragma omp parallel for num_threads(threads_for(N)) schedule(static)
  for (int64_t i = 0; i < N; ++i) {
    Geo<T> g;
    int32_t rad = 0;
    if (to_camera(cam, means + 3 * i, g)) {
      ewa(cam, quats + 4 * i, lsc + 3 * i, g);
      rad = radius_of(cam, g);
    }
    o_rad[i] = rad;
    if (rad == 0) {
      o_m2[2 * i] = o_m2[2 * i + 1] = T(0);
      o_con[3 * i] = o_con[3 * i + 1] = o_con[3 * i + 2] = T(0);
      o_z[i] = T(1);
      o_op[i] = T(0);
      for (int k = 0; k < 3; ++k) o_col[3 * i + k] = o_nrm[3 * i + k] = T(0);
      o_sl[2 * i] = o_sl[2 * i + 1] = T(0);
      continue;
    }
    o_m2[2 * i] = g.m2[0]; o_m2[2 * i + 1] = g.m2[1];
    for (int k = 0; k < 3; ++k) o_con[3 * i + k] = g.conic[k];
    o_z[i] = g.p[2];
    T op = T(1) / (T(1) + std::exp(-opac[i]));
    if (cam.antialiased) op = op * std::sqrt(std::max(g.det / g.Dlp, T(1e-12)));
    o_op[i] = op;
    T d[3], Y[16];
    view_dir(g.rel, d);
    sh_basis(cam.sh_degree, d, Y);
    for (int ch = 0; ch < 3; ++ch) {
      T acc = T(0);
      for (int k = 0; k < nb; ++k) acc += Y[k] * coeff(sh0, shN, cam, i, k, ch);
      o_col[3 * i + ch] = std::max(acc + T(0.5), T(0));
    }
    Plane<T> P;
    plane_of(cam, lsc + 3 * i, g, P);
    o_sl[2 * i] = P.slope[0]; o_sl[2 * i + 1] = P.slope[1];
    for (int k = 0; k < 3; ++k) o_nrm[3 * i + k] = P.normal[k];
  }
}

// Gradients of one visible Gaussian (the chain rule of forward_impl, last operation first).
template <typename T>
void backward_one(const Cam<T>& cam, int64_t i, const T* means, const T* quats, const T* lsc,
                  const T* opac, const T* sh0, const T* shN, const T* g_m2, const T* g_con,
                  const T* g_z, const T* g_op, const T* g_col, const T* g_sl, const T* g_nrm,
                  T* d_mean, T* d_quat, T* d_ls, T* d_op, T* d_sh0, T* d_shN, bool geometry) {
  Geo<T> g;
  to_camera(cam, means + 3 * i, g);
  if (geometry) ewa(cam, quats + 4 * i, lsc + 3 * i, g);
  const T* ls = lsc + 3 * i;
  const T x = g.p[0], y = g.p[1], z = g.p[2], e = cam.eps2d;
  T p_bar[3] = {T(0), T(0), g_z[i]}, rel_bar[3] = {T(0), T(0), T(0)};
  T a_bar = 0, b_bar = 0, c_bar = 0, det_bar = 0, Dlp_bar = 0, A_bar[9] = {}, ls_bar[3] = {};

  // colour = max(0, sum_k Y_k c_k + 0.5), dir = rel / |rel|
  const int nb = (cam.sh_degree + 1) * (cam.sh_degree + 1);
  T d[3], Y[16], v[16];
  const T inv_rel = view_dir(g.rel, d);
  sh_basis(cam.sh_degree, d, Y);
  T gc[3];
  for (int ch = 0; ch < 3; ++ch) {
    T acc = T(0);
    for (int k = 0; k < nb; ++k) acc += Y[k] * coeff(sh0, shN, cam, i, k, ch);
    gc[ch] = acc + T(0.5) >= T(0) ? g_col[3 * i + ch] : T(0);
  }
  for (int k = 0; k < nb; ++k) {
    v[k] = T(0);
    for (int ch = 0; ch < 3; ++ch) {
      v[k] += gc[ch] * coeff(sh0, shN, cam, i, k, ch);
      T* dst = k == 0 ? d_sh0 + 3 * i + ch : d_shN + (i * cam.sh_rest + (k - 1)) * 3 + ch;
      *dst = Y[k] * gc[ch];
    }
  }
  if (!geometry) return;  // the colours' gradient alone (a frozen geometry: splat/frozen.py)
  T d_bar[3] = {T(0), T(0), T(0)};
  sh_basis_vjp(cam.sh_degree, d, v, d_bar);
  const T rr = g.rel[0] * g.rel[0] + g.rel[1] * g.rel[1] + g.rel[2] * g.rel[2];
  const T dd = rr >= T(1e-24) ? d[0] * d_bar[0] + d[1] * d_bar[1] + d[2] * d_bar[2] : T(0);
  for (int k = 0; k < 3; ++k) rel_bar[k] += (d_bar[k] - d[k] * dd) * inv_rel;

  // opacity = sigmoid(o) [* sqrt(max(det / Dlp, 1e-12))]
  const T sig = T(1) / (T(1) + std::exp(-opac[i]));
  T sig_bar = g_op[i];
  if (cam.antialiased) {
    const T ratio = g.det / g.Dlp, sq = std::sqrt(std::max(ratio, T(1e-12)));
    sig_bar = g_op[i] * sq;
    const T ratio_bar = ratio >= T(1e-12) ? g_op[i] * sig * T(0.5) / sq : T(0);
    det_bar += ratio_bar / g.Dlp;
    // d ratio / d Dlp = -(det / Dlp) / Dlp, in torch's order: det / Dlp^2 overflowed float32 (Dlp ~ 1e36
    // for a huge Gaussian seen up close, log-scale 40) and gave inf / inf = NaN (fuzz finding,
    // tests/test_fuzz_render.py)
    Dlp_bar += -ratio_bar * (ratio / g.Dlp);
  }
  d_op[i] = sig_bar * sig * (T(1) - sig);

  // means2d = (fx x / z + cx, fy y / z + cy)
  const T gm0 = g_m2[2 * i], gm1 = g_m2[2 * i + 1];
  p_bar[0] += cam.fx * gm0 / z;
  p_bar[1] += cam.fy * gm1 / z;
  p_bar[2] += -(cam.fx * x * gm0 + cam.fy * y * gm1) / (z * z);

  // conic = (c + e, -b, a + e) / Dlp,  Dlp = det + e (a + c) + e^2
  const T g0 = g_con[3 * i], g1 = g_con[3 * i + 1], g2 = g_con[3 * i + 2];
  c_bar += g0 / g.Dlp;
  b_bar += -g1 / g.Dlp;
  a_bar += g2 / g.Dlp;
  Dlp_bar += -(g0 * g.conic[0] + g1 * g.conic[1] + g2 * g.conic[2]) / g.Dlp;  // not / Dlp^2: overflow (above)
  det_bar += Dlp_bar;
  a_bar += e * Dlp_bar;
  c_bar += e * Dlp_bar;

  // (a, b, c) = (M0.M0, M0.M1, M1.M1), det = sum of squared 2x2 minors of M
  const T* M = g.M;
  T Mb[6];
  for (int j = 0; j < 3; ++j) {
    Mb[j] = T(2) * a_bar * M[j] + b_bar * M[3 + j];
    Mb[3 + j] = b_bar * M[j] + T(2) * c_bar * M[3 + j];
  }
  const T m0b = T(2) * g.mn[0] * det_bar, m1b = T(2) * g.mn[1] * det_bar, m2b = T(2) * g.mn[2] * det_bar;
  Mb[0] += m0b * M[4] + m1b * M[5];
  Mb[4] += m0b * M[0] - m2b * M[2];
  Mb[1] += -m0b * M[3] + m2b * M[5];
  Mb[3] += -m0b * M[1] - m1b * M[2];
  Mb[5] += m1b * M[0] + m2b * M[1];
  Mb[2] += -m1b * M[3] - m2b * M[4];
  for (int j = 0; j < 6; ++j)
    if (!g.M_in[j]) Mb[j] = T(0);

  // M0 = ux RS0 - vx RS2, M1 = uy RS1 - vy RS2 with u = f / z, v = f t / z^2
  const T iz = g.inv_z;
  const T ux = cam.fx * iz, vx = cam.fx * g.tx * iz * iz, uy = cam.fy * iz, vy = cam.fy * g.ty * iz * iz;
  T RS_bar[9];
  T ux_bar = 0, vx_bar = 0, uy_bar = 0, vy_bar = 0;
  for (int j = 0; j < 3; ++j) {
    RS_bar[j] = ux * Mb[j];
    RS_bar[3 + j] = uy * Mb[3 + j];
    RS_bar[6 + j] = -vx * Mb[j] - vy * Mb[3 + j];
    ux_bar += Mb[j] * g.RS[j];
    vx_bar -= Mb[j] * g.RS[6 + j];
    uy_bar += Mb[3 + j] * g.RS[3 + j];
    vy_bar -= Mb[3 + j] * g.RS[6 + j];
  }
  const T iz_bar = cam.fx * ux_bar + T(2) * cam.fx * g.tx * iz * vx_bar + cam.fy * uy_bar +
                   T(2) * cam.fy * g.ty * iz * vy_bar;
  const T tx_bar = cam.fx * iz * iz * vx_bar, ty_bar = cam.fy * iz * iz * vy_bar;
  p_bar[2] += -iz * iz * iz_bar;
  // t = z clamp(x / z, lo, hi)
  p_bar[2] += g.clx * tx_bar + g.cly * ty_bar;
  const T xz_bar = g.x_in ? z * tx_bar : T(0), yz_bar = g.y_in ? z * ty_bar : T(0);
  p_bar[0] += xz_bar / z;
  p_bar[1] += yz_bar / z;
  p_bar[2] += -(xz_bar * x + yz_bar * y) / (z * z);

  // RaDe-GS slopes and normals
  Plane<T> P;
  plane_of(cam, ls, g, P);
  T nh_bar[3];
  for (int k = 0; k < 3; ++k) nh_bar[k] = P.r0n < 0 ? g_nrm[3 * i + k] : -g_nrm[3 * i + k];
  const T qx_bar = g_sl[2 * i] / cam.fx, qy_bar = g_sl[2 * i + 1] / cam.fy;
  p_bar[2] += -(P.nh[0] * qx_bar + P.nh[1] * qy_bar) / P.denom;
  nh_bar[0] += -z * qx_bar / P.denom;
  nh_bar[1] += -z * qy_bar / P.denom;
  const T denom_bar = z * (P.nh[0] * qx_bar + P.nh[1] * qy_bar) / (P.denom * P.denom);
  const T mx_bar = denom_bar * P.sgn;  // torch.maximum: ties split the gradient
  const T absr_bar = P.absr > P.mc ? mx_bar : (P.absr == P.mc ? T(0.5) * mx_bar : T(0));
  const T mc_bar = P.mc > P.absr ? mx_bar : (P.absr == P.mc ? T(0.5) * mx_bar : T(0));
  const T r0n_bar = absr_bar * (P.r0n > 0 ? T(1) : (P.r0n < 0 ? T(-1) : T(0)));
  const T r0norm_bar = mc_bar * cam.min_cos;
  T r0_bar[3];
  for (int k = 0; k < 3; ++k) {
    r0_bar[k] = r0n_bar * P.nh[k] + r0norm_bar * P.r0[k] / P.r0norm;
    nh_bar[k] += r0n_bar * P.r0[k];
  }
  T n_bar[3];
  const T nd = P.n_big ? P.nh[0] * nh_bar[0] + P.nh[1] * nh_bar[1] + P.nh[2] * nh_bar[2] : T(0);
  for (int k = 0; k < 3; ++k) n_bar[k] = (nh_bar[k] - P.nh[k] * nd) * P.inv_n;
  T local_bar[3];
  T ls_min_bar = 0;
  for (int j = 0; j < 3; ++j) {
    const T t_bar = g.A[j] * n_bar[0] + g.A[3 + j] * n_bar[1] + g.A[6 + j] * n_bar[2];
    for (int k = 0; k < 3; ++k) A_bar[3 * k + j] += n_bar[k] * P.t[j];
    local_bar[j] = t_bar * P.w[j];
    if (P.wkeep[j]) {  // w = exp(2 (ls_min - ls_j))
      const T e_bar = t_bar * P.local[j] * P.w[j];
      ls_min_bar += T(2) * e_bar;
      ls_bar[j] -= T(2) * e_bar;
    }
  }
  ls_bar[P.jmin] += ls_min_bar;
  for (int k = 0; k < 3; ++k)
    for (int j = 0; j < 3; ++j) {
      A_bar[3 * k + j] += P.r0[k] * local_bar[j];
      r0_bar[k] += g.A[3 * k + j] * local_bar[j];
    }
  p_bar[0] += r0_bar[0] / z;
  p_bar[1] += r0_bar[1] / z;
  p_bar[2] += -(x * r0_bar[0] + y * r0_bar[1]) / (z * z);

  // RS = A diag(s), s = exp(ls)
  for (int j = 0; j < 3; ++j) {
    T s_bar = 0;
    for (int k = 0; k < 3; ++k) {
      A_bar[3 * k + j] += RS_bar[3 * k + j] * g.s[j];
      s_bar += RS_bar[3 * k + j] * g.A[3 * k + j];
    }
    ls_bar[j] += s_bar * g.s[j];
  }
  for (int j = 0; j < 3; ++j) d_ls[3 * i + j] = ls_bar[j];

  // A = R Rot  ->  Rot_bar = R^T A_bar;  Rot(qn) -> qn_bar;  qn = q / max(|q|, 1e-6)
  T Rb[9];
  for (int k = 0; k < 3; ++k)
    for (int j = 0; j < 3; ++j)
      Rb[3 * k + j] = cam.R[k] * A_bar[j] + cam.R[3 + k] * A_bar[3 + j] + cam.R[6 + k] * A_bar[6 + j];
  const T w = g.qn[0], qx = g.qn[1], qy = g.qn[2], qz = g.qn[3];
  T qb[4];
  qb[0] = T(2) * (-Rb[1] * qz + Rb[2] * qy + Rb[3] * qz - Rb[5] * qx - Rb[6] * qy + Rb[7] * qx);
  qb[1] = T(2) * (Rb[1] * qy + Rb[2] * qz + Rb[3] * qy - Rb[5] * w + Rb[6] * qz + Rb[7] * w) -
          T(4) * qx * (Rb[4] + Rb[8]);
  qb[2] = T(2) * (Rb[1] * qx + Rb[2] * w + Rb[3] * qx + Rb[5] * qz - Rb[6] * w + Rb[7] * qz) -
          T(4) * qy * (Rb[0] + Rb[8]);
  qb[3] = T(2) * (-Rb[1] * w + Rb[2] * qx + Rb[3] * w + Rb[5] * qy + Rb[6] * qx + Rb[7] * qy) -
          T(4) * qz * (Rb[0] + Rb[4]);
  const T qd = g.q_big ? w * qb[0] + qx * qb[1] + qy * qb[2] + qz * qb[3] : T(0);
  for (int k = 0; k < 4; ++k) d_quat[4 * i + k] = (qb[k] - g.qn[k] * qd) * g.q_inv;

  // p = R rel, rel = mean - C
  for (int k = 0; k < 3; ++k)
    d_mean[3 * i + k] = rel_bar[k] + cam.R[k] * p_bar[0] + cam.R[3 + k] * p_bar[1] + cam.R[6 + k] * p_bar[2];
}

template <typename T>
void backward_impl(const Cam<T>& cam, int64_t N, const int32_t* radii, const T* means,
                   const T* quats, const T* lsc, const T* opac, const T* sh0, const T* shN,
                   const T* g_m2, const T* g_con, const T* g_z, const T* g_op, const T* g_col,
                   const T* g_sl, const T* g_nrm, T* d_mean, T* d_quat, T* d_ls, T* d_op,
                   T* d_sh0, T* d_shN, bool geometry) {
  const int64_t rest = cam.sh_rest;
#pragma omp parallel for num_threads(threads_for(N)) schedule(static)
  for (int64_t i = 0; i < N; ++i) {
    if (radii[i] == 0) {
      for (int k = 0; k < 3; ++k) d_sh0[3 * i + k] = T(0);
      if (geometry) {
        for (int k = 0; k < 3; ++k) d_mean[3 * i + k] = d_ls[3 * i + k] = T(0);
        for (int k = 0; k < 4; ++k) d_quat[4 * i + k] = T(0);
        d_op[i] = T(0);
      }
      std::fill(d_shN + i * rest * 3, d_shN + (i + 1) * rest * 3, T(0));
      continue;
    }
    // coefficients above the rendered degree get zero gradient
    const int64_t used = (cam.sh_degree + 1) * (cam.sh_degree + 1) - 1;
    std::fill(d_shN + (i * rest + used) * 3, d_shN + (i + 1) * rest * 3, T(0));
    backward_one(cam, i, means, quats, lsc, opac, sh0, shN, g_m2, g_con, g_z, g_op, g_col, g_sl,
                 g_nrm, d_mean, d_quat, d_ls, d_op, d_sh0, d_shN, geometry);
  }
}

void check(const std::vector<torch::Tensor>& ts) {
  for (const auto& t : ts) {
    TORCH_CHECK(t.device().is_cpu() && t.is_contiguous(), "project_cpu: tensors must be contiguous CPU");
    TORCH_CHECK(t.scalar_type() == ts[0].scalar_type(), "project_cpu: mixed float dtypes");
  }
}

}  // namespace project_cpu

std::vector<torch::Tensor> project_forward(torch::Tensor means, torch::Tensor quats,
                                           torch::Tensor log_scales, torch::Tensor opacities,
                                           torch::Tensor sh0, torch::Tensor shN, torch::Tensor R,
                                           torch::Tensor C, torch::Tensor K, int64_t W, int64_t H,
                                           double near, double far, double eps2d, double min_cos,
                                           bool antialiased, int64_t sh_degree) {
  using namespace project_cpu;
  check({means, quats, log_scales, opacities, sh0, shN, R, C, K});
  TORCH_CHECK(sh_degree >= 0 && sh_degree <= 3 && (sh_degree + 1) * (sh_degree + 1) - 1 <= shN.size(1),
              "project_cpu: SH degree ", sh_degree, " needs more coefficients than shN holds");
  const int64_t N = means.size(0);
  auto o = means.options();
  torch::Tensor m2 = torch::empty({N, 2}, o), con = torch::empty({N, 3}, o), z = torch::empty({N}, o);
  torch::Tensor rad = torch::empty({N}, o.dtype(torch::kInt32)), op = torch::empty({N}, o);
  torch::Tensor col = torch::empty({N, 3}, o), sl = torch::empty({N, 2}, o), nrm = torch::empty({N, 3}, o);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_forward", [&] {
    auto cam = make_cam<scalar_t>(R, C, K, W, H, near, far, eps2d, min_cos, antialiased, sh_degree,
                                  shN.size(1));
    forward_impl<scalar_t>(cam, N, means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
                           log_scales.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(),
                           sh0.data_ptr<scalar_t>(), shN.data_ptr<scalar_t>(), m2.data_ptr<scalar_t>(),
                           con.data_ptr<scalar_t>(), z.data_ptr<scalar_t>(), rad.data_ptr<int32_t>(),
                           op.data_ptr<scalar_t>(), col.data_ptr<scalar_t>(), sl.data_ptr<scalar_t>(),
                           nrm.data_ptr<scalar_t>());
  });
  return {m2, con, z, rad, op, col, sl, nrm};
}

std::vector<torch::Tensor> project_backward(
    torch::Tensor means, torch::Tensor quats, torch::Tensor log_scales, torch::Tensor opacities,
    torch::Tensor sh0, torch::Tensor shN, torch::Tensor R, torch::Tensor C, torch::Tensor K,
    torch::Tensor radii, torch::Tensor g_m2, torch::Tensor g_con, torch::Tensor g_z,
    torch::Tensor g_op, torch::Tensor g_col, torch::Tensor g_sl, torch::Tensor g_nrm, int64_t W,
    int64_t H, double near, double far, double eps2d, double min_cos, bool antialiased,
    int64_t sh_degree, bool geometry) {
  using namespace project_cpu;
  check({means, quats, log_scales, opacities, sh0, shN, R, C, K, g_m2, g_con, g_z, g_op, g_col,
         g_sl, g_nrm});
  TORCH_CHECK(radii.scalar_type() == torch::kInt32 && radii.is_contiguous(), "radii must be int32");
  const int64_t N = means.size(0);
  // without the geometry's gradients (geometry false) their tensors are empty and never written
  auto grad_of = [&](const torch::Tensor& t) { return geometry ? torch::empty_like(t) : torch::empty({0}, t.options()); };
  torch::Tensor d_mean = grad_of(means), d_quat = grad_of(quats), d_ls = grad_of(log_scales), d_op = grad_of(opacities);
  torch::Tensor d_sh0 = torch::empty_like(sh0), d_shN = torch::empty_like(shN);
  AT_DISPATCH_FLOATING_TYPES(means.scalar_type(), "project_backward", [&] {
    auto cam = make_cam<scalar_t>(R, C, K, W, H, near, far, eps2d, min_cos, antialiased, sh_degree,
                                  shN.size(1));
    backward_impl<scalar_t>(
        cam, N, radii.data_ptr<int32_t>(), means.data_ptr<scalar_t>(), quats.data_ptr<scalar_t>(),
        log_scales.data_ptr<scalar_t>(), opacities.data_ptr<scalar_t>(), sh0.data_ptr<scalar_t>(),
        shN.data_ptr<scalar_t>(), g_m2.data_ptr<scalar_t>(), g_con.data_ptr<scalar_t>(),
        g_z.data_ptr<scalar_t>(), g_op.data_ptr<scalar_t>(), g_col.data_ptr<scalar_t>(),
        g_sl.data_ptr<scalar_t>(), g_nrm.data_ptr<scalar_t>(), d_mean.data_ptr<scalar_t>(),
        d_quat.data_ptr<scalar_t>(), d_ls.data_ptr<scalar_t>(), d_op.data_ptr<scalar_t>(),
        d_sh0.data_ptr<scalar_t>(), d_shN.data_ptr<scalar_t>(), geometry);
  });
  return {d_mean, d_quat, d_ls, d_op, d_sh0, d_shN};
}
