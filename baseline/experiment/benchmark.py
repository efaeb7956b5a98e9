"""``pgs benchmark``: one comparison per scene of a dataset, run by an executor, and the
dataset's report in the layout of the papers' tables.

For each scene ``OUT/<scene>/`` is exactly the folder ``pgs compare`` would make (the same run
folders, config hashes, resume and archived records); every unfinished run becomes one job of
the executor (:mod:`baseline.experiment.executors`: this process, N local processes, or Ray tasks on a
cluster), finished runs are skipped, so a benchmark that was stopped, or whose cluster lost a
node, is completed by running the same command again. When all jobs are done, each scene's
comparison report is written (``pgs compare`` reusing every run), then the dataset's:

* per method and rate point (and seed mean, with seeds) the mean over the scenes of PSNR,
  SSIM, LPIPS and size, split as the paper's Table 3 (feature vs the rest);
* BD-rate and BD-PSNR against the baseline (and of a method against each contender it
  extends) per scene and their mean;
* speed against error (training time, encode / decode time, FPS, Gaussians per view);
* the survey CSVs, one per method and scene (``survey/<method>/<Dataset>/<scene>.csv``: each
  method's folder laid out as the 3DGS compression survey reads a method's ``results/``).

Protocols (``--protocol``) add a dataset patch (kind ``dataset``, ``pgs config --list``):
``mip360``, ``tandt``, ``deepblending``, ``nerf-synthetic``.
"""
from __future__ import annotations

import json
import statistics
import time
from pathlib import Path
from typing import Optional

from baseline.experiment.executors import Job, make_executor
from baseline.experiment.plan import BASELINE, parse_methods, plan_runs
from baseline.experiment.records import is_finished, lpips_id
from baseline.eval.report import survey_datasets
from baseline.fileio import read_text_bounded, write_text_atomic

MB = 2 ** 20


def find_scenes(root: Path, names: Optional[list[str]] = None) -> list[Path]:
    """The scene folders under ``root`` (``names``: those, in that order)."""
    from baseline.data.readers import detect_format
    from baseline.data.errors import SceneError

    root = Path(root)
    if names:
        out = []
        for n in names:
            p = root / n
            detect_format(p.resolve())          # a clear error for a missing or bad scene
            out.append(p.resolve())
        return out
    out = []
    for p in sorted(root.iterdir()):
        if p.is_dir():
            try:
                detect_format(p.resolve())
                out.append(p.resolve())
            except SceneError:
                continue
    if not out:
        raise FileNotFoundError(f"{root}: no scene folder (COLMAP or Blender) found")
    return out


def plan_jobs(scenes: list[Path], out: Path, vs: list[str], lambdas, seeds, common: list[str],
              sets: list[str], lpips_weights: Optional[str] = None) -> tuple[list, list]:
    """(every run's (scene, spec), the jobs of the unfinished ones)."""
    methods = parse_methods(list(vs))
    lp = lpips_id(lpips_weights) if lpips_weights else None
    allruns, jobs = [], []
    for sc in scenes:
        sout = (out / sc.name).resolve()
        for spec in plan_runs(sout, methods, lambdas, common, sets, seeds):
            allruns.append((sc, spec))
            if not is_finished(spec, lp):
                jobs.append(Job(scene=str(sc), out=str(sout), method=spec.method.name,
                                method_patches=tuple(spec.method.patches),
                                lmbda=spec.lmbda if lambdas else None, seed=spec.seed,
                                common_patches=tuple(common), sets=tuple(sets),
                                lpips_weights=lpips_weights, label=f"{sc.name}: {spec.label}"))
    return allruns, jobs


