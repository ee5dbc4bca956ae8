"""Plain-PyTorch dense reference renderer (every pixel against every Gaussian).

It follows the formulas of SPEC §3 (and ``csrc/common/*_math.h``) with ordinary
tensor ops, so autograd gives reference gradients. Tests and benchmarks run it in
float64 to measure the kernels' error. Memory is O(pixels x N): use it on small
scenes, or render pixel chunks with ``pixel_chunk``.
"""
from __future__ import annotations

from typing import Optional

import torch
from torch import Tensor

from .rasterize import camera_center

# The reference's constants are written from their sources, not imported from the kernels'
# RasterSettings, so that a wrong kernel default shows up as a difference:
#   INRIA diff-gaussian-rasterization, cuda_rasterizer/forward.cu: ``cov[0][0] += 0.3f`` (eps2d),
#   ``alpha = min(0.99f, ...)``, ``if (alpha < 1.0f / 255.0f) continue``,
#   ``if (test_T < 0.0001f) done = true``; SPEC §3 (the same values).
#   near/far: gsplat's defaults (near_plane=0.01, far_plane=1e10).
REF_EPS2D = 0.3
REF_ALPHA_MAX = 0.99
REF_ALPHA_THRESHOLD = 1.0 / 255.0
REF_T_MIN = 1e-4
REF_NEAR = 0.01
REF_FAR = 1e10

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def quat_to_rotmat_ref(quats: Tensor) -> Tensor:
    """[N, 4] (w, x, y, z), any norm → [N, 3, 3] rotation matrices."""
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    w, x, y, z = q.unbind(-1)
    return torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1).reshape(-1, 3, 3)


def sh_to_color_ref(dirs: Tensor, coeffs: Tensor, degree: int) -> Tensor:
    """Evaluate real SH (INRIA order) for directions [N, 3] and coeffs [N, K, 3] → [N, 3]."""
    d = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    x, y, z = d.unbind(-1)
    basis = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        basis += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        basis += [SH_C2[0] * x * y, SH_C2[1] * y * z, SH_C2[2] * (2 * zz - xx - yy),
                  SH_C2[3] * x * z, SH_C2[4] * (xx - yy)]
    if degree >= 3:
        basis += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z,
                  SH_C3[2] * y * (4 * zz - xx - yy), SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
                  SH_C3[4] * x * (4 * zz - xx - yy), SH_C3[5] * z * (xx - yy),
                  SH_C3[6] * x * (xx - 3 * yy)]
    b = torch.stack(basis, dim=-1)  # [N, B]
    return torch.einsum("nb,nbc->nc", b, coeffs[:, : b.shape[1]])


def project_ref(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, viewmat: Tensor,
                K: Tensor, width: int, height: int, *, near: float = REF_NEAR,
                far: float = REF_FAR, eps2d: float = REF_EPS2D,
                antialiased: bool = False,
                alpha_threshold: float = REF_ALPHA_THRESHOLD) -> dict[str, Tensor]:
    """EWA projection of every Gaussian. Returns means2d [N,2], conics [N,3], depths [N],
    opacities [N] (compensated) and ``valid`` [N] bool (not culled by near/far/det/opacity)."""
    R, t = viewmat[:3, :3], viewmat[:3, 3]
    p = means @ R.T + t
    x, y, z = p.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    valid = (z > near) & (z < far)
    zs = torch.where(valid, z, torch.ones_like(z))  # keep culled rows finite
    M = (R @ quat_to_rotmat_ref(quats)) * scales[:, None, :]
    cov3 = M @ M.transpose(1, 2)

    def clamp(c: Tensor, f: Tensor, cc: Tensor, size: int) -> Tensor:
        lim_pos = (size - cc + 0.15 * size) / f
        lim_neg = (cc + 0.15 * size) / f
        return zs * torch.minimum(torch.maximum(c / zs, -lim_neg), lim_pos)

    tx, ty = clamp(x, fx, cx, width), clamp(y, fy, cy, height)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / zs**2, zero, fy / zs, -fy * ty / zs**2],
                    dim=-1).reshape(-1, 2, 3)
    cov2 = J @ cov3 @ J.transpose(1, 2)
    a, b, c = cov2[:, 0, 0], cov2[:, 0, 1], cov2[:, 1, 1]
    a1, c1 = a + eps2d, c + eps2d
    det = a1 * c1 - b * b
    valid = valid & (det > 0)
    det_s = torch.where(valid, det, torch.ones_like(det))
    opac = opacities
    if antialiased:
        det0 = (a * c - b * b).clamp_min(0)
        opac = opacities * torch.sqrt(det0 / det_s)
    valid = valid & (opac >= alpha_threshold)
    conics = torch.stack([c1 / det_s, -b / det_s, a1 / det_s], dim=-1)
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)
    return {"means2d": means2d, "conics": conics, "depths": z, "opacities": opac,
            "valid": valid}


