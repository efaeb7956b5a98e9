"""Export decoded neural Gaussians as a standard 3DGS PLY that common splat viewers open.

Scaffold-GS's neural Gaussians are view dependent (opacity, colour, scale and rotation come from
MLPs of the view direction and distance, and the set drawn changes with the view); a 3DGS PLY
holds one static set with spherical-harmonic colours. :func:`export_sh_ply` turns one into the
other over the training cameras:

* the Gaussians kept are the union over the training views of those drawn (mask on, opacity
  > 0) in at least one view; each gets its mean opacity over the views that see its anchor
  (0 where it is not drawn), and the opacity-weighted mean of its scales (in log space) and of
  its rotations (sign-aligned quaternions);
* its colour is fitted to spherical harmonics of degree ``sh_degree`` (default 3, 3DGS's basis
  and constants) by least squares over the directions from the training cameras to it,
  weighted by its opacity in each view, with a small ridge on the degree >= 1 coefficients so
  that a Gaussian seen from few views stays well posed;
* the export renders the PLY's Gaussians with the toolkit's rasterizer and measures its own
  fidelity: PSNR against the decoded model's renders on the test views (and both against the
  ground truth); the PLY's header comments say what it is and carry these figures.

Without training cameras (``pgs decode`` of a file whose scene is not here) the fallback is
:func:`export_run_ply`: the Gaussians seen from one viewpoint (the mean training camera centre
the file records), colours as degree-0 coefficients. Properties follow the 3DGS convention
(SIBR, SuperSplat, antimatter15/splat, ...): x y z, nx ny nz, f_dc_0..2, f_rest_0..44
(channel-major, zeros above the fitted degree), opacity as a logit, scale_0..2 as log-scales,
rot_0..3 as a (w, x, y, z) quaternion.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from baseline.eval.metrics import format_psnr
from baseline.fileio import atomic_path

SH_C0 = 0.28209479177387814
N_REST = 45


@torch.no_grad()
def gaussians_at_view(model, center: torch.Tensor, values: dict | None = None, coded=None):
    """Every anchor's neural Gaussians seen from ``center`` [3]; ``coded``
    (:class:`baseline.pipeline.CodedState`): the coded anchors with their coded values.

    Decoded with one thread: GEMM blocking over many threads may change the last bit of a
    sum, and the export is one pass, so a file is byte-identical on any machine's threads."""
    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if coded is not None:
            return model.decode(center, coded.index, coded.values, xyz=coded.xyz)
        idx = torch.arange(model.n_anchors, device=model.xyz.device)
        return model.decode(center, idx, values)
    finally:
        torch.set_num_threads(prev)


