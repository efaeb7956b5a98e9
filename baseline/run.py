"""Run folders: train into one, reload it, evaluate it.

A run folder holds ``config.toml`` (the merged config), ``scene.json`` (where the scene is and
how it was loaded), ``checkpoint.pt``, ``results.json`` and ``test/ours_<iterations>/``
(``renders/``, ``gt/``, ``per_view.json``: 3DGS's layout, :mod:`baseline.eval.evaluate`).
"""
from __future__ import annotations

import json
import platform
from pathlib import Path
from typing import Optional

import torch

from baseline.config import TRAINING_SEMANTICS, Config, component_semantics, from_toml
from baseline.fileio import write_text_atomic
from baseline.train.trainer import CHECKPOINT_NAME, Trainer


def load_scene_for(cfg: Config, scene_path: str, progress: bool = True):
    from baseline.data.scene import load_scene

    bg = (1.0, 1.0, 1.0) if cfg.data.background == "white" else (0.0, 0.0, 0.0)
    return load_scene(scene_path, resolution=cfg.data.resolution, images=cfg.data.images or None,
                      eval=cfg.data.eval, test_every=cfg.data.test_every, background=bg,
                      cache_dir=cfg.data.cache_dir or None,
                      random_init_points=cfg.data.random_init_points,
                      random_init_extent=cfg.data.random_init_extent, seed=cfg.train.seed,
                      near=cfg.data.near, progress=progress)


def write_json_atomic(path: Path, data: dict) -> None:
    """``data`` as indented JSON (tensors and numpy scalars converted), written atomically."""
    write_text_atomic(path, json.dumps(data, indent=2, default=_json_default))


def _json_default(o):
    if isinstance(o, (torch.Tensor,)):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    return str(o)


def versions() -> dict:
    import numpy

    v = {"python": platform.python_version(), "torch": torch.__version__, "numpy": numpy.__version__}
    for mod in ("numba", "pycolmap", "constriction", "gsplat"):
        try:
            v[mod] = __import__(mod).__version__
        except Exception:
            pass
    import baseline

    v["pgs"] = baseline.__version__
    return v


def prepare_run_folder(scene_path: str | Path, out: str | Path, *, resume: bool = False,
                       overwrite: bool = False) -> Path:
    """Check that a training may write ``out`` before anything is written (``pgs train`` and
    :func:`baseline.api.train`): the scene is readable (a wrong path leaves no folder behind);
    ``out`` is new, empty, a run of this scene (started, or with ``resume`` finished; resuming
    needs its checkpoint) or with ``overwrite`` any run or toolkit output, whose run records are
    removed under its lock (never while another process trains there); never a folder of the
    user's files (:func:`baseline.guard.check_output`)."""
    from baseline.data.readers import detect_format
    from baseline.guard import RUN_FILES, RunLock, check_output

    detect_format(Path(scene_path))
    out = Path(out)
    check_output(out, command="train", source=scene_path, folder=True, overwrite=overwrite,
                 may_be_run=resume or overwrite)
    if resume and not (out / CHECKPOINT_NAME).is_file():
        raise ValueError(f"--resume: {out} holds no run to resume (no {CHECKPOINT_NAME}); leave "
                         f"--resume out to start one")
    if overwrite and not resume and out.is_dir():
        with RunLock(out):
            for name in RUN_FILES:
                (out / name).unlink(missing_ok=True)
    return out


