#pragma once
// EWA projection of one 3D Gaussian and its vector-Jacobian product.
// The CPU kernel, the CUDA kernel and (through the same formulas written in
// PyTorch) the float64 reference in tiger/render/reference.py all follow this file.
#include <math.h>
#include <stdint.h>

#include "linalg.h"

namespace tiger {

template <typename T>
struct Camera {
  Mat3<T> R;  // world->camera rotation (top-left of viewmat)
  Vec3<T> t;  // world->camera translation
  T fx, fy, cx, cy;
  int width, height;
};

template <typename T>
struct ProjectOptions {
  T eps2d;            // dilation added to the 2D covariance diagonal [px^2]
  T near_plane;       // cull z <= near
  T far_plane;        // cull z >= far
  T alpha_threshold;  // a Gaussian contributes nowhere o*G falls below this
  bool antialiased;   // scale opacity by sqrt(det(cov) / det(cov + eps I))
};

template <typename T>
struct Projected {
  T u, v;          // pixel-space mean
  T ca, cb, cc;    // conic = inverse dilated covariance [[ca, cb], [cb, cc]]
  T depth;         // camera-space z
  T opacity;       // opacity after antialiasing compensation
  T ext_x, ext_y;  // opacity-aware half extents [px]
};

// Rotation from a (w, x, y, z) quaternion already normalised.
template <typename T>
TIGER_HD Mat3<T> quat_to_rotmat(T w, T x, T y, T z) {
  Mat3<T> r;
  r.m[0][0] = T(1) - T(2) * (y * y + z * z);
  r.m[0][1] = T(2) * (x * y - w * z);
  r.m[0][2] = T(2) * (x * z + w * y);
  r.m[1][0] = T(2) * (x * y + w * z);
  r.m[1][1] = T(1) - T(2) * (x * x + z * z);
  r.m[1][2] = T(2) * (y * z - w * x);
  r.m[2][0] = T(2) * (x * z - w * y);
  r.m[2][1] = T(2) * (y * z + w * x);
  r.m[2][2] = T(1) - T(2) * (x * x + y * y);
  return r;
}

// d(loss)/d(w,x,y,z) of the normalised quaternion, given d(loss)/dR.
template <typename T>
TIGER_HD void quat_to_rotmat_vjp(T w, T x, T y, T z, const Mat3<T>& g, T out[4]) {
  const auto& v = g.m;
  out[0] = T(2) * (-z * v[0][1] + y * v[0][2] + z * v[1][0] - x * v[1][2] - y * v[2][0] + x * v[2][1]);
  out[1] = T(2) * (y * v[0][1] + z * v[0][2] + y * v[1][0] - T(2) * x * v[1][1] - w * v[1][2] +
                   z * v[2][0] + w * v[2][1] - T(2) * x * v[2][2]);
  out[2] = T(2) * (-T(2) * y * v[0][0] + x * v[0][1] + w * v[0][2] + x * v[1][0] + z * v[1][2] -
                   w * v[2][0] + z * v[2][1] - T(2) * y * v[2][2]);
  out[3] = T(2) * (-T(2) * z * v[0][0] - w * v[0][1] + x * v[0][2] + w * v[1][0] -
                   T(2) * z * v[1][1] + y * v[1][2] + x * v[2][0] + y * v[2][1]);
}

// Smallest quaternion norm used when normalising, so a zero quaternion gives
// the identity rotation instead of NaN.
template <typename T>
TIGER_HD T quat_norm_floor() {
  return T(1e-12);
}

// Camera-space x/z is clamped to a little beyond the field of view before the
// Jacobian is formed (as 3DGS does), so Gaussians far off-axis do not explode.
// Returns the clamped tx = z * clamp(x/z) and its partials.
template <typename T>
struct ClampedCoord {
  T t, dx, dz, df, dc;
};

template <typename T>
TIGER_HD ClampedCoord<T> clamp_to_frustum(T x, T z, T f, T c, int size) {
  const T slack = T(0.15) * T(size);  // 0.3 * tan(fov/2) * f
  const T lim_pos = (T(size) - c + slack) / f;
  const T lim_neg = (c + slack) / f;
  const T r = x / z;
  ClampedCoord<T> o;
  if (r > lim_pos) {
    o = {z * lim_pos, T(0), lim_pos, -z * lim_pos / f, -z / f};
  } else if (r < -lim_neg) {
    o = {-z * lim_neg, T(0), -lim_neg, z * lim_neg / f, -z / f};
  } else {
    o = {x, T(1), T(0), T(0), T(0)};
  }
  return o;
}

// Intermediate terms of the EWA projection, shared by the forward and its VJP
// (which recomputes them rather than storing them per Gaussian).
template <typename T>
struct EwaTerms {
  Vec3<T> p;                  // camera-space mean
  T qn, qw, qx, qy, qz;       // quaternion norm (floored) and the normalised quaternion
  Mat3<T> Rq, W, M;           // local rotation, W = R Rq, M = W diag(scale)
  ClampedCoord<T> tx, ty;     // frustum-clamped x, y for the Jacobian
  T iz, j00, j02, j11, j12;   // 1/z and the Jacobian J = [[j00, 0, j02], [0, j11, j12]]
  T a0[3], a1[3];             // rows of J M: cov2d = (J M)(J M)^T
  T ca0, cb0, cc0;            // 2D covariance before dilation
  T ca, cc, det;              // dilated diagonal and determinant
};

template <typename T>
TIGER_HD EwaTerms<T> ewa_terms(const T* mean, const T* quat, const T* scale, const Camera<T>& cam,
                               const ProjectOptions<T>& opt) {
  EwaTerms<T> e;
  e.p = matvec(cam.R, Vec3<T>{mean[0], mean[1], mean[2]}) + cam.t;
  T qn = sqrt(quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3]);
  e.qn = qn > quat_norm_floor<T>() ? qn : quat_norm_floor<T>();
  e.qw = quat[0] / e.qn, e.qx = quat[1] / e.qn, e.qy = quat[2] / e.qn, e.qz = quat[3] / e.qn;
  e.Rq = quat_to_rotmat(e.qw, e.qx, e.qy, e.qz);
  e.W = matmul(cam.R, e.Rq);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) e.M.m[i][j] = e.W.m[i][j] * scale[j];
  e.tx = clamp_to_frustum(e.p.x, e.p.z, cam.fx, cam.cx, cam.width);
  e.ty = clamp_to_frustum(e.p.y, e.p.z, cam.fy, cam.cy, cam.height);
  e.iz = T(1) / e.p.z;
  e.j00 = cam.fx * e.iz, e.j02 = -cam.fx * e.tx.t * e.iz * e.iz;
  e.j11 = cam.fy * e.iz, e.j12 = -cam.fy * e.ty.t * e.iz * e.iz;
  for (int k = 0; k < 3; ++k) {
    e.a0[k] = e.j00 * e.M.m[0][k] + e.j02 * e.M.m[2][k];
    e.a1[k] = e.j11 * e.M.m[1][k] + e.j12 * e.M.m[2][k];
  }
  e.ca0 = e.a0[0] * e.a0[0] + e.a0[1] * e.a0[1] + e.a0[2] * e.a0[2];
  e.cb0 = e.a0[0] * e.a1[0] + e.a0[1] * e.a1[1] + e.a0[2] * e.a1[2];
  e.cc0 = e.a1[0] * e.a1[0] + e.a1[1] * e.a1[1] + e.a1[2] * e.a1[2];
  e.ca = e.ca0 + opt.eps2d;
  e.cc = e.cc0 + opt.eps2d;
  e.det = e.ca * e.cc - e.cb0 * e.cb0;
  return e;
}

