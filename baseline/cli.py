"""The ``pgs`` command line."""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path


DEVICE_HELP = "where to render: auto | cpu | cuda | cuda:N (default: the run's train.device)"


def _config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--patch", action="append", default=[], metavar="NAME",
                   help="config patch: a shipped one by name (`pgs config --list` shows them by kind) "
                        "or a .toml path; repeat to apply in order")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one config value (after the patches)")
    p.add_argument("-r", "--resolution", type=int, default=None,
                   help="downscale factor (1, 2, 4, 8); default: original size capped at 1600 px")
    p.add_argument("--images", default=None, help="image folder (e.g. images_8)")
    p.add_argument("--iterations", type=int, default=None, help="shortcut for --set train.iterations=N")
    p.add_argument("--device", default=None,
                   help="auto | cpu | cuda | cuda:N: shortcut for --set train.device=...")


def _config_sets(args) -> list:
    """``--set`` overrides followed by the shortcut options' (-r, --images, --iterations,
    --device)."""
    sets = list(args.set)
    if getattr(args, "resolution", None) is not None:
        sets.append(f"data.resolution={args.resolution}")
    if getattr(args, "images", None):
        sets.append(f'data.images="{args.images}"')
    if getattr(args, "iterations", None) is not None:
        sets.append(f"train.iterations={args.iterations}")
    if getattr(args, "device", None):
        sets.append(f'train.device="{args.device}"')
    if getattr(args, "tensorboard", False):
        sets.append("train.tensorboard=true")
    return sets


def _build_cfg(args):
    from baseline.config import build_config

    return build_config(args.patch, _config_sets(args))


def cmd_config(args) -> int:
    from baseline.config import format_patch_list, to_toml

    print(format_patch_list() if args.list else to_toml(_build_cfg(args)))
    return 0


def cmd_make_scene(args) -> int:
    from baseline.data.synthetic import make_scene

    make_scene(args.out, n_views=args.views, width=args.width, height=args.height, seed=args.seed,
               texture_detail=args.detail, overwrite=args.overwrite)
    print(f"wrote synthetic scene to {args.out}")
    return 0


def cmd_train(args) -> int:
    from baseline.run import prepare_run_folder, train_run

    cfg = _build_cfg(args)
    prepare_run_folder(args.scene, args.out, resume=args.resume, overwrite=args.overwrite)
    res = train_run(args.scene, args.out, cfg, resume=args.resume,
                    progress=not args.no_progress)
    _print_results(res)
    return 0


def _print_results(res: dict) -> None:
    t = res.get("test", {})
    from baseline.eval.metrics import format_psnr
    from baseline.eval.report import stalled

    stall = (f", {res['stall_s']:.1f} s of it stalled: paused or sharing its core"
             if stalled(res) else "")
    print(f"iterations {res['iterations']}  train {res['train_time_s']:.1f} s "
          f"({res['s_per_it']:.3f} s/it, {res['threads']} threads on {res.get('machine', '-')}"
          f"{stall})  anchors {res['anchors']}")
    if t:
        lp = "unavailable" if t.get("lpips") is None else f"{t['lpips']:.4f}"
        print(f"test: PSNR {format_psnr(t['psnr'], 3)}  SSIM {t['ssim']:.4f}  LPIPS {lp}  "
              f"FPS {t['fps']:.1f}  Gaussians/view {t['gaussians_mean']:.0f}")


def cmd_eval(args) -> int:
    from baseline.eval.evaluate import method_key
    from baseline.eval.metrics import load_lpips
    from baseline.guard import check_output, write_marker
    from baseline.run import Renderable, write_json_atomic

    target = Path(args.target)
    out_dir = target if target.is_dir() else target.with_suffix("")
    path = (target / "results.json") if target.is_dir() else target.with_suffix(".results.json")
    views = out_dir / args.split
    if not target.is_dir():          # beside a .pgs file: in decode's folder, its own record
        check_output(out_dir, command="eval", source=target, folder=True, shares=("decode",))
        check_output(path, command="eval", source=target, own=_is_eval_record)
    check_output(views, command="eval", source=target, folder=True, shares=("decode",))
    r = Renderable(args.target, args.scene, device=args.device)
    lpips_fn, reason = load_lpips(_lpips_weights(args))
    if lpips_fn is None:
        print(reason, file=sys.stderr)          # stdout stays one JSON document
    if not target.is_dir() and not out_dir.exists():
        write_marker(out_dir, "eval", target)
    folder = views / method_key(r.iterations)
    res = r.evaluate(args.split, render_dir=folder, lpips_fn=lpips_fn)
    write_marker(views, "eval", target)
    res["phase"] = r.phase
    res["views"] = str(folder)
    if r.phase == "decoded":
        res["bytes"] = target.stat().st_size
        res["decode_s"] = r.decoded.decode_s
    print(json.dumps(res, indent=2))
    full = _read_record(path) if path.exists() else {}
    full[args.split] = res
    write_json_atomic(path, full)
    return 0