def encode_run(run_dir: str | Path, output: str | Path, *, overwrite: bool = False,
               codec: Optional[dict] = None, trainer=None) -> tuple[dict, Trainer]:
    """Encode a trained run to ``output`` (``pgs encode`` and :func:`baseline.api.encode`):
    ``output`` is new, this run's own earlier file (the one its record names), or with
    ``overwrite`` any file (:func:`baseline.guard.check_output`); the file names its scene
    (:func:`file_header`), and anchors far outside the scene are refused; ``codec``: codec
    settings other than the run's (``{"positions": "sorted", ...}``), a file the run's record
    does not keep. Returns the encoder's stats and the run's trainer (loaded on the CPU, where
    the codec runs)."""
    import dataclasses

    from baseline.modelfile import encode_model
    from baseline.data.scene import scene_bounds
    from baseline.fileio import read_json_bounded
    from baseline.guard import check_output

    run_dir = Path(run_dir)
    record = run_dir / "results.json"

    def own(path):               # the file this run's record says it encoded there
        try:
            enc = (read_json_bounded(record) if record.is_file() else {}).get("encode") or {}
        except ValueError:
            return False
        return (isinstance(enc.get("file"), str) and Path(enc["file"]).resolve() == path.resolve()
                and path.read_bytes()[:4] == b"PGS\x00")

    check_output(output, command="encode", source=run_dir, overwrite=overwrite, own=own)
    if trainer is None:
        trainer, scene = load_run(run_dir, device="cpu")
    else:
        scene = trainer.scene
    scene_path = read_json_bounded(run_dir / "scene.json")["path"]
    cfg = trainer.cfg
    over = {k: v for k, v in (codec or {}).items() if v and v != getattr(cfg.codec, k)}
    if over:
        cfg = dataclasses.replace(cfg, codec=dataclasses.replace(cfg.codec, **over))
    st = encode_model(cfg, trainer.model, trainer.entropy, output,
                      extra_header=file_header(scene, scene_path), scene_bounds=scene_bounds(scene))
    if not over:            # the run's own configuration: record it with the run
        full = read_json_bounded(record) if record.exists() else {}
        full["encode"] = {"file": str(output), "bytes": st["bytes"], "encode_s": st["encode_s"],
                          "anchors": st["anchors"], "sections": st["sections"]}
        write_json_atomic(record, full)
    return st, trainer


def decoded_scene(dec, scene_override=None):
    """The scene of a decoded file when it is here (``scene_override`` or the path its header
    names), else None."""
    path = scene_override or dec.scene_path
    if not path or not Path(path).exists():
        return None
    return load_scene_for(dec.cfg, path, progress=False)