// Forward projection. Returns false when the Gaussian is culled (outside
// near/far, degenerate covariance, opacity below the threshold, or off screen).
template <typename T>
TIGER_HD bool project_gaussian(const T* mean, const T* quat, const T* scale, T opacity,
                               const Camera<T>& cam, const ProjectOptions<T>& opt, Projected<T>& out) {
  const Vec3<T> p = matvec(cam.R, Vec3<T>{mean[0], mean[1], mean[2]}) + cam.t;
  if (!(p.z > opt.near_plane && p.z < opt.far_plane)) return false;
  const EwaTerms<T> e = ewa_terms(mean, quat, scale, cam, opt);
  const T ca0 = e.ca0, cb0 = e.cb0, cc0 = e.cc0, ca = e.ca, cc = e.cc, det = e.det;
  const T iz = e.iz;
  if (!(det > T(0)) || !isfinite(det)) return false;

  T o = opacity;
  if (opt.antialiased) {
    const T det0 = ca0 * cc0 - cb0 * cb0;
    o *= sqrt((det0 > T(0) ? det0 : T(0)) / det);
  }
  if (!(o >= opt.alpha_threshold)) return false;

  const T inv = T(1) / det;
  out.u = cam.fx * e.p.x * iz + cam.cx;
  out.v = cam.fy * e.p.y * iz + cam.cy;
  out.ca = cc * inv;
  out.cb = -cb0 * inv;
  out.cc = ca * inv;
  out.depth = e.p.z;
  out.opacity = o;
  // Opacity-aware extent: o * exp(-q/2) >= threshold  <=>  q <= 2 log(o / threshold);
  // the ellipse's axis-aligned half widths are sqrt(k2 * cov_xx), sqrt(k2 * cov_yy).
  const T k2 = T(2) * log(o / opt.alpha_threshold);
  out.ext_x = sqrt(k2 * ca);
  out.ext_y = sqrt(k2 * cc);
  if (!(out.u + out.ext_x > T(0) && out.u - out.ext_x < T(cam.width) && out.v + out.ext_y > T(0) &&
        out.v - out.ext_y < T(cam.height)))
    return false;
  return true;
}