def _read_record(path: Path) -> dict:
    """A JSON record of the toolkit's (read bounded; not an object: an error naming it)."""
    from baseline.fileio import read_json_bounded

    rec = read_json_bounded(path, "a pgs record")
    if not isinstance(rec, dict):
        raise ValueError(f"{path}: not a JSON object, not a pgs record")  # noqa: TRY004
    return rec


def _is_eval_record(path: Path) -> bool:
    """``FILE.results.json`` as ``pgs eval FILE.pgs`` writes it: one entry per split."""
    try:
        rec = _read_record(path)
    except ValueError:
        return False
    return bool(rec) and set(rec) <= {"test", "train"} and all(
        isinstance(v, dict) and v.get("phase") == "decoded" for v in rec.values())


def cmd_quant_cost(args) -> int:
    from baseline.eval.quantcost import format_rows, quantization_cost
    from baseline.guard import check_output
    from baseline.run import load_run, write_json_atomic

    check_output(Path(args.run) / "quant_cost.json", command="quant-cost", source=args.run)
    trainer, scene = load_run(args.run, device=args.device)
    cams = scene.test_cameras if args.split == "test" else scene.train_cameras
    rows = quantization_cost(trainer, scene, cams or scene.train_cameras, seed=args.seed)
    print(f"{args.run}: {len(cams or scene.train_cameras)} {args.split} views")
    print(format_rows(rows))
    write_json_atomic(Path(args.run) / "quant_cost.json", {"split": args.split, "rows": rows})
    return 0


def cmd_census(args) -> int:
    from baseline.eval.census import census_of, format_census
    from baseline.guard import check_output
    from baseline.run import write_json_atomic

    labels = [Path(t).name for t in args.targets]

    def own(path):                 # the census of these targets, written before
        try:
            rec = _read_record(path)
        except ValueError:
            return False
        return set(rec) == {"census"} and [r.get("label") for r in rec["census"]] == labels

    if args.json:
        check_output(args.json, command="census", source={"targets": labels},
                     overwrite=args.overwrite, own=own)
    res = []
    for t in args.targets:
        r = census_of(t, thresholds=args.thresholds, device=args.device)
        r["label"] = Path(t).name
        res.append(r)
    print(format_census(res))
    if args.json:
        write_json_atomic(Path(args.json), {"census": res})
    return 0


def cmd_curves(args) -> int:
    from baseline.eval.report.curves import format_curves

    print(format_curves(args.runs, windows=args.windows))
    return 0


def cmd_render(args) -> int:
    from baseline.eval.metrics import format_psnr, load_lpips
    from baseline.guard import check_output, write_marker
    from baseline.run import Renderable

    out = Path(args.output)
    check_output(out, command="render", source=args.target, folder=True,
                 overwrite=args.overwrite)
    r = Renderable(args.target, args.scene, device=args.device)
    write_marker(out, "render", args.target)
    lpips_fn, _ = load_lpips(_lpips_weights(args))
    res = r.evaluate(args.split, render_dir=out, lpips_fn=lpips_fn)
    print(f"rendered {res['n_views']} {args.split} views to {out / 'renders'} (ground truth in "
          f"{out / 'gt'}, metrics per view in {out / 'per_view.json'}; PSNR "
          f"{format_psnr(res['psnr'], 3)}, SSIM {res['ssim']:.4f}, FPS {res['fps']:.1f})")
    return 0


