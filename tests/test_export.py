"""3DGS PLY export: standard property layout, activations stored the way viewers expect."""
import numpy as np
import torch

from baseline.config import build_config
from baseline.eval.export import SH_C0, gaussians_at_view, read_ply, write_ply
from baseline.scaffold.build import build_model


def test_ply_layout_and_values(tmp_path):
    cfg = build_config([], ["model.voxel_size=0.3"])
    model, _ = build_model(cfg, torch.rand(400, 3) * 3)
    center = torch.tensor([0.0, 0.0, -5.0])
    g = gaussians_at_view(model, center)
    n = write_ply(tmp_path / "x.ply", g.means, g.quats, g.scales, g.opacities, g.colors)
    assert n == len(g.means) > 0
    raw = (tmp_path / "x.ply").read_bytes()
    assert raw.startswith(b"ply\nformat binary_little_endian 1.0\n")
    d = read_ply(tmp_path / "x.ply")
    for p in ["x", "y", "z", "f_dc_0", "f_rest_44", "opacity", "scale_2", "rot_3"]:
        assert p in d
    assert np.allclose(d["x"], g.means[:, 0].numpy())
    # opacity stored as a logit, scales as logs, colours as degree-0 SH coefficients
    assert np.allclose(1 / (1 + np.exp(-d["opacity"])), g.opacities.numpy(), atol=1e-5)
    assert np.allclose(np.exp(d["scale_1"]), g.scales[:, 1].numpy(), rtol=1e-5)
    assert np.allclose(d["f_dc_2"] * SH_C0 + 0.5, g.colors[:, 2].numpy(), atol=1e-6)
    q = np.stack([d[f"rot_{i}"] for i in range(4)], 1)
    assert np.allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-5)
    assert not (tmp_path / "x.ply.tmp").exists()
