"""Where the Gaussian masks stand in a training checkpoint: the mask logits and the mask's Adam state.

    python tools/probes/mask_state.py RUN/checkpoint.pt [RUN2/checkpoint.pt ...]

Per checkpoint: the median mask logit, the share of masks off (the coder's rule: a Gaussian is
on when sigmoid(logit) > ``entropy.mask_threshold`` of the run's ``config.toml`` beside the
checkpoint, the default config's without one), the median of Adam's bias-corrected |m| / sqrt(v) (the mean step
of a logit as a fraction of the learning rate: 1 when every step's gradient agrees, near 0 when
they cancel or when rare large gradients dominate v), the share of logits whose first moment
points down (toward "off") and the current mask learning rate.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

from baseline.config import default_config, from_toml


def mask_state(path: str) -> dict:
    run_config = Path(path).with_name("config.toml")
    cfg = from_toml(run_config) if run_config.exists() else default_config()
    ck = torch.load(path, map_location="cpu", weights_only=False)
    logits = ck["model"]["per_anchor.mask"].flatten()
    groups = [g for g in ck["optimizer"]["param_groups"] if g.get("name") == "mask"]
    if len(groups) != 1:
        raise SystemExit(f"{path}: no single optimizer group named 'mask'")
    group = groups[0]
    st = ck["optimizer"]["state"][group["params"][0]]
    beta1, beta2 = group.get("betas", (0.9, 0.999))
    step = float(st["step"])
    m_hat = st["exp_avg"].flatten() / (1 - beta1 ** step)
    v_hat = st["exp_avg_sq"].flatten() / (1 - beta2 ** step)
    ratio = m_hat.abs() / (v_hat.sqrt() + group.get("eps", 1e-15))
    return {
        "iteration": ck["iteration"],
        "logit_median": float(logits.median()),
        "off_share": float((torch.sigmoid(logits) <= cfg.entropy.mask_threshold).float().mean()),
        "step_over_lr_median": float(ratio.median()),
        "down_share": float((st["exp_avg"].flatten() > 0).float().mean()),
        "lr": float(group["lr"]),
    }


def main(argv: list[str]) -> None:
    if not argv:
        raise SystemExit(__doc__)
    for path in argv:
        s = mask_state(path)
        print(f"{path}: iteration {s['iteration']}, logit median {s['logit_median']:.2f}, "
              f"off {100 * s['off_share']:.1f}%, |m|/sqrt(v) median {s['step_over_lr_median']:.3f}, "
              f"pushed down {100 * s['down_share']:.1f}%, lr {s['lr']:.2e}")


if __name__ == "__main__":
    main(sys.argv[1:])