def cmd_view(args) -> int:
    """A web viewer of the decoded model: every frame rendered by the toolkit for the
    browser's camera (baseline/viewer.py)."""
    import signal

    from baseline.viewer import serve

    def stop(*_):
        raise KeyboardInterrupt

    v = serve(args.target, scene=args.scene, host=args.host, port=args.port, device=args.device)
    # a service manager's stop is Ctrl+C's (set after the scene is read: pycolmap's logging
    # installs a SIGTERM handler of its own when it loads)
    signal.signal(signal.SIGTERM, stop)
    print(f"viewer of {args.target}: {v.url} (training cameras grey, test cameras orange; "
          f"Ctrl+C to stop)", flush=True)
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        v.stop()
        print("viewer stopped")
        return 0


def cmd_encode(args) -> int:
    from baseline.modelfile import file_info, format_info, format_rate_check, rate_check
    from baseline.run import encode_run

    codec = {"weight_dtype": args.weights, "positions": args.positions, "masks": args.masks,
             "grids": args.grids}
    st, trainer = encode_run(args.run, args.output, overwrite=args.overwrite, codec=codec)
    if trainer.phase != "adaptive":
        print(f"note: {args.run} stopped before the entropy model was trained (phase "
              f"'{trainer.phase}'); the file is coded with an untrained context model")
    print(format_info(file_info(args.output)))
    print(f"wrote {args.output}: {st['bytes']} bytes ({st['bytes'] / 2**20:.4f} MB), "
          f"{st['anchors']} anchors, encode {st['encode_s']:.2f} s")
    if args.rate_check:
        print(format_rate_check(rate_check(trainer.model, trainer.entropy, st)))
    return 0


def cmd_decode(args) -> int:
    import shutil

    import torch

    from baseline.modelfile import decode_model
    from baseline.contracts import feature_cache
    from baseline.eval.export import export_run_ply, export_sh_ply
    from baseline.eval.metrics import format_psnr
    from baseline.guard import check_output, write_marker
    from baseline.run import Renderable, write_json_atomic

    out = Path(args.output or Path(args.file).with_suffix(""))

    def own(folder):             # written before folders were marked: its record names the file
        try:
            rec = _read_record(folder / "results.json")
        except ValueError:
            return False
        return "ply" in rec and isinstance(rec.get("file"), str) and \
            Path(rec["file"]).resolve() == Path(args.file).resolve()

    # never a run's folder, never inside a scene, never a folder of the user's files
    check_output(out, command="decode", source=args.file, folder=True, overwrite=args.overwrite,
                 own=own, shares=("eval",))
    dec = decode_model(args.file)          # nothing is written unless the file decodes
    print(f"decoded {args.file}: {dec.model.n_anchors} anchors in {dec.decode_s:.2f} s")
    res = {"file": str(args.file), "bytes": Path(args.file).stat().st_size, "decode_s": dec.decode_s,
           "anchors": dec.model.n_anchors}
    created = not out.exists()
    try:
        out.mkdir(parents=True, exist_ok=True)
        write_marker(out, "decode", args.file)
        center = dec.header.get("view_center")
        r = None
        if args.render != "none" or center is None:
            r = Renderable(args.file, args.scene, device=args.device, decoded=dec)
        if args.render != "none":
            from baseline.eval.evaluate import method_key
            from baseline.eval.metrics import default_lpips

            res[args.render] = r.evaluate(
                args.render, render_dir=out / args.render / method_key(r.iterations),
                lpips_fn=default_lpips()[0])
            t = res[args.render]
            print(f"{args.render}: PSNR {format_psnr(t['psnr'], 3)}  SSIM {t['ssim']:.4f}  "
                  f"FPS {t['fps']:.1f}")
            prov = feature_cache(r.model)
            if prov is not None:             # Predict-GS: FPS without the decoded-model f_c cache
                prov.clear_cache()
                r.model.unbake()             # (a bake holds f_c's first-layer terms)
                nc = r.evaluate(args.render)
                prov.build_cache(r.model.xyz)
                r.model.bake_if_faster()
                t["fps_no_cache"] = nc["fps"]
                print(f"FPS without the f_c cache {nc['fps']:.1f} (with {t['fps']:.1f})")
        model = r.model if r is not None else dec.model
        model.to("cpu")
        ply = out / "point_cloud.ply"
        scene = r.scene if r is not None else _scene_of(dec, args.scene)
        if scene is not None and r is None:        # (Renderable checked its own)
            from baseline.data.scene import scene_bounds
            from baseline.scaffold.model import check_bounds

            check_bounds(model, str(args.file), *scene_bounds(scene))
        if scene is not None and scene.train_cameras:
            model.unbake()
            res["ply"] = export_sh_ply(model, scene, ply, sh_degree=args.sh_degree,
                                       source=str(args.file))
            _print_ply(res["ply"])
        else:
            n = export_run_ply(model, None, ply,
                               center=None if center is None else torch.tensor(center))
            res["ply"] = {"path": str(ply), "gaussians": n, "sh_degree": 0,
                          "note": "scene not here: one viewpoint's Gaussians, degree-0 colours"}
            print(f"wrote {n} Gaussians to {ply}: the scene {dec.scene_path} is not here, so "
                  f"these are the Gaussians seen from the mean training camera with degree-0 "
                  f"colours (pass --scene PATH for the view-union export with SH colours)")
        write_json_atomic(out / "results.json", res)
    except BaseException:
        if created:                          # a failed decode leaves nothing behind
            shutil.rmtree(out, ignore_errors=True)
        raise
    return 0


