"""The trainer: Adam with per-group exponential schedules, named hooks, exact resume.

About 630 lines: the step, its timing, the learning-rate schedules and exact resume share the
trainer's state, which is why they live in one class.

Hooks are :class:`baseline.contracts.TrainingHook` objects built as ``cls(trainer)`` from
registry kind ``hooks``: ``before_step(it)``, ``after_backward(it, ctx)``, ``after_step(it)``,
``state_dict()`` / ``load_state_dict(s)`` (saved in checkpoints), ``restore(it)`` (after a
checkpoint of iteration ``it`` is loaded) and ``log_fields()`` (added to each line of the
training log). They steer the trainer through ``trainer.phase``
(quantization phase), ``trainer.render_scale`` (progressive resolution) and
``trainer.extra_losses`` (name -> callable(ctx) -> scalar).
"""
from __future__ import annotations

import json
import math
import os
import random
import signal
import threading
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from baseline import registry
from baseline.config import Config, to_toml
from baseline.device import (code_version, keep_freed_memory, machine_name, make_generator,
                             resolve_device)
from baseline.fileio import (
    atomic_path,
    open_checked,
    read_text_bounded,
    write_text_atomic,
)
from baseline.memory import allocating
from baseline.pipeline import render_view
from baseline.contracts import TrainingHook
from baseline.scaffold.build import build_entropy, build_model, entropy_param_groups
from baseline.scaffold.densify import TrainingCollapsed  # noqa: F401  (raised by growing)
from baseline.timing import active as active_timer
from baseline.timing import stage
from baseline.train.losses import lr_exp, reconstruction_loss

CHECKPOINT_NAME = "checkpoint.pt"
TRAIN_LOG_NAME = "train_log.jsonl"
TENSORBOARD_DIR = "tb"
TENSORBOARD_MISSING = ("train.tensorboard = true needs the tensorboard package: pip install -e "
                       ".[tensorboard] (or pip install tensorboard)")


class TensorBoardLog:
    """The training curves in TensorBoard (``train.tensorboard``; ``RUN/tb/``), written with
    PyTorch's ``SummaryWriter`` every ``train.log_every`` iterations: the loss and its terms,
    the training PSNR, the rate term's bits per anchor (HAC's coding phase), anchors, Gaussians
    drawn and each parameter group's learning rate. A resumed run purges what was logged past
    its checkpoint, so the curves stay one run."""

    def __init__(self, folder: Path, iteration: int):
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError:
            raise ValueError(TENSORBOARD_MISSING) from None
        self.writer = SummaryWriter(log_dir=str(folder),
                                    purge_step=iteration + 1 if iteration > 0 else None)

    def log(self, it: int, terms: dict, trainer: "Trainer") -> None:
        w = self.writer
        for key in ("loss", "l1", "psnr"):
            if key in terms:
                w.add_scalar(f"train/{key}", float(terms[key]), it)
        for key, v in terms.items():        # the rate's and the masks' terms
            if key not in ("loss", "l1", "psnr", "gaussians", "bpp") and isinstance(v, (int, float)):
                w.add_scalar(f"terms/{key}", float(v), it)
        if "bpp" in terms:                  # bits per coded value x coded values per anchor
            w.add_scalar("rate/bits_per_anchor", float(terms["bpp"]) * trainer.rate_values_per_anchor, it)
            w.add_scalar("rate/bits_per_value", float(terms["bpp"]), it)
        w.add_scalar("model/anchors", trainer.model.n_anchors, it)
        w.add_scalar("model/gaussians", int(terms.get("gaussians", 0)), it)
        for g in trainer.optimizer.param_groups:
            w.add_scalar(f"lr/{g.get('name', 'group')}", float(g["lr"]), it)

    def close(self) -> None:
        self.writer.close()


class NonFiniteError(ValueError):
    """Training reached (or a checkpoint holds) NaN or Inf: nothing is written over the last
    good checkpoint."""


class TrainingStopped(KeyboardInterrupt):
    """SIGINT / SIGTERM during training: the step in flight finished and a checkpoint of it
    was written; ``--resume`` (or the same ``pgs compare``) continues from there."""

    def __init__(self, iteration: int, path):
        super().__init__(f"stopped at iteration {iteration}; checkpoint written to {path}")
        self.iteration, self.path = iteration, path


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity, e.g. under ``taskset``), not the machine's."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # platforms without affinity
        return os.cpu_count() or 1