def decode_run(file: str | Path, out: str | Path, *, scene: Optional[str] = None,
               render: str = "none", device: Optional[str] = None, sh_degree: int = 3,
               overwrite: bool = False, echo=print) -> dict:
    """Decode a ``.pgs`` file into the folder ``out`` (``pgs decode``): optionally evaluate the
    decoded model on one split (``render``: ``test``, ``train`` or ``none``; renders under
    ``out/<split>/``, FPS also without a feature provider's decoded-model cache), then export
    its Gaussians to ``out/point_cloud.ply``: the union over the training views with SH colours
    when the scene is here, else the Gaussians seen from the file's mean training camera with
    degree-0 colours. ``out`` is new, this command's own earlier folder, or with ``overwrite``
    any folder :func:`baseline.guard.check_output` allows; nothing is written unless the file
    decodes, and a failure leaves no new folder behind. ``echo`` prints the progress lines.
    Returns the record written to ``out/results.json``."""
    import shutil

    import torch

    from baseline.contracts import feature_cache
    from baseline.eval.export import export_run_ply, export_sh_ply, format_sh_export
    from baseline.eval.metrics import format_psnr
    from baseline.fileio import read_json_bounded
    from baseline.guard import check_output, write_marker
    from baseline.modelfile import decode_model

    out = Path(out)

    def own(folder):             # written before folders were marked: its record names the file
        try:
            rec = read_json_bounded(folder / "results.json", "a pgs record")
        except ValueError:
            return False
        return isinstance(rec, dict) and "ply" in rec and isinstance(rec.get("file"), str) and \
            Path(rec["file"]).resolve() == Path(file).resolve()

    # never a run's folder, never inside a scene, never a folder of the user's files
    check_output(out, command="decode", source=file, folder=True, overwrite=overwrite,
                 own=own, shares=("eval",))
    dec = decode_model(file)               # nothing is written unless the file decodes
    echo(f"decoded {file}: {dec.model.n_anchors} anchors in {dec.decode_s:.2f} s")
    res = {"file": str(file), "bytes": Path(file).stat().st_size, "decode_s": dec.decode_s,
           "anchors": dec.model.n_anchors}
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_marker(out, "decode", file)
        center = dec.header.get("view_center")
        r = None
        if render != "none" or center is None:
            r = Renderable(file, scene, device=device, decoded=dec)
        if render != "none":
            from baseline.eval.evaluate import method_key
            from baseline.eval.metrics import default_lpips

            res[render] = r.evaluate(render, render_dir=out / render / method_key(r.iterations),
                                     lpips_fn=default_lpips()[0])
            t = res[render]
            echo(f"{render}: PSNR {format_psnr(t['psnr'], 3)}  SSIM {t['ssim']:.4f}  "
                 f"FPS {t['fps']:.1f}")
            prov = feature_cache(r.model)
            if prov is not None:             # FPS without the provider's decoded-model cache
                prov.clear_cache()
                r.model.unbake()             # (a bake holds the cached features' first-layer terms)
                nc = r.evaluate(render)
                prov.build_cache(r.model.positions())
                r.model.bake_if_faster()
                t["fps_no_cache"] = nc["fps"]
                echo(f"FPS without the feature cache {nc['fps']:.1f} (with {t['fps']:.1f})")
        model = r.model if r is not None else dec.model
        model.to("cpu")
        ply = out / "point_cloud.ply"
        sc = r.scene if r is not None else decoded_scene(dec, scene)
        if sc is not None and r is None:        # (Renderable checked its own)
            from baseline.data.scene import scene_bounds
            from baseline.scaffold.model import check_bounds

            check_bounds(model, str(file), *scene_bounds(sc))
        if sc is not None and sc.train_cameras:
            model.unbake()
            res["ply"] = export_sh_ply(model, sc, ply, sh_degree=sh_degree, source=str(file))
            echo(format_sh_export(res["ply"]))
        else:
            n = export_run_ply(model, None, ply,
                               center=None if center is None else torch.tensor(center))
            res["ply"] = {"path": str(ply), "gaussians": n, "sh_degree": 0,
                          "note": "scene not here: one viewpoint's Gaussians, degree-0 colours"}
            echo(f"wrote {n} Gaussians to {ply}: the scene {dec.scene_path} is not here, so "
                 f"these are the Gaussians seen from the mean training camera with degree-0 "
                 f"colours (pass --scene PATH for the view-union export with SH colours)")
        write_json_atomic(out / "results.json", res)
    except BaseException:
        if created:                          # a failed decode leaves nothing behind
            shutil.rmtree(out, ignore_errors=True)
        raise
    return res


def train_run(scene_path: str, out: str | Path, cfg: Config, resume: bool = False,
              progress: bool = True, evaluate_after: bool = True) -> dict:
    """Train (or resume) a run in ``out`` and evaluate it on the test views."""
    from baseline.guard import RunLock, check_resume

    out = Path(out)
    scene = load_scene_for(cfg, scene_path, progress=progress)
    with RunLock(out):                     # one process writes a run folder at a time
        trainer = Trainer(cfg, scene, out, progress=progress)
        ck = out / CHECKPOINT_NAME
        if resume and ck.exists():
            check_resume(out, cfg, scene, scene_path)   # the same scene and training config
            trainer.load_checkpoint(ck)
            print(f"resumed from {ck} at iteration {trainer.iteration}")
        write_scene_record(out, scene, scene_path)
        trainer.train()
        return _finish_run(trainer, scene, scene_path, out, cfg, evaluate_after)


def write_scene_record(out: Path, scene, scene_path) -> None:
    """Write ``out/scene.json``: what the run is trained on (``scene_identity``, checked on
    resume) and the scene's evaluation protocol; every command that loads the run reads it."""
    from baseline.guard import scene_identity

    write_json_atomic(Path(out) / "scene.json", {**scene_identity(scene, scene_path),
                                                 "protocol": getattr(scene, "protocol", {})})