def cmd_info(args) -> int:
    from baseline.modelfile import file_info, format_info

    info = file_info(args.file)
    h = info["header"]
    print(f"{args.file}: {info['total_bytes']} bytes, {info['n_anchors']} anchors x "
          f"{h.get('n_offsets', '?')} Gaussians; positions {h['position_coding']}, masks "
          f"{h['mask_coding']}, grids {h['grid_coding']}, network weights "
          f"{h.get('weight_dtype', 'float32')}")
    print(format_info(info))
    return 0


def _scene_of(dec, scene_override):
    """The scene of a decoded file when it is here (for the view-union PLY), else None."""
    from baseline.run import load_scene_for

    path = scene_override or dec.scene_path
    if not path or not Path(path).exists():
        return None
    return load_scene_for(dec.cfg, path, progress=False)


def _print_ply(r: dict) -> None:
    from baseline.eval.metrics import format_psnr

    print(f"wrote {r['gaussians']} Gaussians to {r['path']} (the union over the training views "
          f"of those drawn, {r['drawn_per_view']:.0f} per view; SH degree {r['sh_degree']}); "
          f"fidelity on {r['views']} test views: {format_psnr(r['psnr_vs_model'])} against the "
          f"model's render, {format_psnr(r['psnr_ply'])} against the ground truth (model "
          f"{format_psnr(r['psnr_model'])})")


def cmd_export_ply(args) -> int:
    from baseline.eval.export import export_run_ply, export_sh_ply
    from baseline.guard import check_output
    from baseline.run import coded_state, load_run

    out = args.output or str(Path(args.run) / "point_cloud.ply")

    def own(path):                # a PLY this command exported from the same run
        from baseline.fileio import open_checked

        f, _, _ = open_checked(path, "a PLY file")
        with f:
            head = f.read(4096)
        return head.startswith(b"ply\n") and f"comment pgs export of {args.run}:".encode() in head

    check_output(out, command="export-ply", source=args.run, overwrite=args.overwrite, own=own)
    trainer, scene = load_run(args.run, device="cpu")
    # in the adaptive phase: what the codec would store (quantized values, 16-bit positions)
    coded = coded_state(trainer)
    if coded is None:
        n = export_run_ply(trainer.model, scene.train_cameras, out)
        print(f"wrote {n} Gaussians to {out} (a run before HAC's coding: one viewpoint's "
              f"Gaussians, degree-0 colours)")
        return 0
    _print_ply(export_sh_ply(trainer.model, scene, out, coded=coded, sh_degree=args.sh_degree,
                             backend=trainer.cfg.train.rasterizer, source=str(args.run)))
    return 0


