"""Commands that run experiments: ``bench``, ``compare``, ``benchmark``, ``warmup``, ``demo``."""
from __future__ import annotations

import sys
import time
from pathlib import Path

from baseline.cli.common import (_config_args, _config_sets, LPIPS_HELP, _lpips_weights,
                                 _positive_int, SCENE_HELP)


def cmd_bench(args) -> int:
    if args.what == "raster":
        from baseline.bench.raster import format_raster_bench, run_raster_bench

        rows = run_raster_bench(threads=args.threads)
        print(format_raster_bench(rows))
    elif args.what == "codec":
        from baseline.bench.codec import format_codec_bench, run_codec_bench, run_model_codec_bench

        rows = []
        for model in (args.model or ["hac", "hacpp"]):
            rows += run_codec_bench(n_anchors=args.anchors or 500_000, model=model,
                                    threads=args.threads or 0)
        rows += [run_model_codec_bench(r) for r in args.run]
        print(format_codec_bench(rows))
    elif args.what == "grid":
        from baseline.bench.grid import format_grid_bench, run_grid_bench

        print(format_grid_bench(run_grid_bench(args.anchors or 100_000, threads=args.threads)))
    elif args.what == "fps":
        from baseline.bench.fps import bench_files, format_fps_bench

        rounds = 5 if args.rounds is None else args.rounds
        print(format_fps_bench(bench_files(args.run, scene=args.scene, rounds=rounds,
                                           threads=args.threads, device=args.device,
                                           max_views=args.views)))
    elif args.what == "train":
        from baseline.bench.train import format_train_bench, run_train_bench

        print(format_train_bench(run_train_bench(args.run, steps=args.steps,
                                                 threads=args.threads or 1,
                                                 anchors=args.anchors, methods=args.vs,
                                                 clock=args.clock)))
    elif args.what == "frame":
        from baseline.bench.fps import bench_frame_files, format_frame_bench

        rounds = 3 if args.rounds is None else args.rounds
        print(format_frame_bench(bench_frame_files(args.run, scene=args.scene, rounds=rounds,
                                                   threads=args.threads, device=args.device,
                                                   max_views=args.views)))
    return 0


def cmd_compare(args) -> int:
    """Side by side: the baseline and each --vs method at each lambda; report + plots."""
    from baseline.experiment import run_compare

    sets = _config_sets(args)
    if args.archive:                   # checked now, not after hours of training
        from baseline.experiment import is_compare_folder
        from baseline.guard import check_output

        check_output(args.archive, command="compare", source=args.scene, folder=True,
                     own=is_compare_folder, overwrite=args.overwrite)
    try:
        results = run_compare(args.scene, args.out, vs=args.vs, lambdas=args.lambdas,
                              common_patches=args.patch, sets=sets,
                              lpips_weights=_lpips_weights(args), progress=not args.no_progress,
                              plots=not args.no_plots, only=args.only, remeasure=args.remeasure,
                              report_only=args.report_only, reference=args.reference,
                              codec=args.codec, seeds=args.seeds,
                              panel_views=args.panel_views, paired_fps=args.paired_fps,
                              lambda_for=args.lambda_for, untimed=args.untimed,
                              overwrite=args.overwrite, jobs=args.jobs)
    except KeyboardInterrupt:
        print(f"\ninterrupted: finished stages are kept in {args.out}; run the same command "
              f"again to resume", file=sys.stderr)
        return 130
    if args.archive:
        from baseline.experiment import archive_records

        kept = archive_records(args.out, args.archive, results, overwrite=args.overwrite)
        print(f"archived the records of {len(kept)} finished run(s) and the report to {args.archive}")
    return 0


def cmd_benchmark(args) -> int:
    """One comparison per scene of a dataset, on an executor; the dataset's report."""
    from baseline.experiment.benchmark import run_benchmark

    sets = _config_sets(args)
    opts = {"retries": args.retries}
    if args.executor == "local":
        opts["jobs"] = args.jobs
    else:
        opts.update(address=args.address, cpus_per_run=args.cpus_per_run,
                    gpus_per_run=args.gpus_per_run)
    scenes = [s for s in (args.scenes or "").split(",") if s] or None
    res = run_benchmark(args.root, args.out, vs=args.vs, lambdas=args.lambdas, seeds=args.seeds,
                        scenes=scenes, protocol=args.protocol, common_patches=args.patch,
                        sets=sets, executor=args.executor, executor_options=opts,
                        lpips_weights=_lpips_weights(args), plots=not args.no_plots,
                        progress=not args.no_progress, overwrite=args.overwrite)
    return 0 if not res["failed"] else 1


