"""Commands on configs and runs: ``config``, ``make-scene``, ``train``, ``eval``, ``census``,
``curves``, ``quant-cost``."""
from __future__ import annotations

import json
import sys
from pathlib import Path

from baseline.cli.common import (_build_cfg, _config_args, DEVICE_HELP, _is_eval_record, LPIPS_HELP,
                                 _lpips_weights, _positive_int, _print_results, _read_record,
                                 SCENE_HELP)


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


def cmd_quant_cost(args) -> int:
    from baseline.eval.quantcost import (format_ablation, format_rows, quantization_cost,
                                         value_ablation)
    from baseline.guard import check_output
    from baseline.run import load_run, write_json_atomic

    # One file per split (test: quant_cost.json, train: quant_cost.train.json), so measuring
    # the training views never replaces the test views' figures.
    name = "quant_cost.json" if args.split == "test" else f"quant_cost.{args.split}.json"
    out_path = Path(args.run) / name
    check_output(out_path, command="quant-cost", source=args.run)
    trainer, scene = load_run(args.run, device=args.device)
    cams = scene.test_cameras if args.split == "test" else scene.train_cameras
    cams = cams or scene.train_cameras
    rows = quantization_cost(trainer, scene, cams, seed=args.seed)
    print(f"{args.run}: {len(cams)} {args.split} views")
    print(format_rows(rows))
    out = {"split": args.split, "rows": rows}
    if args.ablate:
        out["ablation"] = value_ablation(trainer, scene, cams, seed=args.seed)
        print()
        print(format_ablation(out["ablation"]))
    write_json_atomic(out_path, out)
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

    print(format_curves(args.runs, windows=args.windows, ends=args.at))
    return 0


def add_parsers(sub) -> None:
    """This group's subcommands, in the order `pgs --help` lists them."""
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
    p.add_argument("--windows", type=_positive_int, default=6,
                   help="equal spans of the schedule (default 6)")
    p.add_argument("--at", type=_positive_int, nargs="+", default=None, metavar="IT",
                   help="span ends in iterations instead of equal spans (e.g. the stage "
                        "switches: --at 1000 3000 5000 10000 15000)")
    p.set_defaults(fn=cmd_curves)

    p = sub.add_parser("quant-cost", help="PSNR of a trained run with each coded attribute raw, "
                       "rounded (as coded) or noised (as HAC trains): where its quantization loss comes from")
    p.add_argument("run", help="run folder (trained into HAC's adaptive phase)")
    p.add_argument("--split", choices=["test", "train"], default="test", help="the views to use (default test)")
    p.add_argument("--seed", type=int, default=0, help="seed of the noise draws (and of --ablate's shuffle)")
    p.add_argument("--ablate", action="store_true",
                   help="also what each attribute's coded values buy: the decoded model with one "
                        "attribute at the entropy model's mean, zero or shuffled among anchors, and "
                        "how much of the values the context mean predicts (R^2)")
    p.add_argument("--device", default=None, help=DEVICE_HELP)
    p.set_defaults(fn=cmd_quant_cost)