def run_benchmark(root, out, vs: list[str] = (), lambdas=None, seeds=None, scenes=None,
                  protocol: Optional[str] = None, common_patches: list[str] = (),
                  sets: list[str] = (), executor: str = "local", executor_options=None,
                  lpips_weights: Optional[str] = None, plots: bool = True,
                  progress: bool = True, echo: bool = True, overwrite: bool = False) -> dict:
    from baseline.experiment.runner import run_compare
    from baseline.guard import check_output, write_marker
    from baseline.run import write_json_atomic

    out = Path(out).resolve()
    # new, empty, this root's benchmark (to resume) or, with ``overwrite``, another of the
    # toolkit's outputs; never a folder of the user's files
    check_output(out, command="benchmark", source=root, folder=True, overwrite=overwrite)
    common = list(common_patches)
    if protocol is not None:
        if protocol not in survey_datasets():
            raise ValueError(f"--protocol {protocol!r}: one of {', '.join(survey_datasets())}")
        common = [protocol] + common
    scene_dirs = find_scenes(Path(root), scenes)
    write_marker(out, "benchmark", root)
    allruns, jobs = plan_jobs(scene_dirs, out, list(vs), lambdas, seeds, common, list(sets),
                              lpips_weights)
    if echo:
        print(f"benchmark: {len(scene_dirs)} scene(s), {len(allruns)} run(s), "
              f"{len(allruns) - len(jobs)} finished, {len(jobs)} to run on the {executor} "
              f"executor")
    t0 = time.perf_counter()
    ex = make_executor(executor, progress=progress, **(executor_options or {}))
    res = ex.execute(jobs) if jobs else {"done": [], "failed": []}
    wall = time.perf_counter() - t0
    failed = res["failed"]
    per_scene = {}
    for sc in scene_dirs:
        r = run_compare(str(sc), out / sc.name, vs=list(vs), lambdas=lambdas, seeds=seeds,
                        common_patches=common, sets=list(sets), lpips_weights=lpips_weights,
                        progress=False, plots=plots, echo=False, report_only=True,
                        panel_views=None if plots else [])
        per_scene[sc.name] = r
    dataset = survey_datasets()[protocol] if protocol else Path(root).name
    results = {"format": "pgs-benchmark/1", "root": str(Path(root).resolve()),
               "dataset": dataset, "protocol": protocol, "scenes": [s.name for s in scene_dirs],
               "methods": [m.name for m in parse_methods(list(vs))], "lambdas": lambdas,
               "seeds": seeds, "common_patches": common, "sets": list(sets),
               "executor": executor, "executor_options": executor_options or {},
               "jobs_run": len(res["done"]), "failed": [list(f) for f in failed],
               "wall_s_this_invocation": wall,
               "complete": all(r.get("complete") for r in per_scene.values()) and not failed}
    results["table"] = dataset_table(per_scene)
    results["bd"] = dataset_bd(per_scene)
    write_json_atomic(out / "results.json", results)
    write_survey(per_scene, out / "survey", dataset)
    write_text_atomic(out / "report.md", format_benchmark(results))
    if echo:
        print(format_benchmark(results, markdown=False))
        if failed:
            print(f"{len(failed)} run(s) failed after retries: "
                  + "; ".join(f"{n} ({e})" for n, e in failed))
    return results


def _key(r: dict):
    return (r["method"], r["lmbda"])