def cmd_warmup(args) -> int:
    """Compile the CPU kernels (rasterizer and hash grids) into numba's disk cache, two
    processes at once when two cores are free: a first training then starts at once."""
    import subprocess

    from baseline.train.trainer import available_cores

    t0 = time.perf_counter()
    parts = {"rasterizer": "from baseline.render.cpu import kernels; kernels()",
             "hash grids": "from baseline.hac.hashgrid import warm_kernels; warm_kernels()"}

    def start(code):
        return subprocess.Popen([sys.executable, "-c", code], stderr=subprocess.PIPE, text=True)

    if available_cores() >= 2:                         # both at once
        procs = {name: start(code) for name, code in parts.items()}
        errs = {name: p.communicate()[1] for name, p in procs.items()}
    else:                                              # one core: one after the other
        procs, errs = {}, {}
        for name, code in parts.items():
            procs[name] = start(code)
            errs[name] = procs[name].communicate()[1]
    failed = [(n, errs[n]) for n, p in procs.items() if p.returncode != 0]
    for name, err in failed:
        print(f"warmup: compiling the {name} kernels failed:\n{err[-2000:]}", file=sys.stderr)
    if not failed:
        print(f"warmup: CPU kernels compiled or loaded from numba's cache in "
              f"{time.perf_counter() - t0:.0f} s")
    return 1 if failed else 0


DEMO_LAMBDAS = (0.004, 0.002, 0.001)


def demo_scope(iterations: int) -> str:
    """The report's closing line on what the demo's figures are (and are not)."""
    n = f"{iterations // 1000}k" if iterations % 1000 == 0 else f"{iterations:,}"
    return (f"These figures are the embedded synthetic scene's ({n} iterations, one seed): a "
            "check that the pipelines run and a picture of the comparison, not a claim about "
            "real scenes (docs/RESULTS.md has those).")


def demo_contenders() -> list[str]:
    """The registered methods marked as the demo's contenders (:attr:`MethodSpec.demo`)."""
    from baseline import registry

    names = [name for name, spec in sorted(registry.methods().items()) if spec.demo]
    if not names:
        raise ValueError("no installed method is marked as the demo's contender: name one "
                         "with --vs (pgs config --list lists the methods)")
    return names


def cmd_demo(args) -> int:
    """The main job on the embedded default scene: HAC vs Predict-GS at three rate points, side
    by side. The runs train in parallel, one per core (the local executor); the report ends in
    a verdict (BD-rate, equal-lambda changes, paired FPS and training-time ratios)."""
    from baseline.data.synthetic import make_scene
    from baseline.experiment import (
        parse_methods,
        parse_reference,
        plan_reference,
        plan_runs,
        run_compare,
    )
    from baseline.experiment.executors import LocalExecutor, jobs_of
    from baseline.guard import check_output, write_marker
    from baseline.train.trainer import available_cores

    from baseline.eval.metrics import find_lpips_weights

    vs = args.vs or demo_contenders()         # before anything is written
    out = Path(args.out)
    scene = out / "scene"
    # the demo is a comparison on its own scene: new, empty, or an earlier demo (to resume)
    check_output(out, command="compare", source=scene, folder=True, overwrite=args.overwrite,
                 own=lambda p: (p / "scene" / "synthetic.json").is_file())
    write_marker(out, "compare", scene)
    if not (scene / "sparse").exists():
        make_scene(scene)
        print(f"wrote the default synthetic scene to {scene}")
    t0 = time.perf_counter()
    lpips = find_lpips_weights()            # LPIPS whenever both weight files are here
    lambdas = list(args.lambdas or DEMO_LAMBDAS)
    common = ["demo"] + args.patch
    methods = parse_methods(vs)
    ref = None if args.reference == "none" else args.reference
    specs = plan_runs(out, methods, lambdas, common, args.set)
    ref_spec = (None if ref is None else
                plan_reference(out, parse_reference(ref), common, list(args.set)))
    jobs = jobs_of(specs, ref_spec, scene.resolve(), out, common, args.set, lpips_weights=lpips)
    # the longer trainings first (the contenders', then HAC's), the reference last
    jobs.sort(key=lambda j: (j.reference, j.method == "baseline"))
    n = max(1, min(available_cores(), len(jobs)))
    print(f"demo: {len(jobs)} run(s) on {n} core(s), one per core")
    try:
        res = LocalExecutor(jobs=n, progress=True).execute(jobs)
        if res["failed"]:
            for label, err in res["failed"]:
                print(f"demo: {label} failed: {err}", file=sys.stderr)
            return 1
        run_compare(str(scene), out, vs=vs, lambdas=lambdas,
                    common_patches=common, sets=args.set, progress=False, plots=True,
                    reference=ref, paired_fps=True, lpips_weights=lpips,
                    scope=demo_scope(specs[0].cfg.train.iterations),
                    done_before={r["run_dir"]: r["stages_run"] for r in res["done"]})
    except KeyboardInterrupt:
        print("\ninterrupted: run ./run.sh demo again to resume", file=sys.stderr)
        return 130
    print(f"demo wall time {time.perf_counter() - t0:.1f} s; report in {out / 'report.md'}")
    return 0