def cmd_bench(args) -> int:
    if args.what == "raster":
        from baseline.render.bench import format_raster_bench, run_raster_bench

        rows = run_raster_bench(threads=args.threads)
        print(format_raster_bench(rows))
    elif args.what == "codec":
        from baseline.codec.bench import format_codec_bench, run_codec_bench, run_model_codec_bench

        rows = []
        for model in (args.model or ["hac", "hacpp"]):
            rows += run_codec_bench(n_anchors=args.anchors or 500_000, model=model,
                                    threads=args.threads or 0)
        rows += [run_model_codec_bench(r) for r in args.run]
        print(format_codec_bench(rows))
    elif args.what == "grid":
        from baseline.hac.bench import format_grid_bench, run_grid_bench

        print(format_grid_bench(run_grid_bench(args.anchors or 100_000, threads=args.threads)))
    elif args.what == "fps":
        from baseline.eval.fpsbench import bench_files, format_fps_bench

        rounds = 5 if args.rounds is None else args.rounds
        print(format_fps_bench(bench_files(args.run, scene=args.scene, rounds=rounds,
                                           threads=args.threads, device=args.device,
                                           max_views=args.views)))
    elif args.what == "train":
        from baseline.train.bench import format_train_bench, run_train_bench

        print(format_train_bench(run_train_bench(args.run, steps=args.steps,
                                                 threads=args.threads or 1,
                                                 anchors=args.anchors, methods=args.vs,
                                                 clock=args.clock)))
    elif args.what == "frame":
        from baseline.eval.fpsbench import bench_frame_files, format_frame_bench

        rounds = 3 if args.rounds is None else args.rounds
        print(format_frame_bench(bench_frame_files(args.run, scene=args.scene, rounds=rounds,
                                                   threads=args.threads, device=args.device,
                                                   max_views=args.views)))
    return 0


def cmd_compare(args) -> int:
    """Side by side: the baseline and each --vs method at each lambda; report + plots."""
    from baseline.eval.compare import run_compare

    sets = _config_sets(args)
    if args.archive:                   # checked now, not after hours of training
        from baseline.eval.compare import is_compare_folder
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
                              overwrite=args.overwrite)
    except KeyboardInterrupt:
        print(f"\ninterrupted: finished stages are kept in {args.out}; run the same command "
              f"again to resume", file=sys.stderr)
        return 130
    if args.archive:
        from baseline.eval.compare import archive_records

        kept = archive_records(args.out, args.archive, results, overwrite=args.overwrite)
        print(f"archived the records of {len(kept)} finished run(s) and the report to {args.archive}")
    return 0


def cmd_benchmark(args) -> int:
    """One comparison per scene of a dataset, on an executor; the dataset's report."""
    from baseline.eval.benchmark import run_benchmark

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
DEMO_SCOPE = ("These figures are the embedded synthetic scene's (1k iterations, one seed): a "
              "check that the pipelines run and a picture of the comparison, not a claim about "
              "real scenes (docs/RESULTS.md has those).")


def cmd_demo(args) -> int:
    """The main job on the embedded default scene: HAC vs Predict-GS at three rate points, side
    by side. The runs train in parallel, one per core (the local executor); the report ends in
    a verdict (BD-rate, equal-lambda changes, paired FPS and training-time ratios)."""
    from baseline.data.synthetic import make_scene
    from baseline.eval.compare import (
        parse_methods,
        parse_reference,
        plan_runs,
        run_compare,
    )
    from baseline.eval.executors import Job, LocalExecutor
    from baseline.guard import check_output, write_marker
    from baseline.train.trainer import available_cores

    from baseline.eval.metrics import find_lpips_weights

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
    methods = parse_methods(args.vs or ["predict-gs"])
    ref = None if args.reference == "none" else args.reference
    jobs = [Job(scene=str(scene.resolve()), out=str(out.resolve()), method=s.method.name,
                method_patches=tuple(s.method.patches), lmbda=s.lmbda, seed=None,
                common_patches=tuple(common), sets=tuple(args.set), label=s.label,
                lpips_weights=lpips)
            for s in plan_runs(out, methods, lambdas, common, args.set)]
    jobs.sort(key=lambda j: j.method == "baseline")          # the longer trainings first
    if ref is not None:
        m = parse_reference(ref)
        jobs.append(Job(scene=str(scene.resolve()), out=str(out.resolve()), method=m.name,
                        method_patches=tuple(m.patches), lmbda=None, seed=None,
                        common_patches=tuple(common), sets=tuple(args.set),
                        label=f"reference {m.name}", reference=True))
    n = max(1, min(available_cores(), len(jobs)))
    print(f"demo: {len(jobs)} run(s) on {n} core(s), one per core")
    try:
        res = LocalExecutor(jobs=n, progress=True).execute(jobs)
        if res["failed"]:
            for label, err in res["failed"]:
                print(f"demo: {label} failed: {err}", file=sys.stderr)
            return 1
        run_compare(str(scene), out, vs=args.vs or ["predict-gs"], lambdas=lambdas,
                    common_patches=common, sets=args.set, progress=False, plots=True,
                    reference=ref, paired_fps=True, scope=DEMO_SCOPE, lpips_weights=lpips,
                    done_before={r["run_dir"]: r["stages_run"] for r in res["done"]})
    except KeyboardInterrupt:
        print("\ninterrupted: run ./run.sh demo again to resume", file=sys.stderr)
        return 130
    print(f"demo wall time {time.perf_counter() - t0:.1f} s; report in {out / 'report.md'}")
    return 0


