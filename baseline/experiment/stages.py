"""The stages that bring one run to the finished state: train (resuming a checkpoint), encode
to its file, decode the file alone and measure it, the Gaussian census; and the uncompressed
reference's float32 size. Each stage is recorded as soon as it is done."""
from __future__ import annotations

import dataclasses
from typing import Callable, Optional

from tqdm import tqdm

from baseline.contracts import feature_cache
from baseline.experiment.plan import RunSpec
from baseline.experiment.records import (ALIVE_KEYS, DECODED_VIEWS, MB, RECORD, check_scene,
                                         encoded, evaluated, make_row, read_json, records_only,
                                         run_codec, ssim_fields, trained, training_history,
                                         write_record)
from baseline.modelfile import MODEL_FILE


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


def train_stage(spec: RunSpec, scene_path: str, progress: bool,
                 stage: Callable[[str], None]) -> tuple[dict, list[str]]:
    """Stage 1 of a run (a compared method's or the reference's): train it unless its
    results.json holds the test metrics at the configured iterations (an interrupted training
    resumes from its checkpoint). Returns its results and ``["train"]`` if it trained now."""
    from baseline.run import train_run

    check_scene(spec, scene_path)
    res = trained(spec)
    if res is not None:
        return res, []
    stage("train")
    return train_run(scene_path, spec.dir, spec.cfg, resume=True, progress=progress,
                     evaluate_after=True), ["train"]


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
    write_record(spec, record)


def reference_finished(spec: RunSpec) -> bool:
    record = read_json(spec.dir / RECORD)
    return (trained(spec) is not None and record.get("config_hash") == spec.hash
            and "reference" in record)


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
    res, done = train_stage(spec, scene_path, progress, stage)
    record = read_json(spec.dir / RECORD)
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
            **training_history(res),
            "device": res.get("device", "cpu"), "protocol": res.get("protocol", {}),
            "records_only": records_only(spec), "stages_run": done}


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
    write_record(spec, record)


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
    write_record(spec, record)


def _stage_census(spec: RunSpec, record: dict) -> None:
    """Where the run's Gaussians come from (:mod:`baseline.eval.census`), from its checkpoint's
    coded state (what the file holds, with the anchors' births); the per-view list is dropped."""
    from baseline.eval.census import census_of

    c = census_of(str(spec.dir))
    c.pop("view_kept_share", None)
    c.pop("target", None)
    record["census"] = c
    write_record(spec, record)


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

    res, done = train_stage(spec, scene_path, progress, stage)
    record = read_json(spec.dir / RECORD)
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
    if not encoded(spec, record, codec):
        if records_only(spec) and record.get("encode"):
            raise ValueError(f"{spec.label} is kept only as records (no checkpoint), written "
                             f"with codec settings {record['encode'].get('codec', run_codec(spec))}; "
                             f"it cannot be encoded again with {run_codec(spec, codec)}")
        stage("encode")
        _stage_encode(spec, scene_path, record, codec)
        done.append("encode")
    elif _fill_file_counts(spec, record):
        write_record(spec, record)
    if not evaluated(record, lpips if lpips_fn is not None else None):
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
            write_record(spec, record)
    row = make_row(spec, res, record)
    row["stages_run"] = done
    return row