def default_threads() -> int:
    """Threads for ``train.threads = 0``: the available cores, capped by ``OMP_NUM_THREADS`` when
    the environment sets it (``OMP_NUM_THREADS=1 pgs train ...`` then means one thread, as it
    does for any OpenMP program; ``torch.set_num_threads`` would otherwise override it)."""
    cores = available_cores()
    env = os.environ.get("OMP_NUM_THREADS", "").strip()
    try:
        cap = int(env.split(",")[0]) if env else 0
    except ValueError:
        cap = 0
    return min(cores, cap) if cap > 0 else cores


def set_threads(n: int) -> int:
    """Use ``n`` threads (0 = :func:`default_threads`) in torch and numba; never more than the
    cores."""
    cores = available_cores()
    n = default_threads() if n <= 0 else min(n, cores)
    try:
        import numba

        from baseline.render.cpu import configure_numba

        configure_numba("default")  # first: starting the pool may reset torch's threads
        numba.set_num_threads(min(n, numba.config.NUMBA_NUM_THREADS))
    except ImportError:  # numba absent
        pass
    torch.set_num_threads(n)
    return n


def _extend_segments(segs: Optional[list], iteration: int, value) -> list[list]:
    """A checkpoint's ``[first iteration, value]`` stretches (None: not kept, one unrecorded
    stretch from 0), with a new stretch from ``iteration`` where ``value`` differs from the
    last."""
    out = [list(x) for x in segs or [[0, None]]]
    if out[-1][1] != value:
        out.append([int(iteration), value])
    return out


