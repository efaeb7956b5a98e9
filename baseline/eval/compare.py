"""``pgs compare``: train, encode, decode and measure several methods on one scene, side by side.

A *method* is a set of patches on top of the common ones (``--patch``): the baseline is the
plain configuration (Scaffold-GS + HAC unless a common patch says otherwise); each ``--vs
P1+P2`` adds one contender. Every (method, lambda) pair is one *run*, in its own folder
``DIR/runs/<method>-l<lambda>-<config hash>``; the hash covers the whole merged config, so a
changed setting never reuses a stale run.

A run goes through three stages, each recorded as soon as it is done, so an interrupted
comparison picks up where it stopped:

1. **train** -- ``baseline.run.train_run(resume=True)``: a run interrupted mid-training continues
   from its checkpoint; done when ``results.json`` holds the test metrics at the configured
   iteration count.
2. **encode** -- ``encode_model`` to ``model.pgs`` (written atomically); done when
   ``compare.json`` records the encode and the file on disk has the recorded byte count.
3. **decoded** -- ``decode_model`` the file alone and evaluate the *decoded* model on the test
   views (PSNR / SSIM / LPIPS on uint8 images, FPS); models whose feature provider keeps a
   decoded-model cache (``build_cache`` / ``clear_cache``, Predict-GS's SFP) are timed with and
   without it. Done when ``compare.json`` holds these (with LPIPS if weights are given now);
   the views are in ``RUN/decoded/`` (``renders/``, ``gt/``, ``per_view.json``: 3DGS's layout).

A run folder reduced to its records (``config.toml``, ``scene.json``, ``results.json``,
``compare.json``: no checkpoint, no model file) counts as finished and is reported from them, so
finished runs can be archived and a comparison completed later, on another machine, by copying
them into its ``--out`` folder; only the missing runs are trained.

``--codec PATCH`` (a patch that sets only ``[codec]`` keys, e.g. ``compact-codec``) applies
codec settings at the encode stage of every run without touching training: a run recorded with
other codec settings is encoded, decoded and measured again; its training is reused.

Every number in the report is measured in one of these stages or read from their records.
"""
from __future__ import annotations

import dataclasses
import json
import re
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional

from tqdm import tqdm

from baseline.config import Config, build_config, config_hash
from baseline.contracts import feature_cache
from baseline.modelfile import MODEL_FILE

# evaluate()'s breakdown of the Gaussians per view (baseline/eval/evaluate.py alive_breakdown)
ALIVE_KEYS = ("visible_anchors_mean", "mask_on_fraction", "opacity_kept_fraction")

BASELINE = "baseline"
RECORD = "compare.json"
RESULTS_FORMAT = "pgs-compare/1"
# the decoded file's views of a run: renders/, gt/ and per_view.json (3DGS's layout)
DECODED_VIEWS = "decoded"
MB = 2 ** 20


@dataclass(frozen=True)
class Method:
    name: str                   # "baseline" or the contender's patches joined by "+"
    patches: tuple[str, ...]    # on top of the common patches
    lambdas: Optional[tuple[float, ...]] = None     # its own rate points (``--lambda-for``)


@dataclass
class RunSpec:
    method: Method
    lmbda: float
    cfg: Config
    hash: str
    dir: Path
    seed: Optional[int] = None      # train.seed when the comparison was asked for seeds

    @property
    def label(self) -> str:
        """What progress lines and lists call the run: the method's user-facing name (HAC,
        Predict-GS, ...; :func:`baseline.eval.report.method_label`), lambda and seed."""
        from baseline.eval.report import method_label

        common = [p for p in self.cfg.patches if p not in self.method.patches]
        return f"{method_label(self.method.name, common)} lambda={self.lmbda:g}" + (
            f" seed={self.seed}" if self.seed is not None else "")


def _method_of(flag: str, value: str) -> Method:
    """``"predict-gs+masks-x4"`` -> Method named by its patches (a ``.toml`` path by its stem)."""
    parts = tuple(p.strip() for p in value.split("+") if p.strip())
    if not parts:
        raise ValueError(f"{flag} '{value}': expected one or more patch names joined by '+'")
    return Method("+".join(Path(p).stem if p.endswith(".toml") else p for p in parts), parts)


def parse_methods(vs: list[str]) -> list[Method]:
    """``["predict-gs", "predict-gs+entropy-factorized"]`` -> baseline + one Method each."""
    methods = [Method(BASELINE, ())]
    seen = {BASELINE}
    for v in vs:
        m = _method_of("--vs", v)
        name, parts = m.name, m.patches
        if name in seen:
            raise ValueError(f"--vs '{v}': method '{name}' is listed twice")
        seen.add(name)
        methods.append(Method(name, parts))
    return methods


def resolve_method(flag: str, name: str, methods: list[Method], common_patches=(),
                   extra: tuple[str, ...] = ()) -> str:
    """A method named on the command line -> its ``Method.name``: ``baseline``, a ``--vs``
    value, or its name in the report (``HAC``, ``Predict-GS``; :func:`method_label`)."""
    from baseline.eval.report import method_label

    by_label = {method_label(m.name, common_patches): m.name for m in methods}
    got = by_label.get(name, name)
    names = [m.name for m in methods] + list(extra)
    if got not in names:
        raise ValueError(f"{flag} {name}: not a method of this comparison "
                         f"(methods: {', '.join(names)})")
    return got


def with_own_lambdas(methods: list[Method], lambda_for: Optional[list[list]],
                     common_patches=()) -> list[Method]:
    """Apply ``--lambda-for METHOD L [L ...]`` (a list of ``[METHOD, L, ...]``): that method's
    rate points replace ``--lambda`` for it. Methods reach different rates at the same lambda,
    so the points where two curves meet (what BD-rate integrates over) may need a lambda only
    one of them is trained at; training the other there too would cost runs that measure
    nothing."""
    own: dict[str, tuple[float, ...]] = {}
    for item in lambda_for or []:
        if len(item) < 2:
            raise ValueError(f"--lambda-for {' '.join(map(str, item))}: expected a method and "
                             f"one or more lambdas")
        name = resolve_method("--lambda-for", str(item[0]), methods, common_patches)
        try:
            lams = tuple(float(x) for x in item[1:])
        except ValueError:
            raise ValueError(f"--lambda-for {' '.join(map(str, item))}: lambdas must be "
                             f"numbers") from None
        if name in own:
            raise ValueError(f"--lambda-for names method '{item[0]}' twice")
        if len(set(lams)) != len(lams):     # the range is the config's (plan_runs checks it)
            raise ValueError(f"--lambda-for {item[0]} lists a value twice: {list(lams)}")
        own[name] = lams
    return [dataclasses.replace(m, lambdas=own[m.name]) if m.name in own else m
            for m in methods]


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", name)


