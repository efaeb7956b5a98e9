"""Commands on ``.pgs`` files and their decoded models: ``render``, ``view``, ``encode``,
``decode``, ``info``, ``export-ply``."""
from __future__ import annotations

import time
from pathlib import Path

from baseline.cli.common import DEVICE_HELP, LPIPS_HELP, _lpips_weights


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
    try:                         # the URL is printed inside: a stop right after it is a stop
        signal.signal(signal.SIGTERM, stop)
        print(f"viewer of {args.target}: {v.url} (training cameras grey, test cameras orange; "
              f"Ctrl+C to stop)", flush=True)
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
    from baseline.run import decode_run

    decode_run(args.file, args.output or Path(args.file).with_suffix(""), scene=args.scene,
               render=args.render, device=args.device, sh_degree=args.sh_degree,
               overwrite=args.overwrite)
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


def cmd_export_ply(args) -> int:
    from baseline.eval.export import export_run_ply, export_sh_ply, format_sh_export
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
    print(format_sh_export(export_sh_ply(trainer.model, scene, out, coded=coded,
                                         sh_degree=args.sh_degree,
                                         backend=trainer.cfg.train.rasterizer,
                                         source=str(args.run))))
    return 0


def add_parsers(sub) -> None:
    """This group's subcommands, in the order `pgs --help` lists them."""
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
