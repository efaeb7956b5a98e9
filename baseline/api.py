"""The toolkit from Python, in five calls: train, encode, decode, render, evaluate.

    from baseline import api
    run = api.train("runs/demo/scene", "runs/hac", patches=["demo"])  # a run folder
    pgs = api.encode(run, "runs/hac.pgs")                             # one self-contained file
    model = api.decode(pgs)                                           # decoded, with its scene
    images = api.render(model)                                        # uint8 [H, W, 3] per test view
    print(api.evaluate(model, out="runs/hac-test")["psnr"])           # + renders/, gt/, per_view.json

Each call is what the command of the same name does, with the same guards: nothing is written
onto a run's records or into a scene (:mod:`baseline.guard`), a training into a folder that
holds a run needs ``resume`` or ``overwrite``, and bad input raises ``ValueError`` /
``FileNotFoundError`` naming the problem. A model to render or evaluate is a run folder, a
``.pgs`` file, or what :func:`decode` returned; run folders render as the codec stores them
(HAC's adaptive phase: quantized values, 16-bit positions), so a run and its file render alike.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from baseline.run import Renderable

__all__ = ["decode", "encode", "evaluate", "render", "train"]


def train(scene: str | Path, out: str | Path, patches: Sequence[str] = (),
          sets: Sequence[str] = (), *, resume: bool = False, overwrite: bool = False,
          progress: bool = False) -> Path:
    """Train a model on ``scene`` (a COLMAP or Blender folder) into the run folder ``out``,
    with config ``patches`` applied in order, then ``sets`` (``"train.iterations=1000"``), as
    ``pgs train SCENE --out OUT --patch P --set K=V``; evaluated on the test views
    (``out/results.json``, ``out/test/ours_<iterations>/``). Returns ``out``."""
    from baseline import registry
    from baseline.config import build_config
    from baseline.run import prepare_run_folder, train_run

    registry.ensure_loaded()
    cfg = build_config(list(patches), list(sets))
    out = prepare_run_folder(scene, out, resume=resume, overwrite=overwrite)
    train_run(str(scene), out, cfg, resume=resume, progress=progress)
    return out


def encode(run: str | Path, path: str | Path, *, overwrite: bool = False) -> Path:
    """Compress the trained run folder ``run`` into the ``.pgs`` file ``path`` (its codec
    settings, the file naming its scene), as ``pgs encode RUN -o PATH``. Returns ``path``."""
    from baseline.run import encode_run

    encode_run(run, path, overwrite=overwrite)
    return Path(path)


def decode(path: str | Path, scene: str | Path | None = None,
           device: str | None = None) -> Renderable:
    """Decode a ``.pgs`` file (from the file alone, on the CPU, then moved to ``device``) and
    load the scene it names (or ``scene``): a :class:`~baseline.run.Renderable` with
    ``.model``, ``.cfg``, ``.scene``, ``.cameras(split)`` and ``.render(camera)``."""
    return Renderable(path, None if scene is None else str(scene), device=device)


def _source(model) -> str:
    """What a model was read from (a run folder or a ``.pgs`` file), as output markers name it."""
    return str(model.target if isinstance(model, Renderable) else model)


def _renderable(model, scene=None) -> Renderable:
    return model if isinstance(model, Renderable) else Renderable(
        model, None if scene is None else str(scene))


def render(model, split: str = "test", out: str | Path | None = None,
           scene: str | Path | None = None) -> list[np.ndarray]:
    """Render every view of ``split`` (test or train) of ``model`` (a run folder, a ``.pgs``
    file or what :func:`decode` returned): uint8 images [H, W, 3], one per view in the scene's
    order, rounded as the metrics round them. ``out``: also written there as PNG
    (``out/renders/<view>.png``; the folder may be no run's and in no scene)."""
    from baseline.data.images import write_png_atomic
    from baseline.eval.evaluate import view_file_names
    from baseline.eval.metrics import to_uint8
    from baseline.guard import check_output, write_marker

    if out is not None:
        check_output(out, command="render", source=_source(model), folder=True)
    r = _renderable(model, scene)
    if out is not None:
        write_marker(out, "render", _source(model))
    cams = r.cameras(split)
    images = [to_uint8(r.render(c)) for c in cams]
    if out is not None:
        for name, img in zip(view_file_names(cams), images):
            write_png_atomic(Path(out) / "renders" / name, img)
    return images


def evaluate(model, split: str = "test", out: str | Path | None = None,
             scene: str | Path | None = None, lpips_weights: str | None = None) -> dict:
    """PSNR, SSIM (3DGS's; ``ssim_skimage`` scikit-image's), LPIPS (when its weights are found
    or given: ``lpips_weights``, as ``--lpips-weights``) on uint8 images, FPS and Gaussians per
    view of ``model`` on ``split``, as ``pgs eval``. ``out``: also ``renders/``, ``gt/`` and
    ``per_view.json`` there, as 3DGS lays out ``test/ours_<iterations>/``."""
    from baseline.eval.metrics import default_lpips
    from baseline.guard import check_output, write_marker

    if out is not None:
        check_output(out, command="render", source=_source(model), folder=True)
    r = _renderable(model, scene)
    if out is not None:
        write_marker(out, "render", _source(model))
    lpips_fn, _ = default_lpips(lpips_weights)
    return r.evaluate(split, render_dir=None if out is None else Path(out), lpips_fn=lpips_fn)