def _finish_run(trainer, scene, scene_path, out: Path, cfg: Config, evaluate_after: bool) -> dict:
    from baseline.device import device_name
    from baseline.render import resolve_backend

    results = {
        "config_patches": cfg.patches,
        "scene": str(Path(scene_path).resolve()),
        "protocol": getattr(scene, "protocol", {}),
        "training_semantics": TRAINING_SEMANTICS,
        "component_semantics": component_semantics(cfg),
        "iterations": trainer.iteration,
        "train_time_s": trainer.train_time,
        "s_per_it": trainer.train_time / max(trainer.iteration, 1),
        # of train_time, the seconds the process ran on no core (paused, or sharing its core;
        # CPU runs only), counted from iteration stall_from when that is not 0
        **({"stall_s": trainer.stall_time} if trainer.stall_time is not None else {}),
        **({"stall_from": trainer.stall_from}
           if trainer.stall_time is not None and trainer.stall_from else {}),
        "threads": trainer.threads,
        # present when the run was resumed at another thread count: [first iteration, threads]
        # per stretch (threads None: not recorded by the checkpoint it resumed from)
        **({"threads_by_iteration": trainer.thread_segments}
           if len(trainer.thread_segments) > 1 else {}),
        "device": device_name(trainer.device),
        "machine": trainer.machine,
        # present when the run was resumed on another machine, or from a checkpoint that did
        # not keep it (None): [first iteration, machine] per stretch
        **({"machines_by_iteration": trainer.machine_segments}
           if len(trainer.machine_segments) > 1 else {}),
        "code": trainer.code,
        # present when the run was resumed by other code (or from a checkpoint that did not
        # keep it): [first iteration, code] per stretch
        **({"codes_by_iteration": trainer.code_segments}
           if len(trainer.code_segments) > 1 else {}),
        "backend": resolve_backend(cfg.train.rasterizer, trainer.model.xyz),
        "voxel_size": trainer.voxel_size,
        "anchors": trainer.model.n_anchors,
        "versions": versions(),
    }
    if evaluate_after:
        from baseline.eval.evaluate import method_key
        from baseline.eval.metrics import default_lpips

        folder = out / "test" / method_key(trainer.iteration)
        results["test"] = evaluate_trainer(trainer, scene, render_dir=folder
                                           if cfg.train.save_test_renders else None,
                                           lpips_fn=default_lpips()[0])
    write_json_atomic(out / "results.json", results)
    return results


def file_header(scene, scene_path: str) -> dict:
    """What a ``.pgs`` file records of its scene: the path (for ``--render``) and the export
    viewpoint (the mean training-camera centre: ``pgs decode`` writes the PLY without the
    scene)."""
    from baseline.eval.export import view_center

    return {"scene": str(scene_path),
            "view_center": [float(x) for x in view_center(scene.train_cameras)]}


def coded_state(trainer: Trainer):
    """The anchors as the codec stores them (:class:`baseline.pipeline.CodedState`) in the
    adaptive phase, else None."""
    if trainer.phase != "adaptive":
        return None
    from baseline.pipeline import coded_state as _coded

    return _coded(trainer.model, trainer.entropy, trainer.cfg.codec.positions)


def evaluate_trainer(trainer: Trainer, scene, render_dir: Optional[Path] = None, lpips_fn=None) -> dict:
    from baseline.eval.evaluate import evaluate

    cams = scene.test_cameras or scene.train_cameras
    return evaluate(trainer.model, scene, cams, phase=trainer.phase, entropy=trainer.entropy,
                    backend=trainer.cfg.train.rasterizer, coded=coded_state(trainer),
                    render_dir=render_dir, lpips_fn=lpips_fn, iterations=trainer.iteration)


def _scene_path(run_dir: Path) -> str:
    """The scene a run records in its ``scene.json`` (read bounded)."""
    from baseline.fileio import read_json_bounded

    rec = read_json_bounded(run_dir / "scene.json", "a run's scene record")
    if not isinstance(rec, dict) or not isinstance(rec.get("path"), str):
        raise ValueError(  # noqa: TRY004 - a damaged record: bad input, exit 2
            f"{run_dir / 'scene.json'}: holds no scene path; train the run again")
    return rec["path"]