class Trainer:
    """Trains one model on one scene.

    Args:
        device: where to train; None = the config's ``train.device`` (``auto``: a CUDA GPU when
            torch sees one). The model, entropy model, background and each ground-truth image
            live there; the scene's image cache stays in host memory.
    """

    def __init__(self, cfg: Config, scene, out_dir: str | Path, progress: bool = True,
                 device: str | torch.device | None = None):
        self.cfg = cfg
        self.scene = scene
        self.out = Path(out_dir)
        self.progress = progress
        self.device = resolve_device(str(device) if device is not None else cfg.train.device)
        keep_freed_memory()
        self.threads = set_threads(cfg.train.threads)
        # [first iteration, threads] per stretch of training: a run resumed at another thread
        # count trained its iterations at several (its time per iteration mixes them)
        self.thread_segments: list[list] = [[0, self.threads]]
        # [first iteration, machine] per stretch, likewise: a run resumed on another machine
        # (or from a checkpoint that did not keep it) has a time that measures no one machine
        self.machine = machine_name(self.device)
        self.machine_segments: list[list] = [[0, self.machine]]
        # [first iteration, code] per stretch, likewise: the toolkit's commit (a run resumed by
        # other code, even code that computes the same numbers, has a time of neither)
        self.code = code_version()
        self.code_segments: list[list] = [[0, self.code]]
        torch.manual_seed(cfg.train.seed)
        np.random.seed(cfg.train.seed)
        random.seed(cfg.train.seed)
        # View order and growing draw from a CPU generator (the same stream on every device);
        # the per-step noise and rate sample from one on the training device (on the CPU they
        # are the same generator, as before device support).
        self.generator = torch.Generator().manual_seed(cfg.train.seed)
        self.step_generator = (self.generator if self.device.type == "cpu"
                               else make_generator(cfg.train.seed + 1, self.device))
        self.model, self.voxel_size = build_model(cfg, scene.points)
        self.entropy = build_entropy(cfg, self.model)
        self.mask_training = registry.get("mask_training", cfg.entropy.mask_training)(self)
        self.model.mask_after_selection = self.mask_training.mask_after_selection
        self.model.to(self.device)
        self.entropy.to(self.device)
        self.extent = float(scene.extent)
        self.background = scene.background.float().to(self.device)
        self.phase = "none"
        self.render_scale = 1.0
        self.extra_losses: dict = {}
        self.iteration = 0
        self._last_saved: Optional[int] = None
        self._ema_loss: Optional[float] = None
        self.train_time = 0.0
        # Stall time: the part of train_time in which the process ran on no core (a suspended
        # process, or one sharing its core with other work), summed per step as wall time
        # minus process CPU time where positive. While a step runs, at least one thread of the
        # process computes, so a healthy step's CPU time is about its wall time at any thread
        # count (measured: 0.99 of it at one thread beside another training on a 2-core
        # machine); a SIGSTOP pause inside a step is all stall. A lower bound where several
        # threads run (a thread left waiting while another computes is not counted). CPU only:
        # on a GPU the host thread may sleep in a synchronize, so None there. stall_from: the
        # iteration it is counted from (a run resumed from a checkpoint that did not keep it).
        self.stall_time: Optional[float] = 0.0 if self.device.type == "cpu" else None
        self.stall_from = 0
        self._view_order: list[int] = []
        self.optimizer = self._make_optimizer()
        self.hooks: list[TrainingHook] = [registry.get("hooks", name)(self)
                                          for name in cfg.train.hooks]

    # ---------------------------------------------------------------------------- optimizer
    def _make_optimizer(self) -> torch.optim.Adam:
        """Adam (eps 1e-15, per-group learning rates set by the schedules).

        The fused implementation (one pass per tensor) where PyTorch has it for these tensors:
        the same update as the default loop to float rounding (measured max difference 1.5e-8)
        and 3.3x faster on the CPU with truck-sized per-anchor tensors (88 vs 292 ms per step).
        """
        groups = self._param_groups()
        self._fused = False
        try:
            opt = torch.optim.Adam(groups, lr=0.0, eps=1e-15, fused=True)
            self._fused = True
            return opt
        except (RuntimeError, ValueError):  # a device / dtype without a fused kernel
            return torch.optim.Adam(self._param_groups(), lr=0.0, eps=1e-15)

    def _mask_lr_scale(self) -> float:
        """``lr.mask_schedule_scaled``: the mask logits' learning rate times schedule_base /
        iterations, so that the largest distance Adam can move a logit over the run (the sum of
        the per-step learning rates) is the paper schedule's; 1 otherwise."""
        t = self.cfg.train
        return t.schedule_base / t.iterations if self.cfg.lr.mask_schedule_scaled else 1.0

    def _param_groups(self) -> list[dict]:
        cfg, lr, ext = self.cfg, self.cfg.lr, self.extent
        mask_ext = ext * self._mask_lr_scale()
        mask_final = self.mask_training.mask_lr_final(cfg, mask_ext)
        m = self.model
        groups = [
            dict(name="offsets", params=[m.per_anchor["offsets"]], lr_init=lr.offset_init * ext,
                 lr_final=lr.offset_final * ext),
            dict(name="scaling", params=[m.per_anchor["scaling"]], lr_init=lr.scaling, lr_final=lr.scaling),
            dict(name="mask", params=[m.per_anchor["mask"]], lr_init=lr.mask_init * mask_ext,
                 lr_final=lr.mask_final * mask_ext if mask_final is None else mask_final),
            dict(name="mlp_opacity", params=list(m.decoder.mlp_opacity.parameters()),
                 lr_init=lr.mlp_opacity_init, lr_final=lr.mlp_opacity_final),
            dict(name="mlp_cov", params=list(m.decoder.mlp_cov.parameters()), lr_init=lr.mlp_cov,
                 lr_final=lr.mlp_cov),
            dict(name="mlp_color", params=list(m.decoder.mlp_color.parameters()),
                 lr_init=lr.mlp_color_init, lr_final=lr.mlp_color_final),
        ]
        groups += m.provider.param_groups(cfg)
        if m.refiner is not None:
            groups += m.refiner.param_groups(cfg)
        groups += entropy_param_groups(cfg, self.entropy)
        for g in groups:
            g["lr"] = g["lr_init"]
        return [g for g in groups if g["params"]]

    @property
    def rate_values_per_anchor(self) -> int:
        """The rate's per-value denominator (``entropy.rate_values_per_anchor``; 0: the method's
        own coded values per anchor, as HAC's code computes it: 86 for feat 50 + scaling 6 + offsets 30)."""
        v = self.cfg.entropy.rate_values_per_anchor
        return v if v > 0 else sum(a.dims for a in self.model.coded_attributes())

    @property
    def hash_values_per_anchor(self) -> int:
        """The hash bits' per-value denominator (``entropy.hash_values_per_anchor``; 0: the
        rate's, :attr:`rate_values_per_anchor`)."""
        v = self.cfg.entropy.hash_values_per_anchor
        return v if v > 0 else self.rate_values_per_anchor

    def update_lr(self, it: int) -> None:
        total = self.cfg.train.iterations
        for g in self.optimizer.param_groups:
            g["lr"] = lr_exp(it, total, g["lr_init"], g["lr_final"])

    def on_anchors_changed(self, n_before: int, n_after: int) -> None:
        """Called by growing/pruning hooks after the anchor set changed."""

    # ------------------------------------------------------------------------------- views
    def next_view(self):
        if not self._view_order:
            n = len(self.scene.train_cameras)
            self._view_order = torch.randperm(n, generator=self.generator).tolist()
        return self.scene.train_cameras[self._view_order.pop()]

    # -------------------------------------------------------------------------------- loop
    def step(self, it: int) -> dict:
        """One training iteration. Its stages are named for ``pgs bench train``
        (:mod:`baseline.timing`; free when no bench is timing them)."""
        cfg = self.cfg
        self.model.iteration = it          # the birth of anchors grown in this step
        with stage("hooks before"):
            for h in self.hooks:
                h.before_step(it)
            self.update_lr(it)
        with stage("view + ground truth"):
            cam = self.next_view()
            gt = self.scene.image(cam).to(self.device, non_blocking=True)
            if self.render_scale != 1.0:
                cam_r = cam.scaled(self.render_scale)
                gt = torch.nn.functional.interpolate(
                    gt.permute(2, 0, 1)[None], size=(cam_r.height, cam_r.width), mode="bilinear",
                    align_corners=False, antialias=False)[0].permute(1, 2, 0)
                cam = cam_r
        res = render_view(self.model, cam, self.background, phase=self.phase, training=True,
                          entropy=self.entropy,
                          rate_sample=self.mask_training.render_rate_sample,
                          backend=cfg.train.rasterizer, generator=self.step_generator,
                          decoder_quant=cfg.entropy.decoder_quant)
        g, out = res.gaussians, res.render
        if out.means2d.requires_grad:
            out.means2d.retain_grad()
        with stage("losses"):
            loss, l1 = reconstruction_loss(out.image, gt, cfg.train.lambda_dssim)
            terms = {"l1": float(l1.detach())}
            if g.scales.shape[0] > 0 and cfg.train.lambda_volume > 0:
                loss = loss + cfg.train.lambda_volume * g.scales.prod(dim=1).mean()
            if self.phase == "adaptive":        # the rate and the masks' training
                parts, logged = self.mask_training.loss(res)
                for p in parts:
                    loss = loss + p
                terms.update(logged)
            ctx = {"render": out, "gaussians": g, "camera": cam, "gt": gt, "result": res}
            for name, fn in self.extra_losses.items():
                loss = loss + fn(ctx)
        timer = active_timer()
        if timer is not None:
            timer.backward_started()
        loss.backward()
        if timer is not None:
            timer.backward_finished()
        with stage("densify statistics"):
            for h in self.hooks:
                h.after_backward(it, ctx)
        with stage("optimizer"):
            self.optimizer.step()
            self.optimizer.zero_grad(set_to_none=True)
        with stage("hooks after (growing, pruning)"):
            for h in self.hooks:
                h.after_step(it)
        with torch.no_grad():
            mse = ((out.image.detach().clamp(0, 1) - gt) ** 2).mean()
            terms["psnr"] = float(-10 * torch.log10(mse.clamp_min(1e-10)))
        terms["loss"] = float(loss.detach())
        terms["gaussians"] = int(g.means.shape[0])
        return terms

    def train(self, until: Optional[int] = None, checkpoint_every: Optional[int] = None) -> dict:
        """Train to ``until`` (default: the configured iterations), checkpointing every
        ``train.checkpoint_every`` (paper scale) and at the end.

        SIGINT / SIGTERM (in the main thread) finish the step in flight, write a checkpoint and
        raise :class:`TrainingStopped`; a second signal interrupts at once (the last checkpoint
        stays). A non-finite loss raises :class:`NonFiniteError` and writes nothing.
        """
        cfg = self.cfg
        total = cfg.train.iterations if until is None else min(until, cfg.train.iterations)
        ck = cfg.train.at(cfg.train.checkpoint_every) if checkpoint_every is None else checkpoint_every
        self.out.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(self.out)
        write_text_atomic(self.out / "config.toml", to_toml(cfg))
        with _StopSignals() as stop:
            return self._train_loop(total, ck, stop)

    def _train_loop(self, total: int, ck: int, stop) -> dict:
        cfg = self.cfg
        tb = (TensorBoardLog(self.out / TENSORBOARD_DIR, self.iteration) if cfg.train.tensorboard
              else None)
        try:
            return self._train_steps(total, ck, stop, tb)
        finally:
            if tb is not None:
                tb.close()

    def _train_steps(self, total: int, ck: int, stop, tb: Optional[TensorBoardLog]) -> dict:
        cfg = self.cfg
        with tqdm(total=total, initial=self.iteration, desc="train", disable=not self.progress,
                  dynamic_ncols=True) as bar, self._open_log() as log:
            last = {}
            ema_loss = self._ema_loss            # carried over a resume: the log is one curve
            while self.iteration < total:
                it = self.iteration + 1
                t0, c0 = time.perf_counter(), time.process_time()
                with allocating(f"training {self.out} at iteration {it} "
                                f"({self.model.n_anchors} anchors)", device=str(self.device)):
                    terms = self.step(it)
                dt = time.perf_counter() - t0
                self.train_time += dt
                if self.stall_time is not None:
                    self.stall_time += max(0.0, dt - (time.process_time() - c0))
                if not math.isfinite(terms["loss"]):
                    raise NonFiniteError(
                        f"{self.out}: the loss is {terms['loss']} at iteration {it}; training "
                        f"stopped, the last checkpoint (iteration "
                        f"{self._last_saved if self._last_saved is not None else 'none'}) is kept")
                self.iteration = it
                ema_loss = (terms["loss"] if ema_loss is None
                            else 0.9 * ema_loss + 0.1 * terms["loss"])
                self._ema_loss = ema_loss
                last = terms
                if it % cfg.train.log_every == 0 or it == total:
                    post = {"loss": f"{ema_loss:.4f}", "psnr": f"{terms['psnr']:.2f}",
                            "anchors": self.model.n_anchors, "gs": terms["gaussians"],
                            "ph": self.phase}
                    if "bpp" in terms:
                        post["bits"] = f"{terms['bpp']:.2f}"
                    bar.set_postfix(post, refresh=False)
                    log.write(json.dumps({"it": it, "train_time": round(self.train_time, 3),
                                          **({"stall_time": round(self.stall_time, 3)}
                                             if self.stall_time is not None else {}),
                                          "loss_ema": round(ema_loss, 6), **terms,
                                          "anchors": self.model.n_anchors, "phase": self.phase,
                                          **{k: v for h in self.hooks
                                             for k, v in h.log_fields().items()}},
                                         default=float) + "\n")
                    log.flush()
                    if tb is not None:
                        tb.log(it, terms, self)
                bar.update(1)
                if stop.requested and it < total:
                    path = self.save_checkpoint()
                    log.flush()
                    raise TrainingStopped(it, path)
                if ck and it % ck == 0 and it < total:
                    self.save_checkpoint()
        self.save_checkpoint()
        return last

    def _open_log(self):
        """The run's training log (``train_log.jsonl``: one JSON line every ``log_every``
        iterations with the loss terms, PSNR, anchor and Gaussian counts, phase, the training
        time so far and, on the CPU, the stall time within it), opened for appending. Lines
        past the current iteration (written after the checkpoint a resumed run restarts from)
        are dropped first, so the log stays one curve."""
        path = self.out / TRAIN_LOG_NAME
        if path.is_file():
            keep = []
            for line in read_text_bounded(path, "a training log").splitlines():
                try:
                    if json.loads(line)["it"] <= self.iteration:
                        keep.append(line)
                except (ValueError, KeyError, TypeError):
                    break                   # a torn last line (killed mid-write): stop there
            write_text_atomic(path, "".join(x + "\n" for x in keep))
        return path.open("a")

    # ------------------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        return {
            "iteration": self.iteration,
            "train_time": self.train_time,
            "stall_time": self.stall_time, "stall_from": self.stall_from,
            "loss_ema": self._ema_loss,
            "thread_segments": self.thread_segments,
            "machine_segments": self.machine_segments,
            "code_segments": self.code_segments,
            "shapes": {k: tuple(v.shape) for k, v in self.model.per_anchor.items()},
            "model": self.model.state_dict(),
            "entropy": self.entropy.state_dict(),
            "optimizer": self.optimizer.state_dict(),
            "hooks": {type(h).__name__: st for h in self.hooks
                      if (st := h.state_dict()) is not None},
            "phase": self.phase,
            "render_scale": self.render_scale,
            "voxel_size": self.voxel_size,
            "view_order": list(self._view_order),
            "rng": {"torch": torch.get_rng_state(), "gen": self.generator.get_state(),
                    "numpy": np.random.get_state(), "python": random.getstate(),
                    **({"step_gen": self.step_generator.get_state(), "device": str(self.device)}
                       if self.step_generator is not self.generator else {})},
        }

    def save_checkpoint(self, path: Optional[Path] = None) -> Path:
        """Write the training state atomically; refused (:class:`NonFiniteError`, the previous
        file untouched) when any tensor of the model, entropy model or optimizer state holds
        NaN or Inf."""
        path = Path(path) if path else self.out / CHECKPOINT_NAME
        state = self.state_dict()
        try:
            check_finite(state["model"], path, "model")
            check_finite(state["entropy"], path, "entropy model")
            check_optimizer_finite(state["optimizer"], path)
        except ValueError as e:
            raise NonFiniteError(f"not writing {path}: {e.args[0]}") from None
        with atomic_path(path) as tmp:
            torch.save(state, tmp)
        self._last_saved = self.iteration
        return path

    def load_checkpoint(self, path: str | Path) -> None:
        path = Path(path)
        f, _, _ = open_checked(path, "a checkpoint")   # a regular file under PGS_MAX_FILE_MB
        try:
            with f:
                s = torch.load(f, map_location="cpu", weights_only=False)
        except Exception as e:
            raise ValueError(f"cannot read checkpoint {path}: {e}") from None
        for k, shape in s["shapes"].items():
            if k not in self.model.per_anchor:
                raise ValueError(f"checkpoint {path} has per-anchor tensor '{k}' this model lacks")
            self.model.per_anchor[k] = torch.nn.Parameter(
                torch.zeros(shape, device=self.device),
                requires_grad=self.model.per_anchor[k].requires_grad)
        if "per_anchor.birth" not in s["model"] and "per_anchor.xyz" in s["model"]:
            # written before anchors' births were kept: unknown (-1)
            n = s["model"]["per_anchor.xyz"].shape[0]
            s["model"]["per_anchor.birth"] = torch.full((n,), -1.0)
            self.model.per_anchor["birth"] = torch.nn.Parameter(
                torch.zeros(n, device=self.device), requires_grad=False)
        check_finite(s["model"], path)
        check_finite(s["entropy"], path, "entropy model")
        check_optimizer_finite(s["optimizer"], path)
        self.model.load_state_dict(s["model"])
        from baseline.data.scene import scene_bounds
        from baseline.scaffold.model import check_bounds

        check_bounds(self.model, f"checkpoint {path}", *scene_bounds(self.scene))
        self.entropy.load_state_dict(s["entropy"])
        self.optimizer = self._make_optimizer()
        self.optimizer.load_state_dict(s["optimizer"])
        for g in self.optimizer.param_groups:  # a checkpoint's saved group options win: keep ours
            g["fused"], g["foreach"] = self._fused, None
        for h in self.hooks:
            st = s["hooks"].get(type(h).__name__)
            if st is not None:
                h.load_state_dict(st)
        self.iteration = s["iteration"]
        self._last_saved = self.iteration
        self._ema_loss = s.get("loss_ema")     # checkpoints written before it was kept: None
        # checkpoints written before thread counts / machines were kept: unrecorded (None) up
        # to here
        self.thread_segments = _extend_segments(s.get("thread_segments"), s["iteration"],
                                                self.threads)
        self.machine_segments = _extend_segments(s.get("machine_segments"), s["iteration"],
                                                 self.machine)
        self.code_segments = _extend_segments(s.get("code_segments"), s["iteration"], self.code)
        self.train_time = s["train_time"]
        if self.device.type != "cpu":
            self.stall_time = None
        elif s.get("stall_time") is None:       # not kept (older checkpoint, or a GPU's)
            self.stall_time, self.stall_from = 0.0, int(s["iteration"])
        else:
            self.stall_time, self.stall_from = float(s["stall_time"]), int(s.get("stall_from", 0))
        self.phase = s["phase"]
        self.render_scale = s["render_scale"]
        self.voxel_size = s["voxel_size"]
        self.model.voxel_size = float(self.voxel_size)
        self._view_order = list(s["view_order"])
        for h in self.hooks:
            h.restore(self.iteration)
        torch.set_rng_state(s["rng"]["torch"])
        self.generator.set_state(s["rng"]["gen"])
        if self.step_generator is not self.generator and "step_gen" in s["rng"] \
                and s["rng"].get("device", "").split(":")[0] == self.device.type:
            self.step_generator.set_state(s["rng"]["step_gen"])
        # (a checkpoint moved between devices keeps every tensor; only the per-step noise
        # stream, which belongs to the device it was drawn on, starts afresh)
        np.random.set_state(s["rng"]["numpy"])
        random.setstate(s["rng"]["python"])