def write_ply(path: str | Path, means, quats, scales, opacities, colors, sh=None,
              comments=()) -> int:
    """Write [G,3] means, [G,4] quats (wxyz), [G,3] scales, [G] opacities and either [G,3] rgb
    (``colors``, stored as degree-0 coefficients) or ``sh`` [G,B,3] SH coefficients (B <= 16,
    3DGS's order); ``comments``: header comment lines. Returns G."""
    means = means.detach().cpu().numpy().astype(np.float32)
    G = len(means)
    props = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(N_REST)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    data = np.zeros((G, len(props)), dtype=np.float32)
    data[:, 0:3] = means
    if sh is None:
        data[:, 6:9] = (colors.detach().cpu().numpy() - 0.5) / SH_C0
    else:
        c = sh.detach().cpu().numpy()
        data[:, 6:9] = c[:, 0]
        rest = c[:, 1:]                                        # [G, B-1, 3] -> channel-major
        for ch in range(3):
            data[:, 9 + ch * 15:9 + ch * 15 + rest.shape[1]] = rest[:, :, ch]
    a = opacities.detach().cpu().double().numpy().clip(1e-6, 1 - 1e-6)
    data[:, 9 + N_REST] = np.log(a / (1 - a))
    data[:, 10 + N_REST:13 + N_REST] = np.log(scales.detach().cpu().numpy().clip(1e-12, None))
    q = torch.nn.functional.normalize(quats.detach().cpu(), dim=-1).numpy()
    data[:, 13 + N_REST:17 + N_REST] = q
    com = "".join(f"comment {' '.join(str(c).split())}\n" for c in comments)
    header = ("ply\nformat binary_little_endian 1.0\n" + com + f"element vertex {G}\n"
              + "".join(f"property float {p}\n" for p in props) + "end_header\n")
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(data.astype("<f4").tobytes())
    return G


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Read a binary little-endian float PLY written by :func:`write_ply` (tests, tools)."""
    raw = Path(path).read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    lines = raw[:end].decode("ascii").splitlines()
    n = int(next(l for l in lines if l.startswith("element vertex")).split()[-1])
    props = [l.split()[-1] for l in lines if l.startswith("property")]
    arr = np.frombuffer(raw[end:], dtype="<f4").reshape(n, len(props))
    out = {p: arr[:, i] for i, p in enumerate(props)}
    out["comments"] = [l[len("comment "):] for l in lines if l.startswith("comment ")]
    return out


def view_center(train_cameras) -> torch.Tensor:
    """[3] the export viewpoint: the mean of the training camera centres."""
    return torch.stack([c.center for c in train_cameras]).double().mean(0).float()


def export_run_ply(model, train_cameras, path, values: dict | None = None, coded=None,
                   center: torch.Tensor | None = None) -> int:
    """Write ``model``'s neural Gaussians seen from ``center`` (default :func:`view_center` of
    ``train_cameras``) as a 3DGS PLY; returns the Gaussian count."""
    if center is None:
        if not train_cameras:
            raise ValueError("no export viewpoint: the file records none and no scene is given "
                             "(pass --scene PATH)")
        center = view_center(train_cameras)
    g = gaussians_at_view(model, center.to(model.xyz.device), values, coded)
    return write_ply(path, g.means, g.quats, g.scales, g.opacities, g.colors)


# ------------------------------------------------------------------------ spherical harmonics
# 3DGS's real SH basis (its sh_utils constants and order): colour = sum_i c_i Y_i(d) + 0.5.
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792,
         0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def sh_basis(dirs: torch.Tensor, degree: int) -> torch.Tensor:
    """[N,3] unit directions -> [N, (degree+1)^2] basis values in 3DGS's order."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if degree >= 2:
        xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
        out += [SH_C2[0] * xy, SH_C2[1] * yz, SH_C2[2] * (2 * zz - xx - yy), SH_C2[3] * xz,
                SH_C2[4] * (xx - yy)]
    if degree >= 3:
        out += [SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * xy * z, SH_C3[2] * y * (4 * zz - xx - yy),
                SH_C3[3] * z * (2 * zz - 3 * xx - 3 * yy), SH_C3[4] * x * (4 * zz - xx - yy),
                SH_C3[5] * z * (xx - yy), SH_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def sh_colors(sh: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """3DGS's colour of SH coefficients ``sh`` [G,B,3] seen along ``dirs`` [G,3]:
    max(sum_i c_i Y_i(d) + 0.5, 0)."""
    deg = int(round(sh.shape[1] ** 0.5)) - 1
    b = sh_basis(dirs, deg).to(sh.dtype)
    return ((b[:, :, None] * sh).sum(1) + 0.5).clamp_min(0.0)


def sh_ridge(degree: int, strength: float) -> torch.Tensor:
    """[B] the ridge weight of each coefficient: 0 for degree 0, strength x l(l+1) above."""
    ls = [l for l in range(degree + 1) for _ in range(2 * l + 1)]
    return torch.tensor([strength * l * (l + 1) for l in ls], dtype=torch.float64)


def solve_sh(A: torch.Tensor, R: torch.Tensor, wsum: torch.Tensor, degree: int,
             ridge: float = 1e-3) -> torch.Tensor:
    """Weighted least squares from accumulated normal equations: ``A`` [G,B,B] = sum w b b^T,
    ``R`` [G,B,3] = sum w b (c - 0.5), ``wsum`` [G] = sum w -> coefficients [G,B,3]
    (float64). The ridge (times each Gaussian's total weight) keeps it well posed."""
    B = A.shape[-1]
    reg = torch.diag_embed(sh_ridge(degree, ridge)[None, :].to(A) * wsum[:, None].clamp_min(1e-12))
    eye = 1e-12 * torch.eye(B, dtype=A.dtype, device=A.device)
    return torch.linalg.solve(A + reg + eye, R)


def fit_sh(dirs: torch.Tensor, colors: torch.Tensor, weights: torch.Tensor, degree: int,
           ridge: float = 1e-3) -> torch.Tensor:
    """One Gaussian's SH coefficients [B,3] from samples: directions [V,3], colours [V,3],
    weights [V] (the same fit :func:`export_sh_ply` accumulates per Gaussian)."""
    b = sh_basis(dirs.double(), degree)
    w = weights.double()
    A = (b.T * w) @ b
    R = (b.T * w) @ (colors.double() - 0.5)
    return solve_sh(A[None], R[None], w.sum()[None], degree, ridge)[0]


# --------------------------------------------------------------------- the view-union export
@torch.no_grad()
def union_gaussians(model, cameras, *, coded=None, sh_degree: int = 3, chunk: int = 8192,
                    ridge: float = 1e-3) -> dict:
    """The static 3DGS Gaussians of a decoded or coded model over ``cameras`` (see the module
    docstring): ``{means [G,3], quats [G,4], scales [G,3], opacities [G], sh [G,B,3],
    views [G] (views that saw its anchor), drawn [G] (views that drew it)}``, float32 except the
    counts. One thread (a byte-identical file on any machine); anchors in chunks of ``chunk``."""
    from baseline.render import prefilter_anchors

    prev = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        if coded is not None:
            index, xyz_all, vals_all = coded.index, coded.xyz, coded.values
        else:
            index = torch.arange(model.n_anchors, device=model.xyz.device)
            xyz_all = model.positions()
            vals_all = model.coded_values(index)
        K = model.n_offsets
        B = (sh_degree + 1) ** 2
        scal_all = vals_all["scaling"]
        outs = []
        for s0 in range(0, len(index), chunk):
            sl = slice(s0, s0 + chunk)
            idx, xyz = index[sl], xyz_all[sl]
            vals = {k: v[sl] for k, v in vals_all.items()}
            m = len(idx)
            means = (xyz[:, None, :] + vals["offsets"].reshape(m, K, 3)
                     * vals["scaling"][:, None, :3]).reshape(m * K, 3).double()
            n_vis = torch.zeros(m * K, dtype=torch.int64)
            n_drawn = torch.zeros(m * K, dtype=torch.int64)
            op_sum = torch.zeros(m * K, dtype=torch.float64)
            w_sum = torch.zeros(m * K, dtype=torch.float64)
            logs = torch.zeros(m * K, 3, dtype=torch.float64)
            qsum = torch.zeros(m * K, 4, dtype=torch.float64)
            qref = torch.zeros(m * K, 4, dtype=torch.float64)
            A = torch.zeros(m * K, B, B, dtype=torch.float64)
            R = torch.zeros(m * K, B, 3, dtype=torch.float64)
            for cam in cameras:
                vis = prefilter_anchors(xyz, scal_all[sl][:, :3], cam).nonzero()[:, 0]
                if len(vis) == 0:
                    continue
                h = model.raw_heads(
                    cam.center, idx[vis], {k: v[vis] for k, v in vals.items()}, xyz[vis])
                raw_cov = h.raw_cov
                op = (h.opacity() * model.gaussian_mask(idx[vis])).reshape(-1).double()
                cand = (vis[:, None] * K + torch.arange(K)[None, :]).reshape(-1)
                n_vis[cand] += 1
                w = op.clamp_min(0.0)
                drawn = op > 0
                n_drawn[cand] += drawn.long()
                op_sum[cand] += w
                sel = drawn.nonzero()[:, 0]
                if len(sel) == 0:
                    continue
                c, wk = cand[sel], w[sel]
                cov = raw_cov.reshape(-1, 7)[sel].double()
                scale = (vals["scaling"][vis][:, None, 3:].expand(-1, K, -1).reshape(-1, 3)[sel].double()
                         * torch.sigmoid(cov[:, :3]))
                logs[c] += wk[:, None] * scale.clamp_min(1e-30).log()
                q = torch.nn.functional.normalize(cov[:, 3:7], dim=-1)
                first = qref[c].abs().sum(1) == 0
                qref[c[first]] = q[first]
                q = torch.where(((q * qref[c]).sum(1) < 0)[:, None], -q, q)
                qsum[c] += wk[:, None] * q
                w_sum[c] += wk
                d = torch.nn.functional.normalize(means[c] - cam.center.double()[None, :], dim=-1)
                b = sh_basis(d, sh_degree)
                col = h.colors(sel, torch.float64)
                A[c] += wk[:, None, None] * b[:, :, None] * b[:, None, :]
                R[c] += wk[:, None, None] * b[:, :, None] * (col - 0.5)[:, None, :]
            keep = (n_drawn > 0).nonzero()[:, 0]
            if len(keep):
                ws = w_sum[keep]
                outs.append(dict(
                    means=means[keep].float(),
                    quats=torch.nn.functional.normalize(qsum[keep], dim=-1).float(),
                    scales=(logs[keep] / ws[:, None]).exp().float(),
                    opacities=(op_sum[keep] / n_vis[keep]).float(),
                    sh=solve_sh(A[keep], R[keep], ws, sh_degree, ridge).float(),
                    views=n_vis[keep], drawn=n_drawn[keep]))
        if not outs:
            z = torch.zeros(0)
            return dict(means=z.reshape(0, 3), quats=z.reshape(0, 4), scales=z.reshape(0, 3),
                        opacities=z, sh=z.reshape(0, B, 3), views=z.long(), drawn=z.long())
        return {k: torch.cat([o[k] for o in outs]) for k in outs[0]}
    finally:
        torch.set_num_threads(prev)


@torch.no_grad()
def ply_fidelity(g: dict, model, scene, cameras, *, coded=None, backend: str = "auto") -> dict:
    """Render the static Gaussians ``g`` (:func:`union_gaussians`) and the model on
    ``cameras``: mean PSNR of the PLY against the model's render and of each against the
    ground truth (uint8 images)."""
    from baseline.eval.metrics import psnr, to_uint8
    from baseline.pipeline import render_view
    from baseline.render import rasterize

    bg = scene.background.float().to(model.xyz.device)
    vs_model, ply_gt, model_gt = [], [], []
    for cam in cameras:
        ref = render_view(model, cam, bg, phase="adaptive" if coded is not None else "decoded",
                          coded=coded, backend=backend).render.image
        d = torch.nn.functional.normalize(g["means"] - cam.center[None, :], dim=-1)
        col = sh_colors(g["sh"], d)
        img = rasterize(g["means"], g["quats"], g["scales"], g["opacities"], col, cam,
                        background=bg, backend=backend).image
        gt = to_uint8(scene.image(cam))
        a, b = to_uint8(img), to_uint8(ref)
        vs_model.append(psnr(a, b))
        ply_gt.append(psnr(a, gt))
        model_gt.append(psnr(b, gt))
    return {"views": len(cameras), "psnr_vs_model": float(np.mean(vs_model)),
            "psnr_ply": float(np.mean(ply_gt)), "psnr_model": float(np.mean(model_gt))}


def export_sh_ply(model, scene, path, *, coded=None, sh_degree: int = 3,
                  backend: str = "auto", source: str = "") -> dict:
    """Write ``model``'s view-union Gaussians with fitted SH colours as a 3DGS PLY (module
    docstring) and measure its fidelity on the test views; returns the counts and figures."""
    g = union_gaussians(model, scene.train_cameras, coded=coded, sh_degree=sh_degree)
    test = scene.test_cameras or scene.train_cameras
    fid = ply_fidelity(g, model, scene, test, coded=coded, backend=backend)
    per_view = float(g["drawn"].float().sum()) / max(len(scene.train_cameras), 1)
    comments = [
        f"pgs export of {source or 'a decoded model'}: static 3DGS Gaussians of a view-dependent "
        f"anchor model",
        f"Gaussians: the union over {len(scene.train_cameras)} training views of those drawn "
        f"(mask on, opacity > 0) in at least one; {per_view:.0f} drawn per view on average",
        "opacity: mean over the views that see its anchor; scale, rotation: opacity-weighted "
        "means over the views that draw it",
        f"colour: SH degree {sh_degree} fitted by weighted least squares over the training "
        f"camera directions (3DGS basis)",
        f"fidelity on {fid['views']} test views: PSNR {format_psnr(fid['psnr_vs_model'])} "
        f"against the decoded model's render; against the ground truth "
        f"{format_psnr(fid['psnr_ply'])} (decoded model {format_psnr(fid['psnr_model'])})"]
    n = write_ply(path, g["means"], g["quats"], g["scales"], g["opacities"], None, sh=g["sh"],
                  comments=comments)
    return {"gaussians": n, "drawn_per_view": per_view, "sh_degree": sh_degree, **fid,
            "path": str(path)}


def format_sh_export(r: dict) -> str:
    """One line on an :func:`export_sh_ply` result: the Gaussians written and the PLY's fidelity."""
    return (f"wrote {r['gaussians']} Gaussians to {r['path']} (the union over the training views "
            f"of those drawn, {r['drawn_per_view']:.0f} per view; SH degree {r['sh_degree']}); "
            f"fidelity on {r['views']} test views: {format_psnr(r['psnr_vs_model'])} against the "
            f"model's render, {format_psnr(r['psnr_ply'])} against the ground truth (model "
            f"{format_psnr(r['psnr_model'])})")