def load_run(run_dir: str | Path, progress: bool = False,
             device: str | None = None) -> tuple[Trainer, object]:
    """Rebuild the trainer of a run folder from its config and checkpoint.

    ``device``: where to put the model (None: the config's ``train.device``); the encoder loads
    runs on the CPU, where the codec runs."""
    run_dir = Path(run_dir)
    for name in ("config.toml", "scene.json", CHECKPOINT_NAME):
        if not (run_dir / name).exists():
            raise FileNotFoundError(f"{run_dir} is not a finished run folder: {name} is missing")
    cfg = from_toml(run_dir / "config.toml")
    scene_path = _scene_path(run_dir)
    scene = load_scene_for(cfg, scene_path, progress=progress)
    trainer = Trainer(cfg, scene, run_dir, progress=progress, device=device)
    trainer.load_checkpoint(run_dir / CHECKPOINT_NAME)
    return trainer, scene


class Renderable:
    """Anything `pgs eval` / `pgs render` can draw: a run folder or a decoded ``.pgs`` file."""

    def __init__(self, target: str | Path, scene_override: Optional[str] = None,
                 device: str | None = None, decoded=None):
        """``device``: where to render (None: the config's ``train.device``). A ``.pgs`` file is
        decoded on the CPU, then moved (``decoded``: its :class:`DecodedModel` when the caller
        decoded it already)."""
        from baseline.device import resolve_device

        target = Path(target)
        self.target = target
        self.entropy = None
        self.coded = None
        if target.is_file():
            from baseline.modelfile import decode_model

            dec = decoded if decoded is not None else decode_model(target)
            self.decoded = dec
            self.cfg, self.model, self.phase = dec.cfg, dec.model, "decoded"
            self.iterations = dec.cfg.train.iterations      # what the file's model trained for
            self.model.to(resolve_device(device or self.cfg.train.device))
            self.model.bake_if_faster()
            scene_path = scene_override or dec.header.get("scene")
            if not scene_path:
                raise ValueError(f"{target} does not record its scene; pass --scene PATH")
            if not Path(scene_path).exists():
                raise FileNotFoundError(f"{target} was written for the scene {scene_path}, "
                                        f"which is not here; pass --scene PATH")
        else:
            if not (target / "config.toml").exists():
                raise FileNotFoundError(f"{target} is neither a .pgs file nor a run folder")
            trainer, scene = load_run(target, device=device)
            self.trainer = trainer
            self.cfg, self.model, self.phase = trainer.cfg, trainer.model, trainer.phase
            self.iterations = trainer.iteration
            self.entropy = trainer.entropy
            self.coded = coded_state(trainer)
            scene_path = scene_override or _scene_path(target)
            if scene_override is None:
                self.scene = scene
        if not hasattr(self, "scene"):
            self.scene = load_scene_for(self.cfg, scene_path)
        if self.phase == "decoded":     # a file's anchors against the scene it is drawn in
            from baseline.data.scene import scene_bounds
            from baseline.scaffold.model import check_bounds

            check_bounds(self.model, str(target), *scene_bounds(self.scene))
        self.scene_path = scene_path

    def cameras(self, split: str = "test") -> list:
        """The views of ``split`` (the training views when the scene holds no test view)."""
        cams = self.scene.test_cameras if split == "test" else self.scene.train_cameras
        return cams or self.scene.train_cameras

    def render(self, cam):
        """One view [H, W, 3] float in [0, 1], rendered exactly as :meth:`evaluate` renders it
        (the decoded model, or a run's coded state in HAC's adaptive phase)."""
        from baseline.pipeline import render_view

        bg = self.scene.background.float().to(self.model.xyz.device)
        with torch.no_grad():
            return render_view(self.model, cam, bg, phase=self.phase, training=False,
                               entropy=self.entropy, backend=self.cfg.train.rasterizer,
                               coded=self.coded).render.image

    def evaluate(self, split: str = "test", render_dir: Optional[Path] = None, lpips_fn=None) -> dict:
        """Metrics and FPS on ``split``; ``render_dir``: also ``renders/``, ``gt/`` and
        ``per_view.json`` there (3DGS's ``test/ours_<iterations>`` layout)."""
        from baseline.eval.evaluate import evaluate

        return evaluate(self.model, self.scene, self.cameras(split), phase=self.phase,
                        entropy=self.entropy, backend=self.cfg.train.rasterizer,
                        coded=self.coded, render_dir=render_dir, lpips_fn=lpips_fn,
                        iterations=self.iterations)
