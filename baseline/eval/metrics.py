"""Image quality metrics, computed the way the 3DGS papers report them.

Every metric first rounds both images to uint8, ``round(clamp(x, 0, 1) * 255)`` (docs/method.md section 1:
"metrics are computed on images rounded to uint8"); uint8 inputs are used as they are. Images are
channel-last ``[H, W, C]`` (torch tensors or numpy arrays), like ``Scene.image``.

* :func:`psnr`: ``10 log10(255^2 / MSE)`` over all pixels and channels of the uint8 values
  (``inf`` for identical images).
* :func:`ssim`: SSIM as 3DGS, Scaffold-GS and HAC report it (``ssim`` in 3DGS's
  ``utils/loss_utils.py``): the images in [0, 1] (uint8 / 255), an 11 x 11 Gaussian window
  (sigma 1.5) applied by convolution with zero padding over the whole image, C1 = 0.01^2,
  C2 = 0.03^2, the SSIM map averaged over every pixel and channel. This is the evaluation
  number (:data:`SSIM_CONVENTION`), the one published tables hold.
* :func:`ssim_skimage`: ``skimage.metrics.structural_similarity`` with the same window
  (``gaussian_weights=True, sigma=1.5, use_sample_covariance=False, data_range=255``): it
  averages only over the pixels whose window lies inside the image (a 5-pixel border left
  out), so it differs from :func:`ssim` near borders; kept as a second, named metric.
* :class:`LPIPS`: LPIPS with a VGG16 backbone in plain torch (no torchvision here). Weights are
  never downloaded or guessed: :func:`load_lpips` loads them from a user-given ``.pth`` file and
  otherwise reports ``LPIPS unavailable: pass --lpips-weights PATH``.
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from skimage.metrics import structural_similarity

LPIPS_UNAVAILABLE = ("LPIPS unavailable: its two weight files are not here; get the lpips "
                     "package's weights/v0.1/vgg.pth (pip download --no-deps lpips, unzip the "
                     "wheel) and torchvision's vgg16-397923af.pth, then pass --lpips-weights "
                     "LIN.pth,VGG16.pth (README, LPIPS)")

# What a record's "ssim" is: "3dgs" (the field's, :func:`ssim`). Records written before this
# convention was recorded hold scikit-image's SSIM under "ssim" (:func:`ssim_skimage`).
SSIM_CONVENTION = "3dgs"
SSIM_CONVENTIONS = {"3dgs": "3DGS's (11x11 Gaussian window, sigma 1.5, zero padding over the "
                            "whole image, as 3DGS / Scaffold-GS / HAC compute it)",
                    "skimage": "scikit-image's (the same window, a 5-pixel border left out)"}

SSIM_SETTINGS = dict(gaussian_weights=True, sigma=1.5, use_sample_covariance=False,
                     data_range=255, channel_axis=-1)


def to_uint8(img) -> np.ndarray:
    """round(clamp(x, 0, 1) * 255) as a uint8 numpy array; uint8 input passes through."""
    if isinstance(img, torch.Tensor):
        if img.dtype == torch.uint8:
            return img.detach().cpu().numpy()
        img = img.detach().cpu().double().numpy()
    img = np.asarray(img)
    if img.dtype == np.uint8:
        return img
    return np.round(np.clip(img.astype(np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)


def _pair(img, gt) -> tuple[np.ndarray, np.ndarray]:
    a, b = to_uint8(img), to_uint8(gt)
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    if a.ndim != 3:
        raise ValueError(f"expected [H, W, C] images, got shape {a.shape}")
    return a, b


def psnr(img, gt) -> float:
    """PSNR in dB of uint8-rounded images [H, W, C] (inf when identical)."""
    a, b = _pair(img, gt)
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return math.inf if mse == 0 else float(10.0 * np.log10(255.0 ** 2 / mse))


def format_psnr(v: float, digits: int = 2) -> str:
    """A PSNR for people: ``"25.31 dB"``, or what it is where it is no figure: infinite when
    the images compared are identical (zero error; e.g. two renders that both drew nothing), or
    undefined when nothing was measured (NaN)."""
    if math.isinf(v):
        return "infinite (the images compared are identical: zero error, no figure)"
    if math.isnan(v):
        return "undefined (no view measured)"
    return f"{v:.{digits}f} dB"


def ssim(img, gt) -> float:
    """SSIM of uint8-rounded images [H, W, C] as 3DGS computes it (the module doc): values / 255,
    11x11 Gaussian window (sigma 1.5), zero padding, mean over pixels and channels.

    The window is applied by :func:`baseline.train.losses.ssim`, the training loss's SSIM (the
    same formula as 3DGS's ``utils/loss_utils.py``), here in float64; no library pads with
    zeros as 3DGS does (scikit-image crops the border, torchmetrics reflects it)."""
    from baseline.train.losses import ssim as ssim_zero_padded

    a, b = _pair(img, gt)
    if min(a.shape[:2]) < 11:
        raise ValueError(f"SSIM needs images of at least 11 x 11 pixels, got {a.shape[:2]}")
    x = torch.from_numpy(a.astype(np.float64) / 255.0)
    y = torch.from_numpy(b.astype(np.float64) / 255.0)
    return float(ssim_zero_padded(x, y))


def ssim_skimage(img, gt) -> float:
    """scikit-image's SSIM of uint8-rounded images [H, W, C] with the 3DGS window (module doc):
    the border whose window leaves the image is not averaged."""
    a, b = _pair(img, gt)
    if min(a.shape[:2]) < 11:
        raise ValueError(f"SSIM needs images of at least 11 x 11 pixels, got {a.shape[:2]}")
    return float(structural_similarity(a, b, **SSIM_SETTINGS))


# ------------------------------------------------------------------------------------- LPIPS
# torchvision's vgg16().features layout: index -> conv (in, out) or "R" (ReLU) / "M" (max pool)
_VGG16 = [64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512]
_TAPS = (3, 8, 15, 22, 29)                 # relu1_2, relu2_2, relu3_3, relu4_3, relu5_3
_CHANNELS = (64, 128, 256, 512, 512)
_SHIFT = (-0.030, -0.088, -0.188)          # LPIPS input scaling layer
_SCALE = (0.458, 0.448, 0.450)


class LPIPS(torch.nn.Module):
    """LPIPS (VGG16 variant): distance of unit-normalized VGG features, weighted per channel.

    ``d(x, y) = sum_l mean_hw( w_l . (f_l(x) / |f_l(x)| - f_l(y) / |f_l(y)|)^2 )`` over the five
    taps relu1_2 ... relu5_3, with inputs mapped to [-1, 1] and then ``(x - shift) / scale``.

    State-dict keys (what :meth:`load_weights` accepts; one file holds both parts):

    * backbone: ``features.{i}.weight`` / ``features.{i}.bias`` for the 13 convolutions,
      ``i`` in 0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28 (torchvision's ``vgg16().features``
      names, also with a ``net.`` prefix), or the lpips package's ``net.slice{k}.{i}.*`` names
      (same ``i``);
    * linear heads: ``lin{k}.model.1.weight`` (lpips package; ``model.0`` without dropout) or ``lin{k}.weight`` or
      ``lins.{k}.weight``, k = 0..4, shapes ``[1, C_k, 1, 1]``, C = 64, 128, 256, 512, 512.

    Other keys (e.g. ``scaling_layer.shift``) are ignored.
    """

    def __init__(self):
        super().__init__()
        layers: list[torch.nn.Module] = []
        c_in = 3
        for v in _VGG16:
            if v == "M":
                layers.append(torch.nn.MaxPool2d(2, 2))
            else:
                layers += [torch.nn.Conv2d(c_in, v, 3, padding=1), torch.nn.ReLU(inplace=False)]
                c_in = v
        self.features = torch.nn.Sequential(*layers)           # indices match torchvision
        self.lins = torch.nn.ModuleList(torch.nn.Conv2d(c, 1, 1, bias=False) for c in _CHANNELS)
        self.register_buffer("shift", torch.tensor(_SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(_SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    @staticmethod
    def _canonical(key: str) -> str | None:
        import re
        k = key[7:] if key.startswith("module.") else key
        m = re.fullmatch(r"(?:net\.)?slice\d\.(\d+)\.(weight|bias)", k) or \
            re.fullmatch(r"(?:net\.)?features\.(\d+)\.(weight|bias)", k)
        if m:
            return f"features.{m.group(1)}.{m.group(2)}"
        m = re.fullmatch(r"lin(\d)(?:\.model\.\d)?\.weight", k) or re.fullmatch(r"lins\.(\d)\.weight", k)
        if m:
            return f"lins.{m.group(1)}.weight"
        return None

    def load_weights(self, state: dict) -> "LPIPS":
        """Load a state dict with the keys listed in the class docstring (strict on those)."""
        want = {k for k in self.state_dict() if k not in ("shift", "scale")}
        got = {}
        for k, v in state.items():
            c = self._canonical(k)
            if c is not None:
                got[c] = torch.as_tensor(v)
        missing = sorted(want - set(got))
        if missing:
            raise ValueError(f"LPIPS weights lack {len(missing)} tensors, e.g. {missing[:4]} "
                             "(expected VGG16 features.* and lin*.weight keys)")
        own = self.state_dict()
        for k in want:
            if tuple(got[k].shape) != tuple(own[k].shape):
                raise ValueError(f"LPIPS weight {k}: shape {tuple(got[k].shape)}, expected "
                                 f"{tuple(own[k].shape)}")
        self.load_state_dict({**{k: got[k] for k in want}, "shift": own["shift"],
                              "scale": own["scale"]})
        return self

    def _feats(self, x: torch.Tensor) -> list[torch.Tensor]:
        x = (x - self.shift) / self.scale
        out = []
        for i, layer in enumerate(self.features):
            x = layer(x)
            if i in _TAPS:
                out.append(x)
            if i >= _TAPS[-1]:
                break
        return out

    @torch.no_grad()
    def forward(self, img, gt) -> torch.Tensor:
        """LPIPS of uint8-rounded images, [H, W, 3] -> scalar tensor, [B, H, W, 3] -> [B]."""
        a = torch.from_numpy(to_uint8(img).astype(np.float32))
        b = torch.from_numpy(to_uint8(gt).astype(np.float32))
        if a.shape != b.shape or a.shape[-1] != 3 or a.ndim not in (3, 4):
            raise ValueError(f"expected two [H, W, 3] or [B, H, W, 3] images, got "
                             f"{tuple(a.shape)} and {tuple(b.shape)}")
        single = a.ndim == 3
        dev = self.shift.device
        a, b = (t.reshape((-1,) + t.shape[-3:]).permute(0, 3, 1, 2).to(dev) / 127.5 - 1.0
                for t in (a, b))
        d = torch.zeros(a.shape[0], device=dev)
        for lin, fa, fb in zip(self.lins, self._feats(a), self._feats(b)):
            na = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            nb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            d = d + lin((na - nb) ** 2).mean(dim=(1, 2, 3))
        return d[0] if single else d


LPIPS_LIN_FILE = "weights/v0.1/vgg.pth"              # inside the lpips package
VGG16_FILE = "vgg16-397923af.pth"                   # torchvision's ImageNet VGG16 weights


def find_lpips_weights() -> Optional[str]:
    """``"LIN,VGG"`` when both halves of the field's LPIPS (VGG) are on this machine already: the
    lpips package's linear layers (``lpips/weights/v0.1/vgg.pth``, found without importing the
    package, which needs torchvision) and torchvision's VGG16 file in the torch hub cache
    (``$TORCH_HOME/hub/checkpoints/vgg16-397923af.pth``). Nothing is ever downloaded."""
    import importlib.util

    try:
        spec = importlib.util.find_spec("lpips")
    except (ImportError, ValueError):
        spec = None
    if spec is None or not spec.origin:
        return None
    lin = Path(spec.origin).parent / LPIPS_LIN_FILE
    vgg = Path(torch.hub.get_dir()) / "checkpoints" / VGG16_FILE
    return f"{lin},{vgg}" if lin.is_file() and vgg.is_file() else None


def default_lpips(weights: str | Path | None = None, device: str | torch.device = "cpu"
                  ) -> tuple[LPIPS | None, str | None]:
    """:func:`load_lpips` of ``weights``, else of the files :func:`find_lpips_weights` finds on
    this machine: LPIPS is measured whenever both weight files can be found."""
    return load_lpips(weights or find_lpips_weights(), device)


def lpips_paths(weights: str | Path) -> list[Path]:
    """The files of a ``--lpips-weights`` value: one path, or several joined by commas."""
    return [Path(w.strip()).expanduser() for w in str(weights).split(",") if w.strip()]


def load_lpips(weights: str | Path | None, device: str | torch.device = "cpu"
               ) -> tuple[LPIPS | None, str | None]:
    """(model, None) when ``weights`` names existing files, else (None, reason).

    ``weights``: one ``.pth`` with both parts, or several joined by commas whose state dicts
    are merged, e.g. the lpips package's ``vgg.pth`` (linear layers) and torchvision's
    ``vgg16-397923af.pth`` (backbone). A file that exists but lacks the expected tensors raises
    ``ValueError``: a user who passed weights gets an error, not a silently missing metric.
    """
    if weights is None:
        return None, LPIPS_UNAVAILABLE
    state: dict = {}
    for p in lpips_paths(weights):
        if not p.is_file():
            return None, f"{LPIPS_UNAVAILABLE} (no file at {p})"
        from baseline.fileio import open_checked

        f, _, _ = open_checked(p, "LPIPS weights")
        with f:
            part = torch.load(f, map_location="cpu", weights_only=True)
        if isinstance(part, dict) and "state_dict" in part and isinstance(part["state_dict"], dict):
            part = part["state_dict"]
        if not isinstance(part, dict):
            raise ValueError(f"LPIPS weights {p}: not a state dict")
        state.update(part)
    return LPIPS().load_weights(state).to(device), None