// Extents are stored as int32 pixels; huge Gaussians saturate instead of overflowing.
template <typename T>
TIGER_HD int32_t extent_to_radius(T e) {
  const T r = ceil(e);
  return r > T(1 << 30) ? (1 << 30) : static_cast<int32_t>(r);
}

// Writes Gaussian i's projection into the op's outputs (means2d [N,2], conics [N,3],
// depths [N], opacities [N], radii [N,2] with a floor of 1 so that 0 keeps meaning culled).
template <typename T>
TIGER_HD void store_projected(const Projected<T>& pr, int64_t i, T* means2d, T* conics, T* depths,
                              T* opacities, int32_t* radii) {
  means2d[2 * i] = pr.u;
  means2d[2 * i + 1] = pr.v;
  conics[3 * i] = pr.ca;
  conics[3 * i + 1] = pr.cb;
  conics[3 * i + 2] = pr.cc;
  depths[i] = pr.depth;
  opacities[i] = pr.opacity;
  const int32_t rx = extent_to_radius(pr.ext_x), ry = extent_to_radius(pr.ext_y);
  radii[2 * i] = rx > 1 ? rx : 1;
  radii[2 * i + 1] = ry > 1 ? ry : 1;
}

// Gradients of one projected Gaussian. Inputs: the upstream gradients of the
// projection's outputs. Outputs are accumulated (+=) into v_* arrays;
// v_R/v_t/v_K (fx, fy, cx, cy) are this Gaussian's share of the camera gradient.
template <typename T>
struct ProjectionGrads {
  T mean[3], quat[4], scale[3], opacity;
  Mat3<T> R;
  T t[3];
  T K[4];  // fx, fy, cx, cy
};

