"""A run's records: the files that say which stages are done (``results.json``,
``compare.json``), the flat results row read from them, the untimed mark, and archiving the
records of finished runs. Nothing here trains or measures."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Optional

from baseline.config import build_config
from baseline.experiment.plan import RunSpec
from baseline.modelfile import MODEL_FILE


# evaluate()'s breakdown of the Gaussians per view (baseline/eval/evaluate.py alive_breakdown)
ALIVE_KEYS = ("visible_anchors_mean", "mask_on_fraction", "opacity_kept_fraction")

RECORD = "compare.json"

RESULTS_FORMAT = "pgs-compare/1"

# the decoded file's views of a run: renders/, gt/ and per_view.json (3DGS's layout)
DECODED_VIEWS = "decoded"

MB = 2 ** 20

RECORD_FILES = ("config.toml", "scene.json", "results.json", RECORD)


def read_json(path: Path) -> dict:
    if not path.exists():
        return {}
    from baseline.fileio import read_text_bounded

    try:
        return json.loads(read_text_bounded(path, "a run's record"))
    except json.JSONDecodeError as e:
        raise ValueError(f"{path} is not valid JSON ({e}); delete it to redo that stage") from None


def write_record(spec: RunSpec, record: dict) -> None:
    from baseline.run import write_json_atomic

    write_json_atomic(spec.dir / RECORD, record)


def trained(spec: RunSpec) -> Optional[dict]:
    res = read_json(spec.dir / "results.json")
    if "test" in res and res.get("iterations") == spec.cfg.train.iterations:
        return res
    return None


def training_history(res: dict) -> dict:
    """The machine and code a run trained on, a resumed run's thread counts, machines and
    codes by stretch of iterations when it had several, and its stall time (of the training
    time, the seconds it ran on no core), each where it was kept."""
    return {k: res[k] for k in ("machine", "threads_by_iteration", "machines_by_iteration",
                                "code", "codes_by_iteration", "stall_s", "stall_from")
            if res.get(k) is not None}


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


def encoded(spec: RunSpec, record: dict, codec: Optional[dict] = None) -> bool:
    enc = record.get("encode")
    if not enc or record.get("config_hash") != spec.hash:
        return False
    # records from before codec settings were recorded were written with the run's own config's
    if enc.get("codec", run_codec(spec)) != run_codec(spec, codec):
        return False
    pgs = spec.dir / MODEL_FILE
    if pgs.exists():
        return pgs.stat().st_size == enc.get("bytes")
    return records_only(spec) and trained(spec) is not None


def lpips_id(weights: Optional[str]) -> Optional[str]:
    """Which LPIPS weights a measurement used: resolved path and byte count (None: no LPIPS)."""
    if weights is None:
        return None
    from baseline.eval.metrics import lpips_paths

    ps = [p.resolve() for p in lpips_paths(weights)]
    if not ps or not all(p.is_file() for p in ps):
        return None
    return ", ".join(f"{p} ({p.stat().st_size} bytes)" for p in ps)


def evaluated(record: dict, lpips: Optional[str]) -> bool:
    """Decoded measurements done for this file (and with these LPIPS weights, if any now)."""
    dec = record.get("decoded")
    if not dec or record.get("encode", {}).get("bytes") != dec.get("bytes"):
        return False
    return lpips is None or (dec.get("lpips") is not None and dec.get("lpips_weights") == lpips)


def is_finished(spec: RunSpec, lpips: Optional[str] = None, codec: Optional[dict] = None) -> bool:
    record = read_json(spec.dir / RECORD)
    return (trained(spec) is not None and encoded(spec, record, codec)
            and evaluated(record, lpips))


def check_scene(spec: RunSpec, scene_path: str) -> None:
    sj = read_json(spec.dir / "scene.json")
    if sj and sj.get("path") != scene_path:
        raise ValueError(f"{spec.dir} was trained on {sj.get('path')}, not {scene_path}; "
                         f"use another --out folder for another scene")


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
        **training_history(res),
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
        record = read_json(spec.dir / RECORD)
        if why.strip():
            record["untimed"] = why.strip()
        else:
            record.pop("untimed", None)
        write_record(spec, record)


def is_compare_folder(folder: Path) -> bool:
    """A comparison's folder written before folders were marked (its ``runs/``)."""
    return (Path(folder) / "runs").is_dir()


def archive_records(out: str | Path, dest: str | Path,
                    results: Optional[dict] = None, overwrite: bool = False) -> list[Path]:
    """Copy the records of the finished runs of comparison ``out`` (and its report, results
    and plots) to ``dest``: a few KB per run, no checkpoints or model files. Copied into another
    comparison's ``--out`` folder they are reported as finished (see :func:`records_only`).
    The top level's report, results (JSON and CSV) and plots are copied with them.
    ``results``: the dict :func:`run_compare` returned; when given, only the runs it reports
    (and its reference) are kept, not other comparisons' runs that share ``out``.
    ``dest`` is checked as ``--out`` is (:func:`baseline.guard.check_output`): new, empty, or
    an archive of the same scene's comparison (``overwrite``: another of the toolkit's).
    Returns the run folders archived."""
    import shutil

    from baseline.guard import check_output

    out, dest = Path(out), Path(dest)
    scene = (results or read_json(out / "results.json")).get("scene")
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
        rec = read_json(run / RECORD)
        res = read_json(run / "results.json")
        if not ("test" in res and (rec.get("encode") and rec.get("decoded")
                                   or "reference" in rec)):
            continue                       # not finished: nothing to keep yet
        (dest / "runs" / run.name).mkdir(parents=True, exist_ok=True)
        for name in RECORD_FILES:
            shutil.copy2(run / name, dest / "runs" / run.name / name)
        done.append(dest / "runs" / run.name)
    for f in out.iterdir() if out.is_dir() else []:
        if f.is_file() and f.suffix in (".md", ".json", ".png", ".csv"):
            dest.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, dest / f.name)
    return done