def plan_runs(out: str | Path, methods: list[Method], lambdas: Optional[list[float]],
              common_patches: list[str] = (), sets: list[str] = (),
              seeds: Optional[list[int]] = None) -> list[RunSpec]:
    """Build every run's config up front (bad patches / keys fail before any training).

    With ``lambdas`` None each method runs once at its config's own ``entropy.lmbda``; a method
    with rate points of its own (``Method.lambdas``) runs at those instead.
    ``seeds``: each rate point is trained once per ``train.seed`` (folders
    ``<method>-l<lambda>-s<seed>-<hash>``), in the order method, seed, lambda, so that one seed's
    whole curve finishes before the next seed starts.
    """
    out = Path(out)
    if seeds is not None:
        seeds = [int(x) for x in seeds]
        if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
            raise ValueError(f"--seeds must list distinct non-negative integers, got {seeds}")
    specs = []
    for m in methods:
        patches = list(common_patches) + list(m.patches)
        for seed in (seeds if seeds is not None else [None]):
            extra = [] if seed is None else [f"train.seed={seed}"]
            lams = m.lambdas or lambdas
            if lams:
                cfgs = [(float(lm), build_config(patches, list(sets) + extra
                                                 + [f"entropy.lmbda={float(lm)!r}"]))
                        for lm in lams]
            else:
                cfg = build_config(patches, list(sets) + extra)
                cfgs = [(float(cfg.entropy.lmbda), cfg)]
            for lm, cfg in cfgs:
                h = config_hash(cfg)
                tag = "" if seed is None else f"-s{seed}"
                d = out / "runs" / f"{_safe(m.name)}-l{lm:g}{tag}-{h}"
                specs.append(RunSpec(m, lm, cfg, h, d, seed))
    return specs


# ------------------------------------------------------------------ the uncompressed reference
REFERENCE = "reference"
REFERENCE_PREFIX = "reference-"


def parse_reference(ref: Optional[str]) -> Optional[Method]:
    """``"scaffold"`` -> the uncompressed reference method (patches on top of the common ones)."""
    return None if ref is None else _method_of("--reference", ref)


def plan_reference(out: str | Path, method: Method, common_patches: list[str] = (),
                   sets: list[str] = ()) -> RunSpec:
    """The reference run: the common patches and ``--set`` values plus the reference's patches,
    so it shares the comparison's scene, resolution, split and schedule. It must train without
    quantization or a rate loss (no ``hac_phases`` hook), or it is no uncompressed reference."""
    cfg = build_config(list(common_patches) + list(method.patches), list(sets))
    if "hac_phases" in cfg.train.hooks:
        raise ValueError(f"--reference {method.name}: its training runs the 'hac_phases' hook "
                         f"(quantization and the rate loss), so it is not an uncompressed "
                         f"reference; use e.g. --reference scaffold")
    h = config_hash(cfg)
    return RunSpec(method, float(cfg.entropy.lmbda), cfg, h,
                   Path(out) / "runs" / f"{REFERENCE_PREFIX}{_safe(method.name)}-{h}")


# per-anchor tensors the renderer never reads: the Gaussian masks (an uncompressed run never
# trains them) and the anchors' births (bookkeeping for the census)
NOT_RENDERED = ("per_anchor.mask", "per_anchor.birth")


def float32_bytes(model_state: dict) -> int:
    """Bytes of every floating tensor the renderer reads, at 4 bytes a value: per-anchor
    positions, features (or whatever the feature provider keeps), offsets, scalings, and the
    networks. The Gaussian masks (``per_anchor.mask``) are not counted: an uncompressed run never
    trains them (all on) and Scaffold-GS has none; nor are the anchors' births. This is the size of the model as float32
    arrays, the yardstick "x times smaller" is measured against."""
    return int(sum(4 * v.numel() for k, v in model_state.items()
                   if v.is_floating_point() and k not in NOT_RENDERED))


def _stage_reference(spec: RunSpec, record: dict) -> None:
    import torch

    from baseline.fileio import open_checked
    from baseline.run import CHECKPOINT_NAME

    ckpt = spec.dir / CHECKPOINT_NAME
    try:
        f, _, _ = open_checked(ckpt, "a checkpoint")
        with f:
            state = torch.load(f, map_location="cpu", weights_only=False)["model"]
    except Exception as e:
        raise ValueError(f"cannot read the reference's checkpoint {ckpt}: {e}") from None
    n = state["per_anchor.xyz"].shape[0]
    record["reference"] = {"float32_bytes": float32_bytes(state), "anchors": int(n)}
    _write_record(spec, record)


def reference_finished(spec: RunSpec) -> bool:
    record = _read_json(spec.dir / RECORD)
    return (_trained(spec) is not None and record.get("config_hash") == spec.hash
            and "reference" in record)


def _train_stage(spec: RunSpec, scene_path: str, progress: bool,
                 stage: Callable[[str], None]) -> tuple[dict, list[str]]:
    """Stage 1 of a run (a compared method's or the reference's): train it unless its
    results.json holds the test metrics at the configured iterations (an interrupted training
    resumes from its checkpoint). Returns its results and ``["train"]`` if it trained now."""
    from baseline.run import train_run

    _check_scene(spec, scene_path)
    res = _trained(spec)
    if res is not None:
        return res, []
    stage("train")
    return train_run(scene_path, spec.dir, spec.cfg, resume=True, progress=progress,
                     evaluate_after=True), ["train"]