template <typename T>
TIGER_HD void project_gaussian_vjp(const T* mean, const T* quat, const T* scale, T opacity,
                                   const Camera<T>& cam, const ProjectOptions<T>& opt, T v_u, T v_v,
                                   T v_ca, T v_cb, T v_cc, T v_depth, T v_opac,
                                   ProjectionGrads<T>& g) {
  // The forward intermediates, recomputed by the same function.
  const EwaTerms<T> e = ewa_terms(mean, quat, scale, cam, opt);
  const Vec3<T> p = e.p;
  const T qn = e.qn, qw = e.qw, qx = e.qx, qy = e.qy, qz = e.qz;
  const Mat3<T>&Rq = e.Rq, &W = e.W, &M = e.M;
  const ClampedCoord<T>&tx = e.tx, &ty = e.ty;
  const T iz = e.iz, iz2 = iz * iz;
  const T j00 = e.j00, j02 = e.j02, j11 = e.j11, j12 = e.j12;
  const T *a0 = e.a0, *a1 = e.a1;
  const T ca0 = e.ca0, cb0 = e.cb0, cc0 = e.cc0, ca = e.ca, cc = e.cc, det = e.det;
  const T inv = T(1) / det;
  const T Ka = cc * inv, Kb = -cb0 * inv, Kc = ca * inv;  // conic

  // Opacity and antialiasing compensation.
  T comp = T(1);
  T g_ca0 = T(0), g_cb0 = T(0), g_cc0 = T(0);  // gradient w.r.t. undilated covariance entries
  if (opt.antialiased) {
    const T det0 = ca0 * cc0 - cb0 * cb0;
    const T c2 = (det0 > T(0) ? det0 : T(0)) * inv;
    comp = sqrt(c2);
    if (comp > T(0)) {
      // d(comp^2)/d(a,b,c) = conic * (1 - comp^2) - eps / det on the diagonal.
      const T v_c2 = v_opac * opacity * T(0.5) / comp;
      const T one_m = T(1) - c2;
      g_ca0 += v_c2 * (Ka * one_m - opt.eps2d * inv);
      g_cb0 += v_c2 * (T(2) * Kb * one_m);
      g_cc0 += v_c2 * (Kc * one_m - opt.eps2d * inv);
    }
  }
  g.opacity += v_opac * comp;

  // Conic = inverse(cov): dL/dcov = -K G K with G the symmetric gradient of K.
  {
    const T G00 = v_ca, G01 = T(0.5) * v_cb, G11 = v_cc;
    // K G
    const T KG00 = Ka * G00 + Kb * G01, KG01 = Ka * G01 + Kb * G11;
    const T KG10 = Kb * G00 + Kc * G01, KG11 = Kb * G01 + Kc * G11;
    const T S00 = -(KG00 * Ka + KG01 * Kb);
    const T S01 = -(KG00 * Kb + KG01 * Kc);
    const T S11 = -(KG10 * Kb + KG11 * Kc);
    g_ca0 += S00;
    g_cb0 += T(2) * S01;  // cb0 appears at (0,1) and (1,0)
    g_cc0 += S11;
  }
  // cov0 = A A^T with rows a0, a1:  dL/da0 = 2 g_ca0 a0 + g_cb0 a1, dL/da1 = g_cb0 a0 + 2 g_cc0 a1.
  T v_a0[3], v_a1[3];
  for (int k = 0; k < 3; ++k) {
    v_a0[k] = T(2) * g_ca0 * a0[k] + g_cb0 * a1[k];
    v_a1[k] = g_cb0 * a0[k] + T(2) * g_cc0 * a1[k];
  }
  // a0 = j00 M[0] + j02 M[2];  a1 = j11 M[1] + j12 M[2]
  T v_j00 = T(0), v_j02 = T(0), v_j11 = T(0), v_j12 = T(0);
  Mat3<T> v_M;
  for (int k = 0; k < 3; ++k) {
    v_j00 += v_a0[k] * M.m[0][k];
    v_j02 += v_a0[k] * M.m[2][k];
    v_j11 += v_a1[k] * M.m[1][k];
    v_j12 += v_a1[k] * M.m[2][k];
    v_M.m[0][k] = v_a0[k] * j00;
    v_M.m[1][k] = v_a1[k] * j11;
    v_M.m[2][k] = v_a0[k] * j02 + v_a1[k] * j12;
  }
  // Camera-space point p: mean2d, depth, and the Jacobian entries.
  T v_px = v_u * cam.fx * iz;
  T v_py = v_v * cam.fy * iz;
  T v_pz = v_depth - v_u * cam.fx * p.x * iz2 - v_v * cam.fy * p.y * iz2;
  T v_fx = v_u * p.x * iz, v_fy = v_v * p.y * iz, v_cx = v_u, v_cy = v_v;
  // j00 = fx/z, j11 = fy/z
  v_pz += -v_j00 * cam.fx * iz2 - v_j11 * cam.fy * iz2;
  v_fx += v_j00 * iz;
  v_fy += v_j11 * iz;
  // j02 = -fx tx / z^2 with tx = tx(x, z, fx, cx)
  {
    const T d_tx = -cam.fx * iz2;  // dj02/dtx
    v_px += v_j02 * d_tx * tx.dx;
    v_pz += v_j02 * (T(2) * cam.fx * tx.t * iz2 * iz + d_tx * tx.dz);
    v_fx += v_j02 * (-tx.t * iz2 + d_tx * tx.df);
    v_cx += v_j02 * d_tx * tx.dc;
    const T d_ty = -cam.fy * iz2;
    v_py += v_j12 * d_ty * ty.dx;
    v_pz += v_j12 * (T(2) * cam.fy * ty.t * iz2 * iz + d_ty * ty.dz);
    v_fy += v_j12 * (-ty.t * iz2 + d_ty * ty.df);
    v_cy += v_j12 * d_ty * ty.dc;
  }
  g.K[0] += v_fx;
  g.K[1] += v_fy;
  g.K[2] += v_cx;
  g.K[3] += v_cy;

  // M = W diag(s), W = R Rq
  Mat3<T> v_W;
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) {
      v_W.m[i][j] = v_M.m[i][j] * scale[j];
      g.scale[j] += v_M.m[i][j] * W.m[i][j];
    }
  const Mat3<T> v_Rq = matmul(transpose(cam.R), v_W);
  g.R = add(g.R, matmul(v_W, transpose(Rq)));
  T v_qn[4];
  quat_to_rotmat_vjp(qw, qx, qy, qz, v_Rq, v_qn);
  const T dotq = qw * v_qn[0] + qx * v_qn[1] + qy * v_qn[2] + qz * v_qn[3];
  g.quat[0] += (v_qn[0] - qw * dotq) / qn;
  g.quat[1] += (v_qn[1] - qx * dotq) / qn;
  g.quat[2] += (v_qn[2] - qy * dotq) / qn;
  g.quat[3] += (v_qn[3] - qz * dotq) / qn;

  // p = R mean + t
  const Vec3<T> v_p{v_px, v_py, v_pz};
  const Vec3<T> v_mean = matTvec(cam.R, v_p);
  g.mean[0] += v_mean.x;
  g.mean[1] += v_mean.y;
  g.mean[2] += v_mean.z;
  const T vp[3] = {v_px, v_py, v_pz};
  for (int i = 0; i < 3; ++i) {
    for (int j = 0; j < 3; ++j) g.R.m[i][j] += vp[i] * mean[j];
    g.t[i] += vp[i];
  }
}

}  // namespace tiger
