"""Export decoded neural Gaussians as a standard 3DGS PLY that common splat viewers open.

The neural Gaussians of Scaffold-GS are view dependent; the export decodes every anchor from one
fixed viewpoint, the mean of the training camera centres (documented choice: it is the view the
scene was most often seen from on average). Properties follow the 3DGS convention that viewers
(SIBR, SuperSplat, antimatter15/splat, ...) read: x y z, nx ny nz, f_dc_0..2 (degree-0 SH:
(rgb - 0.5) / C0), f_rest_0..44 (zeros), opacity as a logit, scale_0..2 as log-scales,
rot_0..3 as a (w, x, y, z) quaternion.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

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


def write_ply(path: str | Path, means, quats, scales, opacities, colors) -> int:
    """Write [G,3] means, [G,4] quats (wxyz), [G,3] scales, [G] opacities, [G,3] rgb. Returns G."""
    means = means.detach().cpu().numpy().astype(np.float32)
    G = len(means)
    props = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(N_REST)]
             + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"])
    data = np.zeros((G, len(props)), dtype=np.float32)
    data[:, 0:3] = means
    data[:, 6:9] = (colors.detach().cpu().numpy() - 0.5) / SH_C0
    a = opacities.detach().cpu().double().numpy().clip(1e-6, 1 - 1e-6)
    data[:, 9 + N_REST] = np.log(a / (1 - a))
    data[:, 10 + N_REST:13 + N_REST] = np.log(scales.detach().cpu().numpy().clip(1e-12, None))
    q = torch.nn.functional.normalize(quats.detach().cpu(), dim=-1).numpy()
    data[:, 13 + N_REST:17 + N_REST] = q
    header = "ply\nformat binary_little_endian 1.0\n" + f"element vertex {G}\n" + "".join(
        f"property float {p}\n" for p in props) + "end_header\n"
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
    return {p: arr[:, i] for i, p in enumerate(props)}


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