def check_finite(state: dict, path, what: str = "model") -> None:
    """Refuse a checkpoint with NaN/Inf values, naming the tensor."""
    for k, v in state.items():
        if torch.is_tensor(v) and v.is_floating_point() and not torch.isfinite(v).all():
            raise ValueError(f"checkpoint {path}: {what} tensor '{k}' contains NaN or Inf values")


def check_optimizer_finite(opt_state: dict, path) -> None:
    """Refuse an optimizer state (Adam moments, steps) with NaN/Inf values, naming the group."""
    names = {}
    for g in opt_state.get("param_groups", []):
        for pid in g.get("params", []):
            names[pid] = g.get("name", "?")
    for pid, st in opt_state.get("state", {}).items():
        for k, v in st.items():
            if torch.is_tensor(v) and v.is_floating_point() and not torch.isfinite(v).all():
                raise ValueError(f"checkpoint {path}: optimizer state '{k}' of parameter group "
                                 f"'{names.get(pid, pid)}' contains NaN or Inf values")


def remove_stale_temps(folder: Path) -> list:
    """Remove temporary files a killed writer left in ``folder`` (``.<stem>.<hex>.tmp<ext>``,
    :func:`baseline.fileio.atomic_path`); returns their names."""
    import re

    gone = []
    for p in Path(folder).glob(".*.tmp*"):
        if re.fullmatch(r"\..+\.[0-9a-f]{8}\.tmp(\.[^.]+)?", p.name) and p.is_file():
            try:
                p.unlink()
                gone.append(p.name)
            except OSError:
                pass
    return gone


class _StopSignals:
    """SIGINT / SIGTERM set :attr:`requested` (the loop then checkpoints and stops); a second
    one interrupts at once. Handlers are only installed in the main thread and restored on
    exit."""

    SIGNALS = ("SIGINT", "SIGTERM")

    def __init__(self):
        self.requested = False
        self._old = {}

    def _handler(self, signum, frame):
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        import sys

        print(f"\n{signal.Signals(signum).name}: stopping after this iteration (a checkpoint is "
              f"written; send it again to stop at once)", file=sys.stderr, flush=True)

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for name in self.SIGNALS:
                sig = getattr(signal, name, None)
                if sig is not None:
                    self._old[sig] = signal.signal(sig, self._handler)
        return self

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            signal.signal(sig, old)
        return False