def dataset_table(per_scene: dict) -> list[dict]:
    """Mean over the scenes per (method, lambda): the seed means first within each scene."""
    from baseline.eval.report import field_ssim, untimed

    def timed(r):   # an untimed training time (stalled, marked, two machines) measures no cost
        return None if untimed(r) else r["train_time_s"]

    acc: dict = {}
    for scene, res in per_scene.items():
        groups: dict = {}
        for r in res.get("runs", []):
            groups.setdefault(_key(r), []).append(r)
        for k, rs in groups.items():
            def mean(f):
                vals = [f(r) for r in rs]
                return None if any(v is None for v in vals) else sum(vals) / len(vals)
            acc.setdefault(k, {})[scene] = {
                "psnr": mean(lambda r: r["psnr"]), "ssim": mean(field_ssim),
                "lpips": mean(lambda r: r.get("lpips")), "mb": mean(lambda r: r["mb"]),
                "feature_mb": mean(lambda r: r["groups"].get("feature", 0) / MB),
                "train_s": mean(timed), "fps": mean(lambda r: r["fps"]),
                "encode_s": mean(lambda r: r["encode_s"]), "decode_s": mean(lambda r: r["decode_s"]),
                "gaussians": mean(lambda r: r.get("gaussians_mean")), "runs": len(rs)}
    rows = []
    for (m, lm), by in sorted(acc.items(), key=lambda kv: (kv[0][0] != "baseline", kv[0])):
        row = {"method": m, "lmbda": lm, "scenes": sorted(by), "n_scenes": len(by)}
        for f in ("psnr", "ssim", "lpips", "mb", "feature_mb", "train_s", "fps", "encode_s",
                  "decode_s", "gaussians"):
            vals = [v[f] for v in by.values()]
            row[f] = None if any(x is None for x in vals) else statistics.fmean(vals)
        row["others_mb"] = None if row["mb"] is None else row["mb"] - row["feature_mb"]
        rows.append(row)
    return rows


def dataset_bd(per_scene: dict) -> list[dict]:
    """BD-rate / BD-PSNR per scene (the seed-mean curves where there are seeds) and the mean, per
    method and reference (the baseline, or a contender the method extends)."""
    from baseline.eval.report import bd_against

    out: dict = {}
    for scene, res in per_scene.items():
        for b in res.get("bd") or []:
            if b.get("seed") not in (None, "mean"):
                continue
            key = (b["method"], bd_against(res, b))
            out.setdefault(key, {})[scene] = (b["bd_rate"], b["bd_psnr"])
    rows = []
    for (m, ref), by in out.items():
        rates = [v[0] for v in by.values() if v[0] is not None]
        psnrs = [v[1] for v in by.values() if v[1] is not None]
        rows.append({"method": m, "against": ref,
                     "per_scene": {s: {"bd_rate": v[0], "bd_psnr": v[1]}
                                                for s, v in by.items()},
                     "mean_bd_rate": statistics.fmean(rates) if len(rates) == len(by) and rates
                     else None,
                     "mean_bd_psnr": statistics.fmean(psnrs) if len(psnrs) == len(by) and psnrs
                     else None})
    return rows


def write_survey(per_scene: dict, folder: Path, dataset: str) -> None:
    from baseline.eval.report import write_survey as write_scene

    for scene, res in per_scene.items():
        if res.get("runs"):
            write_scene(res, folder, dataset, scene)


def _f(v, nd):
    return "-" if v is None else f"{v:.{nd}f}"