def add_parsers(sub) -> None:
    """This group's subcommands, in the order `pgs --help` lists them."""
    p = sub.add_parser("bench", help="benchmarks, printed as ratios to a reference in one process")
    p.add_argument("what", choices=["raster", "codec", "grid", "fps", "frame", "train"], help="what to time (see the README)")
    p.add_argument("--threads", type=int, default=None, help="threads (default: the cores)")
    p.add_argument("--anchors", type=int, default=None,
                   help="payload size (default: codec 500k, grid 100k)")
    p.add_argument("--run", action="append", default=[],
                   help="codec: also encode and decode this trained run folder; fps / frame: a "
                        ".pgs file or a run folder with model.pgs (fps: the first is the "
                        "reference) (repeatable)")
    p.add_argument("--rounds", type=int, default=None,
                   help="fps / frame: timed passes over the views (default 5 / 3)")
    p.add_argument("--scene", default=None,
                   help="fps / frame: the scene (default: the one each file names in its header)")
    p.add_argument("--views", type=int, default=None, help="fps / frame: time only the first N views")
    p.add_argument("--device", default="cpu", help="fps / frame: cpu | cuda | cuda:N | auto")
    p.add_argument("--model", action="append", default=None,
                   choices=["hac", "hacpp", "factorized"],
                   help="codec: entropy model(s) of the synthetic payload (default hac and hacpp)")
    p.add_argument("--steps", type=int, default=10,
                   help="train: timed training steps per run (after 2 untimed)")
    p.add_argument("--vs", action="append", default=[], metavar="P1[+P2...]",
                   help="train without --run: also a method's synthetic state (its patches, "
                        "e.g. predict-gs), timed after HAC's in the same process (repeatable)")
    p.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                   help="train: wall time, or the process's CPU time (at one thread: a step's "
                        "own cost, whatever else shares the core)")
    p.set_defaults(fn=cmd_bench)

    p = sub.add_parser("compare", help="train/encode/decode methods side by side: tables, BD-rate, plots")
    p.add_argument("scene", help=SCENE_HELP)
    p.add_argument("--vs", action="append", default=[], metavar="P1[+P2...]",
                   help="a contender: patches joined by '+' on top of the common ones; repeat")
    p.add_argument("--lambda", dest="lambdas", type=float, nargs="+", action="extend",
                   default=None, metavar="L", help="rate points (entropy.lmbda); default: the "
                   "config's own; >= 3 give BD-rate / BD-PSNR")
    p.add_argument("--lambda-for", action="append", nargs="+", default=None,
                   metavar="METHOD L", help="one method's rate points in place of --lambda "
                   "(METHOD as for --only; repeat per method): where the curves meet, without "
                   "training every method at every lambda, e.g. --lambda-for HAC 0.008 0.004 "
                   "0.002 0.001")
    p.add_argument("--untimed", action="append", nargs=2, default=None, metavar=("RUN", "WHY"),
                   help="mark a finished run (its folder name under --out's runs/) whose training "
                   "time is no measurement for a reason its record cannot show, e.g. a pause of "
                   "a run trained before the stall time was kept: the report leaves it out of "
                   "training-time ratios and says WHY; kept in its record (archives too); an "
                   "empty WHY removes the mark")
    p.add_argument("--paired-fps", action="store_true",
                   help="time each contender's decoded file against the baseline's in one process "
                        "(middle rate point, lowest seed, 3 rounds, 1 thread) for the verdict's "
                        "FPS ratio; FPS of runs measured at different times make no ratio")
    p.add_argument("--panel-views", type=int, nargs="*", default=None, metavar="V",
                   help="test views (indices) drawn in the report's panels: ground truth, each "
                        "method's decoded render, error map and bit map (default: 0; none "
                        "with an empty list)")
    p.add_argument("--seeds", type=int, nargs="+", default=None, metavar="S",
                   help="train every rate point once per seed (train.seed): the report gives "
                        "each point's seed mean and spread and BD-rate per seed and on the "
                        "seed-mean curves (two seeds or more for any rate-distortion claim)")
    p.add_argument("--out", default="runs/compare", help="comparison folder (runs/, report.md, "
                   "results.json, plots); rerun to resume")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a folder holding another output of pgs (a comparison of another scene)")
    p.add_argument("--lpips-weights", default=None, help=LPIPS_HELP)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--only", action="append", default=None, metavar="METHOD",
                   help="bring only this method's runs to the end and report them (repeat; "
                   "'baseline' (shown as HAC), a --vs value, or its name in the report, e.g. "
                   "Predict-GS): split a comparison across processes sharing --out, then rerun "
                   "without it for the full report")
    p.add_argument("--report-only", action="store_true",
                   help="train and measure nothing: report the finished runs (archived records "
                        "included) and list the missing ones")
    p.add_argument("--remeasure", action="store_true",
                   help="redo encode and decode+eval of trained runs (retake times and FPS)")
    p.add_argument("--jobs", type=_positive_int, default=1, metavar="N",
                   help="runs trained at a time, each in its own process pinned to its share "
                        "of the cores (2 on a 2-core machine: one run per core, one thread "
                        "each); the report follows when all are done")
    p.add_argument("--reference", metavar="P1[+P2...]", default=None,
                   help="an uncompressed run on the same protocol to measure every run against "
                        "(e.g. 'scaffold'): PSNR change and 'x smaller' than its float32 model; "
                        "'--only reference' trains just it")
    p.add_argument("--codec", metavar="PATCH", default=None,
                   help="a patch of [codec] settings applied when encoding every run, training "
                        "unchanged (e.g. compact-codec: lossless, smaller files; runs recorded "
                        "with other settings are encoded and measured again)")
    p.add_argument("--archive", metavar="DIR", default=None,
                   help="afterwards, copy the records of the finished runs this report shows (and its "
                        "reference) and the report to DIR "
                        "(no checkpoints or model files; copy them back into an --out folder "
                        "to report those runs without retraining)")
    _config_args(p)
    p.set_defaults(fn=cmd_compare)

    p = sub.add_parser("benchmark", help="one comparison per scene of a dataset (on this machine "
                       "or a Ray cluster) and the dataset's tables")
    p.add_argument("root", help="folder holding the scene folders")
    p.add_argument("--scenes", default=None, help="comma-separated scene names (default: all)")
    p.add_argument("--protocol", default=None,
                   choices=["mip360", "tandt", "deepblending", "nerf-synthetic"],
                   help="the dataset's HAC protocol patch")
    p.add_argument("--vs", action="append", default=[], metavar="P1[+P2...]", help="a contender: patches joined by '+'; repeat")
    p.add_argument("--lambda", dest="lambdas", type=float, nargs="+", default=None, metavar="L", help="rate points (entropy.lmbda)")
    p.add_argument("--seeds", type=int, nargs="+", default=None, metavar="S", help="train every rate point once per seed")
    p.add_argument("--out", required=True, help="benchmark folder (on Ray: a path every node sees)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a folder holding another output of pgs")
    p.add_argument("--executor", default="local", choices=["local", "ray"], help="where runs execute (default local)")
    p.add_argument("--jobs", type=int, default=1,
                   help="local: runs at a time, each in its own process with its share of the cores")
    p.add_argument("--address", default=None,
                   help="ray: the cluster ('auto' or HOST:PORT); default: a local Ray for this call")
    p.add_argument("--cpus-per-run", type=int, default=1, help="ray: CPUs each run asks for")
    p.add_argument("--gpus-per-run", type=float, default=0,
                   help="ray: GPUs each run asks for (1 on a GPU cluster)")
    p.add_argument("--retries", type=int, default=2, help="attempts after a failure, per run")
    p.add_argument("--lpips-weights", default=None, help=LPIPS_HELP)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    _config_args(p)
    p.set_defaults(fn=cmd_benchmark)

    p = sub.add_parser("warmup", help="compile the CPU kernels into numba's disk cache (run.sh "
                       "does it at set-up; otherwise the first training compiles them)")
    p.set_defaults(fn=cmd_warmup)

    p = sub.add_parser("demo", help="the main job: HAC vs Predict-GS on the embedded scene, three "
                       "rate points trained in parallel, a verdict at the end")
    p.add_argument("--out", default="runs/demo", help="demo folder (default runs/demo)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a folder holding another output of pgs")
    p.add_argument("--patch", action="append", default=[], help="extra patches for every run")
    p.add_argument("--vs", action="append", default=[],
                   help="contenders (default: the installed methods whose spec is marked for the "
                        "demo; `pgs config --list` lists the methods)")
    p.add_argument("--lambda", dest="lambdas", type=float, nargs="+", default=None,
                   help="rate points (default 0.004 0.002 0.001: three, for a BD-rate)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one config value for every run")
    p.add_argument("--reference", default="scaffold", metavar="P1[+P2...]",
                   help="the uncompressed run every method is measured against (default "
                        "scaffold; 'none' for none)")
    p.set_defaults(fn=cmd_demo)