def run_reference(spec: RunSpec, scene_path: str, progress: bool = True,
                  on_stage: Optional[Callable[[str], None]] = None) -> dict:
    """Train the reference (if not yet), measure its float32 size; return its row. Its quality
    is the trained model's on the test views (nothing is coded)."""
    from baseline.guard import RunLock

    stage = on_stage or (lambda s: None)
    if records_only(spec):
        return _reference_stages(spec, scene_path, progress, stage)
    with RunLock(spec.dir):             # one process brings a run to the end at a time
        return _reference_stages(spec, scene_path, progress, stage)


def _reference_stages(spec, scene_path, progress, stage) -> dict:
    res, done = _train_stage(spec, scene_path, progress, stage)
    record = _read_json(spec.dir / RECORD)
    if record.get("config_hash") != spec.hash or done or "reference" not in record:
        record = {"method": spec.method.name, "method_patches": list(spec.method.patches),
                  "config_hash": spec.hash, "scene": scene_path}
        stage("float32 size")
        _stage_reference(spec, record)
        done.append("float32 size")
    ref, test = record["reference"], res["test"]
    return {"method": spec.method.name, "method_patches": list(spec.method.patches),
            "patches": list(spec.cfg.patches), "run_dir": str(spec.dir),
            "config_hash": spec.hash, "psnr": test["psnr"], "ssim": test["ssim"],
            **ssim_fields(test),
            "lpips": test.get("lpips"), "float32_bytes": ref["float32_bytes"],
            "mb": ref["float32_bytes"] / MB, "anchors": ref["anchors"],
            "gaussians_mean": test.get("gaussians_mean"), "fps": test.get("fps"),
            "iterations": res["iterations"], "train_time_s": res["train_time_s"],
            "s_per_it": res["s_per_it"], "threads": res["threads"],
            **_training_history(res),
            "device": res.get("device", "cpu"), "protocol": res.get("protocol", {}),
            "records_only": records_only(spec), "stages_run": done}


