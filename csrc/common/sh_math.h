#pragma once
// Real spherical harmonics, degrees 0-3, in the INRIA 3DGS coefficient order.
// The basis is written once, templated on the number type: with plain floats it
// evaluates colours, with Dual3 it also yields the basis' gradient w.r.t. the
// (normalised) view direction, so forward and backward share one formula.
#include <math.h>
#include <stdint.h>

#include "macros.h"

namespace tiger {

template <typename T>
struct Dual3 {
  T v, dx, dy, dz;
};
template <typename T>
TIGER_HD Dual3<T> operator*(Dual3<T> a, Dual3<T> b) {
  return {a.v * b.v, a.dx * b.v + a.v * b.dx, a.dy * b.v + a.v * b.dy, a.dz * b.v + a.v * b.dz};
}
template <typename T>
TIGER_HD Dual3<T> operator*(Dual3<T> a, T s) {
  return {a.v * s, a.dx * s, a.dy * s, a.dz * s};
}
template <typename T>
TIGER_HD Dual3<T> operator*(T s, Dual3<T> a) {
  return a * s;
}
template <typename T>
TIGER_HD Dual3<T> operator+(Dual3<T> a, Dual3<T> b) {
  return {a.v + b.v, a.dx + b.dx, a.dy + b.dy, a.dz + b.dz};
}
template <typename T>
TIGER_HD Dual3<T> operator-(Dual3<T> a, Dual3<T> b) {
  return {a.v - b.v, a.dx - b.dx, a.dy - b.dy, a.dz - b.dz};
}

TIGER_HD constexpr int sh_num_bases(int degree) { return (degree + 1) * (degree + 1); }

// Writes the (degree+1)^2 basis values for the unit direction (x, y, z).
// N is a scalar type or Dual3<S>; S is the scalar type of the constants.
template <typename S, typename N>
TIGER_HD void sh_basis(int degree, N x, N y, N z, N one, N* out) {
  out[0] = one * S(0.28209479177387814);
  if (degree < 1) return;
  const S c1 = S(0.4886025119029199);
  out[1] = y * S(-c1);
  out[2] = z * c1;
  out[3] = x * S(-c1);
  if (degree < 2) return;
  const N xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  out[4] = xy * S(1.0925484305920792);
  out[5] = yz * S(-1.0925484305920792);
  out[6] = (zz * S(2) - xx - yy) * S(0.31539156525252005);
  out[7] = xz * S(-1.0925484305920792);
  out[8] = (xx - yy) * S(0.5462742152960396);
  if (degree < 3) return;
  out[9] = y * (xx * S(3) - yy) * S(-0.5900435899266435);
  out[10] = xy * z * S(2.890611442640554);
  out[11] = y * (zz * S(4) - xx - yy) * S(-0.4570457994644658);
  out[12] = z * (zz * S(2) - xx * S(3) - yy * S(3)) * S(0.3731763325901154);
  out[13] = x * (zz * S(4) - xx - yy) * S(-0.4570457994644658);
  out[14] = z * (xx - yy) * S(1.445305721320277);
  out[15] = x * (xx - yy * S(3)) * S(-0.5900435899266435);
}

template <typename T>
TIGER_HD T sh_dir_norm(const T* dir) {
  const T n = sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]);
  return n > T(1e-12) ? n : T(1e-12);
}

// rgb[3] = sum_k coeffs[k][:] * Y_k(dir / |dir|); coeffs is [K][3], K >= (degree+1)^2.
template <typename T>
TIGER_HD void sh_eval(int degree, const T* dir, const T* coeffs, T* rgb) {
  const T n = sh_dir_norm(dir);
  T b[16];
  sh_basis<T, T>(degree, dir[0] / n, dir[1] / n, dir[2] / n, T(1), b);
  const int nb = sh_num_bases(degree);
  for (int c = 0; c < 3; ++c) {
    T s = T(0);
    for (int k = 0; k < nb; ++k) s += b[k] * coeffs[k * 3 + c];
    rgb[c] = s;
  }
}

