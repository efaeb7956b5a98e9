"""What the command groups share: the config options and their shortcuts, help texts, small
printers and readers."""
from __future__ import annotations

import argparse
from pathlib import Path


DEVICE_HELP = "where to render: auto | cpu | cuda | cuda:N (default: the run's train.device)"


def _config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--patch", action="append", default=[], metavar="NAME",
                   help="config patch: a shipped one by name (`pgs config --list` shows them by kind) "
                        "or a .toml path; repeat to apply in order")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one config value (after the patches)")
    p.add_argument("-r", "--resolution", type=int, default=None,
                   help="downscale factor (1, 2, 4, 8); default: original size capped at 1600 px")
    p.add_argument("--images", default=None, help="image folder (e.g. images_8)")
    p.add_argument("--iterations", type=int, default=None, help="shortcut for --set train.iterations=N")
    p.add_argument("--device", default=None,
                   help="auto | cpu | cuda | cuda:N: shortcut for --set train.device=...")


def _config_sets(args) -> list:
    """``--set`` overrides followed by the shortcut options' (-r, --images, --iterations,
    --device)."""
    sets = list(args.set)
    if getattr(args, "resolution", None) is not None:
        sets.append(f"data.resolution={args.resolution}")
    if getattr(args, "images", None):
        sets.append(f'data.images="{args.images}"')
    if getattr(args, "iterations", None) is not None:
        sets.append(f"train.iterations={args.iterations}")
    if getattr(args, "device", None):
        sets.append(f'train.device="{args.device}"')
    if getattr(args, "tensorboard", False):
        sets.append("train.tensorboard=true")
    return sets


def _build_cfg(args):
    from baseline.config import build_config

    return build_config(args.patch, _config_sets(args))


def _print_results(res: dict) -> None:
    t = res.get("test", {})
    from baseline.eval.metrics import format_psnr
    from baseline.eval.report import stalled

    stall = (f", {res['stall_s']:.1f} s of it stalled: paused or sharing its core"
             if stalled(res) else "")
    print(f"iterations {res['iterations']}  train {res['train_time_s']:.1f} s "
          f"({res['s_per_it']:.3f} s/it, {res['threads']} threads on {res.get('machine', '-')}"
          f"{stall})  anchors {res['anchors']}")
    if t:
        lp = "unavailable" if t.get("lpips") is None else f"{t['lpips']:.4f}"
        print(f"test: PSNR {format_psnr(t['psnr'], 3)}  SSIM {t['ssim']:.4f}  LPIPS {lp}  "
              f"FPS {t['fps']:.1f}  Gaussians/view {t['gaussians_mean']:.0f}")


def _read_record(path: Path) -> dict:
    """A JSON record of the toolkit's (read bounded; not an object: an error naming it)."""
    from baseline.fileio import read_json_bounded

    rec = read_json_bounded(path, "a pgs record")
    if not isinstance(rec, dict):
        raise ValueError(f"{path}: not a JSON object, not a pgs record")  # noqa: TRY004
    return rec


def _is_eval_record(path: Path) -> bool:
    """``FILE.results.json`` as ``pgs eval FILE.pgs`` writes it: one entry per split."""
    try:
        rec = _read_record(path)
    except ValueError:
        return False
    return bool(rec) and set(rec) <= {"test", "train"} and all(
        isinstance(v, dict) and v.get("phase") == "decoded" for v in rec.values())


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("predict-gs-toolkit")
    except PackageNotFoundError:     # run from a source tree without installing
        v = "unknown (not installed)"
    from baseline.config import TRAINING_SEMANTICS

    return f"{v} (training semantics {TRAINING_SEMANTICS})"


SCENE_HELP = ("scene folder: COLMAP (sparse/0 + images/ or images_N/) or Blender / instant-ngp "
              "(transforms*.json)")
LPIPS_HELP = ("LPIPS (VGG) weights: LIN.pth,VGG16.pth - the lpips package's weights/v0.1/vgg.pth "
              "and torchvision's vgg16-397923af.pth - or one file holding both (README); found "
              "on their own when both are installed, never downloaded; else LPIPS is unavailable")


def _lpips_weights(args):
    """``--lpips-weights``, else the lpips package's and torchvision's files when both are on
    this machine already (:func:`baseline.eval.metrics.find_lpips_weights`; never downloaded)."""
    from baseline.eval.metrics import find_lpips_weights

    return args.lpips_weights or find_lpips_weights()


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{v} must be at least 1")
    return v


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())