def format_benchmark(res: dict, markdown: bool = True) -> str:
    from baseline.eval.report import STALL_FLOOR_S, STALL_LIMIT, method_label

    def name(m):
        return method_label(m, res.get("common_patches", ()))

    head = ["method", "lambda", "scenes", "PSNR", "SSIM", "LPIPS", "size (MB)", "feature (MB)",
            "others (MB)", "train (s)", "encode (s)", "decode (s)", "FPS", "Gaussians/view"]
    rows = [[name(r["method"]), f"{r['lmbda']:g}", str(r["n_scenes"]), _f(r["psnr"], 3),
             _f(r["ssim"], 4), _f(r["lpips"], 4), _f(r["mb"], 4), _f(r["feature_mb"], 4),
             _f(r["others_mb"], 4), _f(r["train_s"], 0), _f(r["encode_s"], 2),
             _f(r["decode_s"], 2), _f(r["fps"], 1), _f(r["gaussians"], 0)]
            for r in res["table"]]
    bd_head = ["method"] + list(res["scenes"]) + ["mean"]
    bd_rows = []
    for b in res["bd"]:
        ref = b.get("against", BASELINE)            # records from before references: baseline
        cells = [name(b["method"]) + ("" if ref == BASELINE else f" vs {name(ref)}")]
        for s in res["scenes"]:
            v = b["per_scene"].get(s)
            cells.append("-" if not v or v["bd_rate"] is None else
                         f"{v['bd_rate']:+.2f}% ({v['bd_psnr']:+.3f} dB)"
                         if v["bd_psnr"] is not None else f"{v['bd_rate']:+.2f}%")
        cells.append("-" if b["mean_bd_rate"] is None else f"{b['mean_bd_rate']:+.2f}%")
        bd_rows.append(cells)

    def table(h, rs):
        if markdown:
            return "\n".join(["| " + " | ".join(h) + " |", "|" + "|".join("---" for _ in h) + "|"]
                             + ["| " + " | ".join(r) + " |" for r in rs])
        w = [max(len(str(c)) for c in col) for col in zip(h, *rs)] if rs else [len(x) for x in h]
        return "\n".join("  ".join(str(c).ljust(x) for c, x in zip(r, w)) for r in [h] + rs)

    proto = (f"protocol `{res['protocol']}` " if res.get("protocol") else "") + \
        f"common patches {', '.join(res['common_patches']) or '(none)'}; --set " \
        f"{', '.join(res['sets']) or '(none)'}; seeds {res.get('seeds') or 'the config'}"
    parts = [f"# Benchmark: {res['dataset']} ({len(res['scenes'])} scenes)" if markdown else
             f"Benchmark: {res['dataset']} ({len(res['scenes'])} scenes)",
             f"Scenes: {', '.join(res['scenes'])}; {proto}. Each scene's comparison report is in "
             f"its folder; means below are over the scenes (within a scene, over its seeds). "
             f"SSIM: 3DGS's (Gaussian window, zero padding; '-' where a scene's records hold "
             f"only scikit-image's).",
             ("## " if markdown else "") + "Mean over the scenes (as the paper's Tables 1 and 3)",
             table(head, rows),
             ("## " if markdown else "") + "BD-rate against the baseline, and of a method that "
             "extends another contender against it (\"vs\"; seed-mean curves; negative = fewer "
             "bytes at equal PSNR)",
             table(bd_head, bd_rows) if any(any(c != "-" for c in r[1:]) for r in bd_rows)
             else "BD-rate needs at least 3 rate points (--lambda) per method.",
             f"Survey CSVs: `survey/<method>/{res['dataset']}/<scene>.csv`. Executor: {res['executor']} "
             f"{res['executor_options'] or ''}; runs done by this invocation: {res['jobs_run']}; "
             f"wall {res['wall_s_this_invocation']:.0f} s."]
    if any(r["train_s"] is None for r in res["table"]):
        parts.append(f"train (s) '-': a run of that row stalled over {STALL_LIMIT:.0%} of its "
                     f"training time and {STALL_FLOOR_S:.0f} s (paused, or sharing its core) or "
                     "was marked untimed; its "
                     "scene's report names it.")
    if res["failed"]:
        parts.append("FAILED after retries: " + "; ".join(f"{n} ({e})" for n, e in res["failed"]))
    if not res["complete"]:
        parts.append("Incomplete: rerun the same command to finish the missing runs.")
    return "\n\n".join(parts) + "\n"


def benchmark_records(out: Path) -> dict:
    """``{run folder name: (psnr, ssim, bytes, anchors)}`` of every finished run under ``out``
    (to compare two executions of one benchmark)."""
    rec = {}
    for p in sorted(Path(out).glob("*/runs/*/compare.json")):
        r = json.loads(read_text_bounded(p, "a run's record"))
        d = r.get("decoded") or {}
        rec[f"{p.parent.parent.parent.name}/{p.parent.name}"] = (
            d.get("psnr"), d.get("ssim"), d.get("bytes"), d.get("anchors"))
    return rec