// Given v_rgb[3], writes v_coeffs[(degree+1)^2][3] (= , or += with Accumulate) and v_dir[3] (=).
// Accumulate: a Gaussian's coefficient gradient summed over several views in one buffer
// (sh_eval_vjp_views); v_dir is per view and always assigned.
template <typename T, bool Accumulate = false>
TIGER_HD void sh_eval_vjp(int degree, const T* dir, const T* coeffs, const T* v_rgb, T* v_coeffs,
                          T* v_dir) {
  const T n = sh_dir_norm(dir);
  const T x = dir[0] / n, y = dir[1] / n, z = dir[2] / n;
  Dual3<T> b[16];
  sh_basis<T, Dual3<T>>(degree, Dual3<T>{x, T(1), T(0), T(0)}, Dual3<T>{y, T(0), T(1), T(0)},
                        Dual3<T>{z, T(0), T(0), T(1)}, Dual3<T>{T(1), T(0), T(0), T(0)}, b);
  const int nb = sh_num_bases(degree);
  T gx = T(0), gy = T(0), gz = T(0);
  for (int k = 0; k < nb; ++k) {
    T vb = T(0);
    for (int c = 0; c < 3; ++c) {
      if constexpr (Accumulate)
        v_coeffs[k * 3 + c] += b[k].v * v_rgb[c];
      else
        v_coeffs[k * 3 + c] = b[k].v * v_rgb[c];
      vb += coeffs[k * 3 + c] * v_rgb[c];
    }
    gx += vb * b[k].dx;
    gy += vb * b[k].dy;
    gz += vb * b[k].dz;
  }
  // Through the normalisation d = dir / |dir|.
  const T dot = gx * x + gy * y + gz * z;
  v_dir[0] = (gx - x * dot) / n;
  v_dir[1] = (gy - y * dot) / n;
  v_dir[2] = (gz - z * dot) / n;
}

// One Gaussian seen from V views (the CPU and CUDA kernels' row loop; one view is V = 1).
// The per-view arrays hold view v's entry for this Gaussian at an offset of v * n entries:
// dir, rgb, v_rgb and v_dir point at view 0's [3] (view v at + 3 v n), visible (null: every view)
// at view 0's flag (view v at + v n). coeffs / v_coeffs: the Gaussian's [K][3] row, shared by the
// views.

// rgb of every view whose flag is set (the others are left untouched).
template <typename T>
TIGER_HD void sh_eval_views(int degree, int64_t views, int64_t n, const T* dir, const T* coeffs,
                            const bool* visible, T* rgb) {
  for (int64_t v = 0; v < views; ++v)
    if (!visible || visible[v * n]) sh_eval<T>(degree, dir + 3 * v * n, coeffs, rgb + 3 * v * n);
}

// v_dir of every view whose flag is set (the others untouched) and v_coeffs = the sum over those
// views of their coefficient gradients, added in view order. The first view assigns (Accumulate
// false), so one view writes exactly sh_eval_vjp's values (bit for bit, signed zeros included).
// Like sh_eval_vjp it writes only the first (degree+1)^2 bases of v_coeffs, and nothing when no
// view's flag is set: the caller zero-fills the rest.
template <typename T>
TIGER_HD void sh_eval_vjp_views(int degree, int64_t views, int64_t n, const T* dir, const T* coeffs,
                                const bool* visible, const T* v_rgb, T* v_coeffs, T* v_dir) {
  bool first = true;
  for (int64_t v = 0; v < views; ++v) {
    if (visible && !visible[v * n]) continue;
    const int64_t o = 3 * v * n;
    if (first)
      sh_eval_vjp<T, false>(degree, dir + o, coeffs, v_rgb + o, v_coeffs, v_dir + o);
    else
      sh_eval_vjp<T, true>(degree, dir + o, coeffs, v_rgb + o, v_coeffs, v_dir + o);
    first = false;
  }
}

}  // namespace tiger