def _version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        v = version("predict-gs-toolkit")
    except PackageNotFoundError:     # run from a source tree without installing
        v = "unknown (not installed)"
    from baseline.config import TRAINING_SEMANTICS

    return f"{v} (training semantics {TRAINING_SEMANTICS})"


SCENE_HELP = ("scene folder: COLMAP (sparse/0 + images/ or images_N/) or Blender / instant-ngp "
              "(transforms*.json)")
LPIPS_HELP = ("LPIPS (VGG) weights: LIN.pth,VGG16.pth - the lpips package's weights/v0.1/vgg.pth "
              "and torchvision's vgg16-397923af.pth - or one file holding both (README); found "
              "on their own when both are installed, never downloaded; else LPIPS is unavailable")


def _lpips_weights(args):
    """``--lpips-weights``, else the lpips package's and torchvision's files when both are on
    this machine already (:func:`baseline.eval.metrics.find_lpips_weights`; never downloaded)."""
    from baseline.eval.metrics import find_lpips_weights

    return args.lpips_weights or find_lpips_weights()


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{v} must be at least 1")
    return v


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="pgs", description="anchor-based 3DGS compression toolkit: "
                                 "HAC, HAC++ and Predict-GS side by side")
    ap.add_argument("--version", action="version", version=f"pgs {_version()}")
    sub = ap.add_subparsers(dest="cmd", required=True)

    p = sub.add_parser("config", help="print the merged config, or the shipped patches (--list)")
    _config_args(p)
    p.add_argument("--list", action="store_true",
                   help="list the shipped patches grouped by kind, with their descriptions")
    p.set_defaults(fn=cmd_config)

    p = sub.add_parser("make-scene", help="write the procedural synthetic scene (COLMAP format)")
    p.add_argument("out", help="folder to write the scene to (COLMAP layout)")
    p.add_argument("--views", type=_positive_int, default=40, help="camera views (every 8th is a test view)")
    p.add_argument("--width", type=_positive_int, default=160, help="image width in pixels")
    p.add_argument("--height", type=_positive_int, default=120, help="image height in pixels")
    p.add_argument("--seed", type=int, default=0, help="scene seed (the same seed writes the same bytes)")
    p.add_argument("--detail", type=float, default=1.0,
                   help="texture detail, 0 to 16; 0 = flat colours")
    p.add_argument("--overwrite", action="store_true",
                   help="replace a scene that pgs make-scene wrote with other arguments")
    p.set_defaults(fn=cmd_make_scene)

    p = sub.add_parser("train", help="train a model on a scene")
    p.add_argument("scene", help=SCENE_HELP)
    p.add_argument("--out", required=True, help="run folder (config, checkpoint, results)")
    p.add_argument("--resume", action="store_true", help="continue from the run's checkpoint "
                   "(the same scene and training configuration, checked)")
    p.add_argument("--overwrite", action="store_true",
                   help="start over in a folder that holds a run (its records are removed)")
    p.add_argument("--no-progress", action="store_true",
                   help="no progress bars (follow OUT/train_log.jsonl instead)")
    p.add_argument("--tensorboard", action="store_true",
                   help="also log loss, PSNR, bits per anchor, anchors, Gaussians and learning "
                        "rates to TensorBoard in OUT/tb/ (train.tensorboard; needs the "
                        "tensorboard package: pip install -e .[tensorboard])")
    _config_args(p)
    p.set_defaults(fn=cmd_train)

    p = sub.add_parser("eval", help="evaluate a run folder or a .pgs file on the test views")
    p.add_argument("target", help="run folder or .pgs file")
    p.add_argument("--split", choices=["test", "train"], default="test", help="the views to use (default test)")
    p.add_argument("--scene", default=None, help="scene path (default: the one recorded)")
    p.add_argument("--lpips-weights", default=None, help=LPIPS_HELP)
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.set_defaults(fn=cmd_eval)

    p = sub.add_parser("census", help="where the rendered Gaussians come from: kept share with "
                       "the refiner's corrections on and off, neighbours' patterns, initial vs grown "
                       "anchors, PSNR as the opacity threshold rises")
    p.add_argument("targets", nargs="+", help="run folders (trained into the adaptive phase) or "
                   ".pgs files; from the second on, also the PSNR each keeps when cut to the "
                   "first one's Gaussians per view")
    p.add_argument("--thresholds", type=float, nargs="+", default=None,
                   help="opacity thresholds of the sweep (default 0 0.005 0.01 0.02 0.05 0.1 0.2 0.3)")
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    p.add_argument("--overwrite", action="store_true",
                   help="let --json replace an existing file")
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.set_defaults(fn=cmd_census)

    p = sub.add_parser("curves", help="where in its schedule a run falls behind another: mean "
                       "training L1 per span of the schedule and the rate's bits per anchor, "
                       "from the runs' training logs")
    p.add_argument("runs", nargs="+", help="run folders; from the second on, changes vs the first")
    p.add_argument("--windows", type=int, default=6, help="equal spans of the schedule (default 6)")
    p.set_defaults(fn=cmd_curves)

    p = sub.add_parser("quant-cost", help="PSNR of a trained run with each coded attribute raw, "
                       "rounded (as coded) or noised (as HAC trains): where its quantization loss comes from")
    p.add_argument("run", help="run folder (trained into HAC's adaptive phase)")
    p.add_argument("--split", choices=["test", "train"], default="test", help="the views to use (default test)")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise draws")
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.set_defaults(fn=cmd_quant_cost)

    p = sub.add_parser("render", help="render the views of a run folder or a .pgs file: "
                       "DIR/renders, DIR/gt (PNG) and DIR/per_view.json, as 3DGS lays them out")
    p.add_argument("target", help="run folder or .pgs file")
    p.add_argument("-o", "--output", required=True, help="folder for renders/, gt/ and per_view.json")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a folder holding another output of pgs")
    p.add_argument("--lpips-weights", default=None, help=LPIPS_HELP)
    p.add_argument("--split", choices=["test", "train"], default="test", help="the views to use (default test)")
    p.add_argument("--scene", default=None, help="scene path (default: the one recorded)")
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.set_defaults(fn=cmd_render)

    p = sub.add_parser("view", help="a web viewer of a decoded model (or a run): the browser's "
                       "camera rendered by the toolkit, the training and test cameras as "
                       "frustums (needs the viewer extra)")
    p.add_argument("target", help=".pgs file or run folder")
    p.add_argument("--scene", default=None, help="scene path (default: the one recorded)")
    p.add_argument("--port", type=int, default=8080, help="port (default 8080)")
    p.add_argument("--host", default="0.0.0.0",
                   help="address to listen on (default 0.0.0.0: every interface; 127.0.0.1: "
                        "this machine only)")
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.set_defaults(fn=cmd_view)

    p = sub.add_parser("encode", help="compress a trained run into one .pgs file")
    p.add_argument("run", help="run folder (trained)")
    p.add_argument("-o", "--output", required=True, help="the .pgs file to write")
    p.add_argument("--overwrite", action="store_true",
                   help="allow the output to replace an existing file or a run's record file "
                        "(never a scene's)")
    p.add_argument("--weights", choices=["float32", "float16"], default=None,
                   help="network weight precision in the file (default: the run's codec.weight_dtype)")
    p.add_argument("--positions", choices=["raw16", "sorted", "lattice"], default=None,
                   help="anchor positions: raw 16-bit (HAC), the same coded losslessly as a set "
                        "(sorted), or the exact voxel-lattice coordinates octree-coded (lattice, "
                        "HAC++'s kind of coding) (default: the run's codec.positions)")
    p.add_argument("--masks", choices=["bernoulli", "patterns"], default=None,
                   help="Gaussian masks: one global probability (HAC) or per-anchor patterns "
                        "(default: the run's codec.masks)")
    p.add_argument("--grids", choices=["all", "used"], default=None,
                   help="hash grids: every entry (HAC) or only those the anchors read "
                        "(default: the run's codec.grids)")
    p.add_argument("--rate-check", action="store_true",
                   help="print the training loss's bit estimate beside the bytes written, per section")
    p.set_defaults(fn=cmd_encode)

    p = sub.add_parser("decode", help="decode a .pgs file: OUT/point_cloud.ply (3DGS PLY) and "
                       "OUT/results.json; with --render also renders + metrics")
    p.add_argument("file", help=".pgs file")
    p.add_argument("-o", "--output", default=None, help="output folder (default: beside the file)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into a folder holding another output of pgs (its point_cloud.ply and results.json are replaced)")
    p.add_argument("--render", choices=["test", "train", "none"], default="none", help="also render these views and measure them")
    p.add_argument("--scene", default=None, help="scene path (default: the one the file records)")
    p.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], default=3,
                   help="degree of the PLY's fitted spherical-harmonic colours (default 3)")
    p.add_argument("--device", default=None, help=DEVICE_HELP + " (decoding itself: CPU)")
    p.set_defaults(fn=cmd_decode)

    p = sub.add_parser("info", help="per-section bit allocation of a .pgs file")
    p.add_argument("file", help=".pgs file")
    p.set_defaults(fn=cmd_info)

    p = sub.add_parser("export-ply", help="write the decoded neural Gaussians as a 3DGS PLY")
    p.add_argument("run", help="run folder (trained)")
    p.add_argument("-o", "--output", default=None, help="PLY file (default RUN/point_cloud.ply)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing file")
    p.add_argument("--sh-degree", type=int, choices=[0, 1, 2, 3], default=3,
                   help="degree of the fitted spherical-harmonic colours (default 3)")
    p.set_defaults(fn=cmd_export_ply)

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
    p.add_argument("--vs", action="append", default=[], help="contenders (default predict-gs)")
    p.add_argument("--lambda", dest="lambdas", type=float, nargs="+", default=None,
                   help="rate points (default 0.004 0.002 0.001: three, for a BD-rate)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                   help="override one config value for every run")
    p.add_argument("--reference", default="scaffold", metavar="P1[+P2...]",
                   help="the uncompressed run every method is measured against (default "
                        "scaffold; 'none' for none)")
    p.set_defaults(fn=cmd_demo)

    args = ap.parse_args(argv)
    from baseline import memory, registry
    from baseline.device import keep_freed_memory

    keep_freed_memory()          # trainings, decodes and renders reuse their freed blocks
    try:
        registry.ensure_loaded()
        return args.fn(args)
    except KeyboardInterrupt as e:     # TrainingStopped says where its checkpoint is
        print(f"pgs {args.cmd}: interrupted" + (f": {e}; run it again with --resume to continue"
                                               if str(e) else ""), file=sys.stderr)
        return 130
    except KeyError as e:          # a missing key: its name, not its repr
        print(f"pgs {args.cmd}: error: missing {e.args[0] if e.args else e}", file=sys.stderr)
        return 2
    except (ValueError, FileNotFoundError, OSError) as e:
        print(f"pgs {args.cmd}: error: {_one_line(e)}", file=sys.stderr)
        return 2
    except (MemoryError, RuntimeError) as e:
        if not memory.is_allocation_failure(e):
            return _internal_error(args, e)
        # an allocation no step named (AllocationError names its own)
        msg = str(e) if isinstance(e, memory.AllocationError) else memory.describe(
            f"in pgs {args.cmd}", e)
        print(f"pgs {args.cmd}: error: {_one_line(msg)}", file=sys.stderr)
        return 2
    except Exception as e:  # noqa: BLE001 - never a traceback to a user; say it is a bug
        return _internal_error(args, e)


def _internal_error(args, e: BaseException) -> int:
    print(f"pgs {args.cmd}: internal error ({type(e).__name__}: {_one_line(e)}); please "
          f"report it with the command that caused it", file=sys.stderr)
    return 2


def _one_line(e: BaseException) -> str:
    return " ".join(str(e).split())


if __name__ == "__main__":
    sys.exit(main())