# ----------------------------------------------------------------------------------- stages
def _read_json(path: Path) -> dict:
    if not path.exists():
        return {}
    from baseline.fileio import read_text_bounded

    try:
        return json.loads(read_text_bounded(path, "a run's record"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON ({e}); delete it to redo that stage") from None


def _trained(spec: RunSpec) -> Optional[dict]:
    res = _read_json(spec.dir / "results.json")
    if "test" in res and res.get("iterations") == spec.cfg.train.iterations:
        return res
    return None


def _training_history(res: dict) -> dict:
    """The machine a run trained on, a resumed run's thread counts and machines by stretch of
    iterations when it had several, and its stall time (of the training time, the seconds it
    ran on no core), each where it was kept."""
    return {k: res[k] for k in ("machine", "threads_by_iteration", "machines_by_iteration",
                                "stall_s", "stall_from") if res.get(k) is not None}


def records_only(spec: RunSpec) -> bool:
    """The run folder keeps its records but neither its checkpoint nor its model file.

    That is how finished runs are archived (e.g. committed beside a report): their measurements
    are reported from ``results.json`` and ``compare.json`` as they were taken; nothing can be
    re-encoded or remeasured from them.
    """
    from baseline.run import CHECKPOINT_NAME

    return not (spec.dir / MODEL_FILE).exists() and not (spec.dir / CHECKPOINT_NAME).exists()


def codec_overrides(patch: Optional[str]) -> dict:
    """The ``[codec]`` settings patch ``patch`` changes (``{}`` for None); a patch that also
    changes anything else is refused (``--codec`` must not change what is trained)."""
    from baseline.config import to_dict

    if not patch:
        return {}
    base, cfg = to_dict(build_config([]), drop_meta=True), to_dict(build_config([patch]), drop_meta=True)
    other = sorted(f"{sec}.{k}" for sec, vals in cfg.items() if sec != "codec" and isinstance(vals, dict)
                   for k, v in vals.items() if base.get(sec, {}).get(k) != v)
    if other:
        raise ValueError(f"--codec {patch}: a codec patch may set only [codec] keys; it also sets "
                         f"{', '.join(other)} (give those with --patch or --vs)")
    return {k: v for k, v in cfg["codec"].items() if base["codec"].get(k) != v}


def run_codec(spec: RunSpec, overrides: Optional[dict] = None) -> dict:
    """The codec settings a run's file is (to be) written with: its config's, then overrides."""
    return {**dataclasses.asdict(spec.cfg.codec), **(overrides or {})}


def _encoded(spec: RunSpec, record: dict, codec: Optional[dict] = None) -> bool:
    enc = record.get("encode")
    if not enc or record.get("config_hash") != spec.hash:
        return False
    # records from before codec settings were recorded were written with the run's own config's
    if enc.get("codec", run_codec(spec)) != run_codec(spec, codec):
        return False
    pgs = spec.dir / MODEL_FILE
    if pgs.exists():
        return pgs.stat().st_size == enc.get("bytes")
    return records_only(spec) and _trained(spec) is not None


def lpips_id(weights: Optional[str]) -> Optional[str]:
    """Which LPIPS weights a measurement used: resolved path and byte count (None: no LPIPS)."""
    if weights is None:
        return None
    from baseline.eval.metrics import lpips_paths

    ps = [p.resolve() for p in lpips_paths(weights)]
    if not ps or not all(p.is_file() for p in ps):
        return None
    return ", ".join(f"{p} ({p.stat().st_size} bytes)" for p in ps)


def _evaluated(record: dict, lpips: Optional[str]) -> bool:
    """Decoded measurements done for this file (and with these LPIPS weights, if any now)."""
    dec = record.get("decoded")
    if not dec or record.get("encode", {}).get("bytes") != dec.get("bytes"):
        return False
    return lpips is None or (dec.get("lpips") is not None and dec.get("lpips_weights") == lpips)


def is_finished(spec: RunSpec, lpips: Optional[str] = None, codec: Optional[dict] = None) -> bool:
    record = _read_json(spec.dir / RECORD)
    return (_trained(spec) is not None and _encoded(spec, record, codec)
            and _evaluated(record, lpips))


def _check_scene(spec: RunSpec, scene_path: str) -> None:
    sj = _read_json(spec.dir / "scene.json")
    if sj and sj.get("path") != scene_path:
        raise ValueError(f"{spec.dir} was trained on {sj.get('path')}, not {scene_path}; "
                         f"use another --out folder for another scene")


def _write_record(spec: RunSpec, record: dict) -> None:
    from baseline.run import write_json_atomic

    write_json_atomic(spec.dir / RECORD, record)


def _stage_encode(spec: RunSpec, scene_path: str, record: dict,
                  codec: Optional[dict] = None) -> None:
    from baseline.modelfile import encode_model, file_info
    from baseline.config import CodecConfig
    from baseline.run import file_header, load_run

    trainer, scene = load_run(spec.dir, device="cpu")     # the codec runs on the CPU
    if trainer.phase != "adaptive":
        tqdm.write(f"note: {spec.label} stopped before the entropy model was trained "
                   f"(phase '{trainer.phase}'); its file is coded with an untrained context model")
    settings = run_codec(spec, codec)
    cfg = dataclasses.replace(trainer.cfg, codec=CodecConfig(**settings))
    from baseline.data.scene import scene_bounds

    st = encode_model(cfg, trainer.model, trainer.entropy, spec.dir / MODEL_FILE,
                      extra_header=file_header(scene, scene_path), scene_bounds=scene_bounds(scene))
    info = file_info(spec.dir / MODEL_FILE)
    record["encode"] = {"bytes": st["bytes"], "encode_s": st["encode_s"], "anchors": st["anchors"],
                        "phase": trainer.phase, "sections": info["sections"],
                        "groups": info["groups"], "codec": settings}
    _add_file_counts(record["encode"], info)
    record.pop("decoded", None)          # a new file: its decoded measurements are redone
    _write_record(spec, record)


def _add_file_counts(enc: dict, info: dict) -> None:
    """Counts read from the file (not measurements): masks on and, per coded attribute, the
    values coded and bits per value (:func:`baseline.modelfile.coded_elements`)."""
    enc["attributes"] = info.get("attributes", [])
    enc["masks_on"] = info.get("masks_on")


def _fill_file_counts(spec: RunSpec, record: dict) -> bool:
    """Records written before the counts existed get them from the model file, when it is still
    there and is the one recorded (same size). Returns whether the record changed."""
    from baseline.modelfile import file_info

    enc = record.get("encode") or {}
    pgs = spec.dir / MODEL_FILE
    if "attributes" in enc or not pgs.exists() or pgs.stat().st_size != enc.get("bytes"):
        return False
    _add_file_counts(enc, file_info(pgs))
    return True


def _stage_decoded(spec: RunSpec, scene_path: str, record: dict, lpips_fn,
                   lpips: Optional[str]) -> None:
    from baseline.modelfile import decode_model
    from baseline.device import device_name, resolve_device
    from baseline.eval.evaluate import evaluate
    from baseline.render import resolve_backend
    from baseline.run import load_scene_for

    pgs = spec.dir / MODEL_FILE
    dec = decode_model(pgs)                          # on the CPU, then rendered on the run's device
    dev = resolve_device(spec.cfg.train.device)
    dec.model.to(dev)
    dec.model.bake_if_faster()
    scene = load_scene_for(dec.cfg, scene_path)
    cams = scene.test_cameras or scene.train_cameras
    backend = dec.cfg.train.rasterizer
    ev = evaluate(dec.model, scene, cams, phase="decoded", backend=backend,
                  render_dir=spec.dir / DECODED_VIEWS, lpips_fn=lpips_fn,
                  iterations=dec.cfg.train.iterations)
    out = {"bytes": pgs.stat().st_size, "decode_s": dec.decode_s, "psnr": ev["psnr"],
           "ssim": ev["ssim"], "ssim_skimage": ev["ssim_skimage"],
           "ssim_convention": ev["ssim_convention"],
           "lpips": ev["lpips"], "fps": ev["fps"], "n_views": ev["n_views"],
           "lpips_weights": lpips if lpips_fn is not None else None,
           "gaussians_mean": ev["gaussians_mean"], "anchors": ev["anchors"],
           **{k: ev[k] for k in ALIVE_KEYS},
           "split": "test" if scene.test_cameras else "train (no test views)",
           "backend": resolve_backend(backend, dec.model.xyz), "device": device_name(dev),
           "has_cache": False, "fps_nocache": None, "psnr_nocache": None}
    prov = feature_cache(dec.model)
    if prov is not None:
        prov.clear_cache()
        dec.model.unbake()                  # (a bake holds f_c's first-layer terms)
        ev2 = evaluate(dec.model, scene, cams, phase="decoded", backend=backend)
        prov.build_cache(dec.model.xyz)
        dec.model.bake_if_faster()
        out.update(has_cache=True, fps_nocache=ev2["fps"], psnr_nocache=ev2["psnr"])
    record["decoded"] = out
    _write_record(spec, record)


def _stage_census(spec: RunSpec, record: dict) -> None:
    """Where the run's Gaussians come from (:mod:`baseline.eval.census`), from its checkpoint's
    coded state (what the file holds, with the anchors' births); the per-view list is dropped."""
    from baseline.eval.census import census_of

    c = census_of(str(spec.dir))
    c.pop("view_kept_share", None)
    c.pop("target", None)
    record["census"] = c
    _write_record(spec, record)


def run_one(spec: RunSpec, scene_path: str, lpips_fn=None, lpips: Optional[str] = None,
            progress: bool = True, on_stage: Optional[Callable[[str], None]] = None,
            remeasure: bool = False, codec: Optional[dict] = None) -> dict:
    """Bring one run to the finished state (skipping stages already done); return its row.

    ``remeasure``: redo the encode and decode+eval stages of a trained run even when they are
    recorded (the same bytes are written again; times and FPS are retaken, e.g. on a quiet
    machine after runs were trained side by side). ``codec``: codec settings applied at the
    encode stage (:func:`codec_overrides`); a file written with other settings is redone."""
    from baseline.guard import RunLock

    stage = on_stage or (lambda s: None)
    if records_only(spec):
        return _run_stages(spec, scene_path, lpips_fn, lpips, progress, stage, remeasure, codec)
    with RunLock(spec.dir):             # one process brings a run to the end at a time
        return _run_stages(spec, scene_path, lpips_fn, lpips, progress, stage, remeasure, codec)


def _run_stages(spec, scene_path, lpips_fn, lpips, progress, stage, remeasure, codec) -> dict:
    from baseline.train.trainer import set_threads

    res, done = _train_stage(spec, scene_path, progress, stage)
    record = _read_json(spec.dir / RECORD)
    if record.get("config_hash") != spec.hash or done:
        record = {}                      # (re)trained now: an older file no longer applies
    elif remeasure and records_only(spec):
        tqdm.write(f"note: {spec.label} keeps only its records (no checkpoint, no model file): "
                   f"reported as recorded, not remeasured")
    elif remeasure:
        record.pop("encode", None)
        record.pop("decoded", None)
    record.update(method=spec.method.name, method_patches=list(spec.method.patches),
                  lmbda=spec.lmbda, config_hash=spec.hash, scene=scene_path)
    set_threads(spec.cfg.train.threads)
    if not _encoded(spec, record, codec):
        if records_only(spec) and record.get("encode"):
            raise ValueError(f"{spec.label} is kept only as records (no checkpoint), written "
                             f"with codec settings {record['encode'].get('codec', run_codec(spec))}; "
                             f"it cannot be encoded again with {run_codec(spec, codec)}")
        stage("encode")
        _stage_encode(spec, scene_path, record, codec)
        done.append("encode")
    elif _fill_file_counts(spec, record):
        _write_record(spec, record)
    if not _evaluated(record, lpips if lpips_fn is not None else None):
        stage("decode+eval")
        _stage_decoded(spec, scene_path, record, lpips_fn, lpips)
        done.append("decode+eval")
    from baseline.run import CHECKPOINT_NAME

    if "census" not in record and not records_only(spec) \
            and record.get("encode", {}).get("phase") == "adaptive" \
            and (spec.dir / CHECKPOINT_NAME).exists():      # a run that reached HAC's coding
        stage("census")
        _stage_census(spec, record)
        done.append("census")
    if "train_curve" not in record and not records_only(spec):
        from baseline.eval.report.curves import train_curve

        curve = train_curve(spec.dir, res.get("iterations"))
        if curve is not None:           # derived from the training log; nothing is measured
            record["train_curve"] = curve
            _write_record(spec, record)
    row = make_row(spec, res, record)
    row["stages_run"] = done
    return row


def mark_untimed(specs: list[RunSpec], name: str, why: str, lpips: Optional[str] = None,
                 codec: Optional[dict] = None) -> None:
    """Mark finished run ``name`` (its folder's name) as untimed in its record: its training
    time holds something its record cannot show (e.g. a pause of the process in a run trained
    before the stall time was kept), said in ``why``; an empty ``why`` removes the mark. The
    report leaves such a run out of training-time ratios and names why (``report.untimed``);
    the mark travels with the archived record and is dropped when the run is trained again."""
    from baseline.guard import RunLock

    spec = next((s for s in specs if s.dir.name == name), None)
    if spec is None:
        raise ValueError(f"--untimed: {name!r} is no run of this comparison (a folder name "
                         f"under its runs/, e.g. {specs[0].dir.name if specs else '-'})")
    if not is_finished(spec, lpips, codec):      # (checked before the lock makes its folder)
        raise ValueError(f"--untimed: {name} has not finished: only a finished run's "
                         f"training time can be marked")
    with RunLock(spec.dir):
        record = _read_json(spec.dir / RECORD)
        if why.strip():
            record["untimed"] = why.strip()
        else:
            record.pop("untimed", None)
        _write_record(spec, record)


def ssim_fields(measured: dict) -> dict:
    """``ssim_convention`` and ``ssim_skimage`` of a measurement (a record's decoded stage, a
    run's test evaluation): records from before the convention was kept measured "ssim" with
    scikit-image, so that value is their ``ssim_skimage`` too."""
    conv = measured.get("ssim_convention", "skimage")
    return {"ssim_convention": conv,
            "ssim_skimage": measured.get("ssim_skimage",
                                         measured.get("ssim") if conv == "skimage" else None)}


def make_row(spec: RunSpec, res: dict, record: dict) -> dict:
    """One flat results row from a run's results.json and compare.json (no new measurement)."""
    enc, dec = record["encode"], record["decoded"]
    return {
        "method": spec.method.name,
        "method_patches": list(spec.method.patches),
        "patches": list(spec.cfg.patches),
        "lmbda": spec.lmbda,
        "seed": spec.seed,
        "train_seed": spec.cfg.train.seed,
        "run_dir": str(spec.dir),
        "config_hash": spec.hash,
        "psnr": dec["psnr"], "ssim": dec["ssim"], "lpips": dec["lpips"],
        # which SSIM "ssim" is (baseline.eval.metrics.SSIM_CONVENTIONS): records written before
        # the convention was kept hold scikit-image's
        **ssim_fields(dec),
        "lpips_weights": dec.get("lpips_weights"),
        "bytes": dec["bytes"], "mb": dec["bytes"] / MB,
        "sections": enc["sections"], "groups": enc["groups"],
        "codec": enc.get("codec", run_codec(spec)),
        # counts read from the file; absent from records written before they were kept
        "attributes": enc.get("attributes"), "masks_on": enc.get("masks_on"),
        "iterations": res["iterations"], "train_time_s": res["train_time_s"],
        "s_per_it": res["s_per_it"], "threads": res["threads"],
        **_training_history(res),
        "encode_s": enc["encode_s"], "decode_s": dec["decode_s"],
        "fps": dec["fps"], "fps_nocache": dec["fps_nocache"], "has_cache": dec["has_cache"],
        "psnr_nocache": dec["psnr_nocache"],
        "anchors": dec["anchors"], "anchors_trained": res["anchors"],
        "gaussians_mean": dec["gaussians_mean"], "n_views": dec["n_views"], "split": dec["split"],
        # where the Gaussians per view come from; absent from records written before they were kept
        **{k: dec.get(k) for k in ALIVE_KEYS},
        "backend": dec["backend"], "phase_at_encode": enc["phase"],
        # runs recorded before device support trained on the CPU (the only device then)
        "device": res.get("device", "cpu"),
        "pre_encode": {k: res["test"].get(k) for k in ("psnr", "ssim", "fps")},
        "protocol": res.get("protocol", {}),
        "train_versions": res.get("versions", {}),
        # records written before the version was kept were trained with version 1
        "training_semantics": res.get("training_semantics", 1),
        # versions of the components that declare one (absent: every component at version 1)
        "component_semantics": res.get("component_semantics", {}),
        "rate_values_per_anchor": spec.cfg.entropy.rate_values_per_anchor,
        "records_only": records_only(spec),
        # the Gaussian census (absent from records written before it was kept)
        "census": record.get("census"),
        # the training curve's summary (baseline.eval.report.curves; absent from older records)
        "train_curve": record.get("train_curve"),
        # why its training time is no measurement, where a user marked it (mark_untimed)
        "untimed": record.get("untimed"),
    }


RECORD_FILES = ("config.toml", "scene.json", "results.json", RECORD)


def is_compare_folder(folder: Path) -> bool:
    """A comparison's folder written before folders were marked (its ``runs/``)."""
    return (Path(folder) / "runs").is_dir()


def archive_records(out: str | Path, dest: str | Path,
                    results: Optional[dict] = None, overwrite: bool = False) -> list[Path]:
    """Copy the records of the finished runs of comparison ``out`` (and its report, results
    and plots) to ``dest``: a few KB per run, no checkpoints or model files. Copied into another
    comparison's ``--out`` folder they are reported as finished (see :func:`records_only`).
    ``results``: the dict :func:`run_compare` returned; when given, only the runs it reports
    (and its reference) are kept, not other comparisons' runs that share ``out``.
    ``dest`` is checked as ``--out`` is (:func:`baseline.guard.check_output`): new, empty, or
    an archive of the same scene's comparison (``overwrite``: another of the toolkit's).
    Returns the run folders archived."""
    import shutil

    from baseline.guard import check_output

    out, dest = Path(out), Path(dest)
    scene = (results or _read_json(out / "results.json")).get("scene")
    # an archive is a comparison's folder reduced to its records: the same rule as --out
    check_output(dest, command="compare", source=scene, folder=True, own=is_compare_folder,
                 overwrite=overwrite)
    keep = None
    if results is not None:
        rows = list(results["runs"]) + ([results["reference"]] if results.get("reference") else [])
        keep = {Path(r["run_dir"]).name for r in rows}
    done = []
    for run in sorted((out / "runs").glob("*")) if (out / "runs").is_dir() else []:
        if keep is not None and run.name not in keep:
            continue                       # another comparison's run sharing this folder
        rec = _read_json(run / RECORD)
        res = _read_json(run / "results.json")
        if not ("test" in res and (rec.get("encode") and rec.get("decoded")
                                   or "reference" in rec)):
            continue                       # not finished: nothing to keep yet
        (dest / "runs" / run.name).mkdir(parents=True, exist_ok=True)
        for name in RECORD_FILES:
            shutil.copy2(run / name, dest / "runs" / run.name / name)
        done.append(dest / "runs" / run.name)
    for f in out.iterdir() if out.is_dir() else []:
        if f.is_file() and f.suffix in (".md", ".json", ".png"):
            dest.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, dest / f.name)
    return done


# ------------------------------------------------------------------------------ the command
def _warm_up_rasterizer(specs: list[RunSpec]) -> None:
    """Compile / load the CPU rasterizer kernels before anything is timed.

    Otherwise the first run of the process pays it inside its training (and FPS) timings and
    the methods' times are not comparable.
    """
    if not any(s.cfg.train.rasterizer in ("cpu", "auto") for s in specs):
        return
    try:
        from baseline.render.cpu import kernels
    except ImportError:        # no numba: the reference backend is used, nothing to warm up
        return
    kernels()


def paired_fps_bench(results: dict, rounds: int = 3, threads: int = 1,
                     previous: dict | None = None) -> dict:
    """Each contender's decoded file timed against the baseline's in one process
    (:func:`baseline.eval.fpsbench.bench_files`: same views, rounds in rotated order), at the
    middle rate point both have (the lowest seed): ``{method: {ratio, fps, fps_ref, lmbda,
    rounds, threads, ratio_rounds, runs, bytes}}``; FPS taken by separate runs at separate times
    make no ratio. ``ratio`` is ``fps / fps_ref`` (each the median over rounds), the figures it
    is printed beside; ``ratio_rounds`` the range of the per-round ratios.

    ``previous``: the ``fps_pair`` of an earlier report of this comparison; a pair of the same
    two runs and files (folder names and byte counts) is reused as measured, so a report rebuilt
    from finished runs is the same report (``--remeasure`` passes None and times it again)."""
    from baseline.eval.fpsbench import bench_files
    from baseline.eval.report import method_names, runs_of

    base = results.get("baseline", BASELINE)
    out = {}
    for m in method_names(results):
        if m == base:
            continue
        lams = sorted({r["lmbda"] for r in runs_of(results, m)}
                      & {r["lmbda"] for r in runs_of(results, base)})
        if not lams:
            continue
        lm = lams[len(lams) // 2]
        pick = [min((r for r in runs_of(results, x) if r["lmbda"] == lm),
                    key=lambda r: -1 if r.get("seed") is None else r["seed"]) for x in (base, m)]
        ident = {"runs": [Path(r["run_dir"]).name for r in pick],
                 "bytes": [int(r["bytes"]) for r in pick]}
        old = (previous or {}).get(m)
        if old and all(old.get(k) == v for k, v in ident.items()) \
                and old.get("rounds") == rounds:
            out[m] = old                   # measured earlier on these very files
            continue
        files = [Path(r["run_dir"]) / MODEL_FILE for r in pick]
        if not all(f.exists() for f in files):
            continue                       # records only: no file to time
        res = bench_files([str(f) for f in files], rounds=rounds, threads=threads)
        plain = [r for r in res["rows"] if r["form"] == "plain"]
        ref, con = plain[0], plain[-1]
        out[m] = {"ratio": con["fps"] / ref["fps"], "fps": con["fps"], "fps_ref": ref["fps"],
                  "lmbda": lm, "rounds": rounds, "threads": res["threads"],
                  "ratio_rounds": [con["ratio_min"], con["ratio_max"]], **ident}
    return out


def _stages_text(stages: list[str]) -> str:
    """What a progress line says a run's stages were in this command: trained, measured, or
    reused as recorded."""
    if "train" in stages:
        rest = [x for x in stages if x != "train"]
        return "trained now" + (f", then {', '.join(rest)}" if rest else "")
    return "measured now: " + ", ".join(stages) if stages else "reused (finished earlier)"


def run_compare(scene: str | Path, out: str | Path, vs: list[str] = (),
                lambdas: Optional[list[float]] = None, common_patches: list[str] = (),
                sets: list[str] = (), lpips_weights: Optional[str] = None,
                progress: bool = True, plots: bool = True, echo: bool = True,
                only: Optional[list[str]] = None, remeasure: bool = False,
                report_only: bool = False, reference: Optional[str] = None,
                codec: Optional[str] = None, seeds: Optional[list[int]] = None,
                panel_views: Optional[list[int]] = None, paired_fps: bool = False,
                scope: Optional[str] = None, lambda_for: Optional[list[list]] = None,
                untimed: Optional[list[list[str]]] = None, overwrite: bool = False,
                done_before: dict | None = None) -> dict:
    """Run (or resume) a comparison; write ``out/results.json``, ``out/report.md`` and plots.

    ``only``: bring only the runs of these methods (``baseline``, a ``--vs`` value, or a name as
    the report shows it: ``HAC``, ``Predict-GS``) to the finished state, and report those; the others are left as they are.
    This splits a comparison across processes or machines sharing ``out`` (e.g. one process per
    core: ``taskset -c 0 pgs compare ... --only baseline`` beside ``taskset -c 1 ... --only
    predict-gs``); a final invocation without it reuses every finished run for the full report.
    ``remeasure``: see :func:`run_one`.
    ``report_only``: train and measure nothing; report the finished runs (archived records
    included) and list the others as missing (``results["missing"]``). For a long comparison
    that spans days or machines: its report so far, without starting the runs still to do.
    ``reference``: patches (joined by '+') of an uncompressed run on the same protocol, e.g.
    ``"scaffold"``: trained once (``--only reference`` trains just it), measured as the trained
    model on the test views plus its float32 size (:func:`float32_bytes`); the report then gives
    every run's size ratio and PSNR change against it.
    ``codec``: a patch of ``[codec]`` settings applied when encoding every run (training and run
    folders unchanged); e.g. ``"compact-codec"``.
    ``seeds``: train every rate point once per seed (``train.seed``); the report then gives each
    point's seed mean and spread, and BD-rate per seed and on the seed-mean curves.
    ``panel_views``: test views drawn in the report's panels (render, error map, bit map per
    method; default ``[0]``, ``[]`` for none).
    ``lambda_for``: ``[[METHOD, L, ...], ...]``, rate points of one method in place of
    ``lambdas`` (:func:`with_own_lambdas`).
    ``untimed``: ``[[RUN, WHY], ...]``, finished runs (folder names under ``out/runs``) whose
    training time is no measurement for a reason their record cannot show (:func:`mark_untimed`).
    ``overwrite``: ``out`` may hold another output of the toolkit (else it is new, empty, or
    this scene's comparison: :func:`baseline.guard.check_output`).
    ``done_before``: ``{run folder: [stages]}`` this command already ran elsewhere (``pgs demo``'s
    parallel workers), so that its messages say those runs were trained now, not reused.
    ``lpips_weights`` None: the weight files found on this machine, if any
    (:func:`baseline.eval.metrics.find_lpips_weights`).

    A report rebuilt from finished runs reuses their recorded measurements, the paired FPS
    included: the same command gives the same report (``remeasure`` retakes them).
    """
    from baseline.eval.metrics import load_lpips
    from baseline.eval.report import format_report, write_report
    from baseline.run import versions, write_json_atomic

    if report_only and remeasure:
        raise ValueError("--report-only measures nothing: it cannot be combined with --remeasure")
    scene_path = str(Path(scene).resolve())
    if not Path(scene_path).exists():
        raise FileNotFoundError(f"scene {scene} does not exist")
    out = Path(out)
    methods = parse_methods(list(vs))
    if lambdas is not None and len(set(lambdas)) != len(lambdas):
        raise ValueError(f"--lambda lists a value twice: {lambdas}")
    methods = with_own_lambdas(methods, lambda_for, common_patches)
    codec_over = codec_overrides(codec)
    specs = plan_runs(out, methods, lambdas, list(common_patches), list(sets), seeds)
    ref_method = parse_reference(reference)
    ref_spec = (plan_reference(out, ref_method, list(common_patches), list(sets))
                if ref_method is not None else None)
    if only:
        extra = (REFERENCE,) if ref_spec is not None else ()
        only = [resolve_method("--only", o, methods, common_patches, extra)   # "HAC" = "baseline"
                for o in only]
        specs = [s for s in specs if s.method.name in only]
        methods = [m for m in methods if m.name in only]
    if lpips_weights is None:
        from baseline.eval.metrics import find_lpips_weights

        lpips_weights = find_lpips_weights()
    lpips_fn, lpips_reason = load_lpips(lpips_weights)
    lp_id = lpips_id(lpips_weights) if lpips_fn is not None else None
    from baseline.device import resolve_device

    if not report_only:                 # a wrong scene path leaves no output folder behind
        from baseline.data.readers import detect_format
        from baseline.guard import check_output, write_marker

        detect_format(Path(scene_path))
        # not a run's folder, not inside the scene, not a folder of the user's files; a
        # comparison of this scene (to resume) or, with ``overwrite``, another of the toolkit's
        check_output(out, command="compare", source=scene_path, folder=True,
                     overwrite=overwrite, own=is_compare_folder)
        write_marker(out, "compare", scene_path)
    out.mkdir(parents=True, exist_ok=True)
    try:                # the paired FPS an earlier report of this comparison measured
        earlier_fps = _read_json(out / "results.json").get("fps_pair")
    except ValueError:
        earlier_fps = None

    results = {
        "format": RESULTS_FORMAT,
        "scene": scene_path,
        "baseline": BASELINE,
        "methods": [{"name": m.name, "patches": list(m.patches)}
                    | ({"lambdas": list(m.lambdas)} if m.lambdas else {}) for m in methods],
        "common_patches": list(common_patches),
        "sets": list(sets),
        "lambdas": None if lambdas is None else [float(x) for x in lambdas],
        "seeds": None if seeds is None else [int(x) for x in seeds],
        "codec": {"patch": codec, "settings": codec_over} if codec else None,
        "lpips": f"measured with {lp_id}" if lpips_fn is not None else lpips_reason,
        "only": list(only) if only else None,
        "reference": None,
        "reference_method": (None if ref_method is None else
                             {"name": ref_method.name, "patches": list(ref_method.patches)}),
        "versions": versions(),
        "complete": False,
        "missing": [],
        "runs": [],
    }
    for name, why in untimed or ():
        mark_untimed(specs, name, why, lp_id, codec_over)
    finished = [is_finished(s, lp_id, codec_over) for s in specs]   # reads each run's records once
    earlier = {str(Path(k).resolve()): list(v) for k, v in (done_before or {}).items() if v}
    # runs this command brought to the end elsewhere are no runs that had finished before it
    n_done = 0 if remeasure else sum(f and str(s.dir.resolve()) not in earlier
                                     for s, f in zip(specs, finished))
    if echo and methods:
        per = sorted({sum(s.method.name == m.name for s in specs) for m in methods})
        per_txt = "/".join(str(n // len(seeds) if seeds else n) for n in per)
        what = (f"{per_txt} rate point(s) x {len(seeds)} seed(s)" if seeds
                else f"{per_txt} rate point(s)")
        ref_txt = (f" + the uncompressed reference ({ref_method.name})"
                   if ref_spec is not None and (not only or REFERENCE in only) else "")
        print(f"compare: {len(methods)} method(s) x {what} = "
              f"{len(specs)} run(s){ref_txt} on {scene_path}; {n_done} already finished in "
              f"{out / 'runs'}")
        slow = sorted({s.cfg.train.iterations for s in specs
                       if s.cfg.train.iterations >= s.cfg.train.schedule_base
                       and str(resolve_device(s.cfg.train.device)) == "cpu"})
        if slow and not report_only:
            print(f"note: {slow[-1]} iterations per run on the CPU (the paper's schedule; hours "
                  f"per run on real scenes): --patch cpu runs the 6k-iteration CPU preset, "
                  f"--patch demo the 1k one")
    elif echo:
        print(f"compare: the uncompressed reference only, on {scene_path}")
    if report_only:
        results["missing"] = [s.label for s, done in zip(specs, finished) if not done]
        specs = [s for s, done in zip(specs, finished) if done]
        if echo and results["missing"]:
            print("--report-only: not run yet (left alone): " + ", ".join(results["missing"]))
    ref_done = ref_spec is not None and reference_finished(ref_spec)
    # the reference is trained when asked for (no --only, or --only reference); once finished it
    # is reported by every invocation
    ref_todo = ref_spec is not None and not ref_done and not report_only and (
        not only or REFERENCE in only)
    if ref_spec is not None and not ref_done and not ref_todo and report_only:
        results["missing"].append(f"{REFERENCE} ({ref_method.name})")
    if n_done < len(specs) or ref_todo:
        _warm_up_rasterizer(specs + ([ref_spec] if ref_todo else []))
    t0 = time.perf_counter()
    if ref_done or ref_todo:
        head = f"[{REFERENCE}] {ref_method.name} (uncompressed)"
        row = run_reference(ref_spec, scene_path, progress=progress,
                            on_stage=(lambda s: tqdm.write(f"{head}: {s} ({ref_spec.dir})"))
                            if echo else None)
        results["reference"] = row
        write_json_atomic(out / "results.json", results)
        if echo:
            what = _stages_text(earlier.get(str(ref_spec.dir.resolve()), []) + row["stages_run"])
            print(f"{head}: PSNR {row['psnr']:.3f} dB  float32 {row['mb']:.4f} MB  [{what}]")
    bar = tqdm(total=len(specs), desc="compare", unit="run", disable=not progress,
               dynamic_ncols=True, position=0)
    for i, spec in enumerate(specs):
        head = f"[{i + 1}/{len(specs)}] {spec.label}"
        bar.set_postfix_str(head, refresh=True)

        def on_stage(s, head=head):
            bar.set_postfix_str(f"{head}: {s}", refresh=True)
            if echo:
                tqdm.write(f"{head}: {s} ({spec.dir})")

        row = run_one(spec, scene_path, lpips_fn, lp_id, progress=progress, on_stage=on_stage,
                      remeasure=remeasure, codec=codec_over)
        results["runs"].append(row)
        write_json_atomic(out / "results.json", results)       # partial results survive
        if echo:
            what = _stages_text(earlier.get(str(spec.dir.resolve()), []) + row["stages_run"])
            tqdm.write(f"{head}: PSNR {row['psnr']:.3f} dB  {row['mb']:.4f} MB  "
                       f"FPS {row['fps']:.1f}  [{what}]")
        bar.update(1)
    bar.close()
    results["complete"] = not results["missing"]
    results["wall_s_this_invocation"] = time.perf_counter() - t0
    if paired_fps and results["runs"]:
        results["fps_pair"] = paired_fps_bench(results, previous=None if remeasure
                                               else earlier_fps)
    if scope:
        results["scope"] = scope
    paths = write_report(results, out, plots=plots, panel_views=panel_views)
    results["report"] = {k: str(v) for k, v in paths.items()}
    write_json_atomic(out / "results.json", results)
    if echo:
        print(format_report(results, markdown=False))
        print("wrote " + ", ".join(str(p) for p in [out / "results.json", *paths.values()]))
    return results
