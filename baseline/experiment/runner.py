"""``run_compare``: a whole comparison (plan, the runs brought to the end one after another,
the reference, the paired FPS bench, the report)."""
from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

from tqdm import tqdm

from baseline.experiment.plan import (BASELINE, REFERENCE, RunSpec, parse_methods,
                                      parse_reference, plan_reference, plan_runs, resolve_method,
                                      with_own_lambdas)
from baseline.experiment.records import (RESULTS_FORMAT, codec_overrides, is_compare_folder,
                                         is_finished, lpips_id, mark_untimed, read_json)
from baseline.experiment.stages import reference_finished, run_one, run_reference
from baseline.modelfile import MODEL_FILE


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
    (:func:`baseline.bench.fps.bench_files`: same views, rounds in rotated order), at the
    middle rate point both have (the lowest seed): ``{method: {ratio, fps, fps_ref, lmbda,
    rounds, threads, ratio_rounds, runs, bytes}}``; FPS taken by separate runs at separate times
    make no ratio. ``ratio`` is ``fps / fps_ref`` (each the median over rounds), the figures it
    is printed beside; ``ratio_rounds`` the range of the per-round ratios.

    ``previous``: the ``fps_pair`` of an earlier report of this comparison; a pair of the same
    two runs and files (folder names and byte counts) is reused as measured, so a report rebuilt
    from finished runs is the same report (``--remeasure`` passes None and times it again)."""
    from baseline.bench.fps import bench_files
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


def _train_in_workers(specs: list[RunSpec], ref_spec: Optional[RunSpec], scene_path: str,
                      out: Path, common_patches: list[str], sets: list[str],
                      lpips_weights: Optional[str], codec: Optional[str], jobs: int,
                      progress: bool, echo: bool) -> dict:
    """Bring ``specs`` (and ``ref_spec``) to the finished state on ``jobs`` worker processes;
    ``{run folder (resolved): [stages run]}``. Raises with every failed run's error."""
    from baseline.experiment.executors import LocalExecutor, jobs_of
    from baseline.train.trainer import available_cores

    work = jobs_of(specs, ref_spec, scene_path, out, common_patches, sets, lpips_weights, codec)
    if not work:
        return {}
    n = max(1, min(jobs, available_cores(), len(work)))
    if echo:
        print(f"compare: {len(work)} run(s) to do on {n} worker(s), one per core share: "
              + ", ".join(j.label for j in work))

    def said(row):
        if echo:
            tqdm.write(f"finished: {row['label']} ({row['run_dir']})")

    res = LocalExecutor(jobs=n, progress=progress).execute(work, on_done=said)
    if res["failed"]:
        raise RuntimeError(f"{len(res['failed'])} run(s) failed (the finished ones are kept; "
                           f"run the same command again to resume): "
                           + "; ".join(f"{label}: {err}" for label, err in res["failed"]))
    return {str(Path(r["run_dir"]).resolve()): list(r["stages_run"]) for r in res["done"]}


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
                done_before: dict | None = None, jobs: int = 1) -> dict:
    """Run (or resume) a comparison; write ``out/results.json``, ``out/report.md`` and plots.

    ``only``: bring only the runs of these methods (``baseline``, a ``--vs`` value, or a name as
    the report shows it: ``HAC``, ``HAC++``) to the finished state, and report those; the others are left as they are.
    This splits a comparison across processes or machines sharing ``out`` (e.g. one process per
    core: ``taskset -c 0 pgs compare ... --only baseline`` beside ``taskset -c 1 ... --only
    hacpp``); a final invocation without it reuses every finished run for the full report.
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
    ``jobs``: runs trained at a time, each in a process of its own pinned to its share of the
    cores (:class:`~baseline.experiment.executors.LocalExecutor`, as ``pgs demo`` runs them):
    the runs still to do (and the reference, when it is to be trained) go to those workers
    first, then this process reports every run as it does after ``--only`` runs in parallel.
    A run that fails there stops the comparison with its error, the finished runs kept.
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
        earlier_fps = read_json(out / "results.json").get("fps_pair")
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
    if jobs > 1 and not report_only:
        todo = [s for s, f in zip(specs, finished) if not f]
        done = _train_in_workers(todo, ref_spec if ref_todo else None, scene_path, out,
                                 list(common_patches), list(sets), lpips_weights, codec, jobs,
                                 progress, echo)
        for k, v in done.items():
            earlier[k] = earlier.get(k, []) + v
        # measured by the workers just now: not measured a second time
        trained_here = set(done)
    else:
        trained_here = set()
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
                      remeasure=remeasure and str(spec.dir.resolve()) not in trained_here,
                      codec=codec_over)
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