def composite_ref(means2d: Tensor, conics: Tensor, opacities: Tensor, colors: Tensor,
                  depths: Tensor, valid: Tensor, width: int, height: int,
                  background: Optional[Tensor] = None, *,
                  alpha_max: float = REF_ALPHA_MAX,
                  alpha_threshold: float = REF_ALPHA_THRESHOLD,
                  t_min: float = REF_T_MIN, pixel_chunk: int = 1 << 16
                  ) -> dict[str, Tensor]:
    """Dense front-to-back compositing → color [H,W,C], alpha [H,W], depth_accum [H,W]."""
    order = torch.argsort(torch.where(valid, depths, torch.full_like(depths, float("inf"))),
                          stable=True)
    order = order[valid[order]]
    m2, cn, op, col, dp = (means2d[order], conics[order], opacities[order], colors[order],
                           depths[order])
    ys, xs = torch.meshgrid(torch.arange(height, dtype=means2d.dtype, device=means2d.device),
                            torch.arange(width, dtype=means2d.dtype, device=means2d.device),
                            indexing="ij")
    pix = torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=-1) + 0.5
    outs_c, outs_a, outs_d = [], [], []
    for s in range(0, pix.shape[0], pixel_chunk):
        d = pix[s:s + pixel_chunk, None, :] - m2[None]  # [P, N, 2]
        q = cn[:, 0] * d[..., 0] ** 2 + 2 * cn[:, 1] * d[..., 0] * d[..., 1] + cn[:, 2] * d[..., 1] ** 2
        alpha = torch.clamp(op * torch.exp(-0.5 * q), max=alpha_max)
        alpha = torch.where(alpha >= alpha_threshold, alpha, torch.zeros_like(alpha))
        t_after = torch.cumprod(1 - alpha, dim=1)
        alpha = torch.where(t_after >= t_min, alpha, torch.zeros_like(alpha))
        trans = torch.cumprod(1 - alpha, dim=1)
        t_before = torch.cat([torch.ones_like(trans[:, :1]), trans[:, :-1]], dim=1)
        w = alpha * t_before
        t_final = trans[:, -1] if trans.shape[1] else torch.ones_like(pix[s:s + pixel_chunk, 0])
        c = w @ col
        if background is not None:
            c = c + t_final[:, None] * background
        outs_c.append(c)
        outs_a.append(1 - t_final)
        outs_d.append(w @ dp)
    C = colors.shape[1]
    return {"color": torch.cat(outs_c).reshape(height, width, C),
            "alpha": torch.cat(outs_a).reshape(height, width),
            "depth_accum": torch.cat(outs_d).reshape(height, width)}


def render_ref(means: Tensor, quats: Tensor, scales: Tensor, opacities: Tensor, colors: Tensor,
               viewmat: Tensor, K: Tensor, width: int, height: int, *,
               background: Optional[Tensor] = None, sh_degree: Optional[int] = None,
               near: float = REF_NEAR, far: float = REF_FAR,
               eps2d: float = REF_EPS2D, antialiased: bool = False,
               alpha_max: float = REF_ALPHA_MAX,
               alpha_threshold: float = REF_ALPHA_THRESHOLD,
               t_min: float = REF_T_MIN, pixel_chunk: int = 1 << 16
               ) -> dict[str, Tensor]:
    """Reference counterpart of :func:`tiger.rasterize_gaussians` (same arguments/outputs)."""
    pr = project_ref(means, quats, scales, opacities, viewmat, K, width, height, near=near,
                     far=far, eps2d=eps2d, antialiased=antialiased,
                     alpha_threshold=alpha_threshold)
    if sh_degree is not None:
        colors = torch.clamp_min(
            sh_to_color_ref(means - camera_center(viewmat), colors, sh_degree) + 0.5, 0.0)
    out = composite_ref(pr["means2d"], pr["conics"], pr["opacities"], colors, pr["depths"],
                        pr["valid"], width, height, background, alpha_max=alpha_max,
                        alpha_threshold=alpha_threshold, t_min=t_min, pixel_chunk=pixel_chunk)
    covered = out["alpha"] > 0
    out["depth"] = torch.where(covered, out["depth_accum"] / torch.where(
        covered, out["alpha"], torch.ones_like(out["alpha"])), torch.zeros_like(out["alpha"]))
    out.update(pr)
    return out
