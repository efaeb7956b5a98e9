"""The 3DGS compression survey's CSV files (one per dataset and method) and the per-run CSV."""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from baseline.config import patch_infos
from baseline.fileio import write_text_atomic
from baseline.eval.report.names import (field_ssim, label, method_names, ordered_runs, runs_of,
                                        seed_mean_points, seeds_of, ssim_convention)


SURVEY_COLUMNS = ["Submethod", "PSNR", "SSIM", "LPIPS", "Size [Bytes]", "#Gaussians"]
RUNS_COLUMNS = ["Method", "lambda", "seed", "PSNR", "SSIM", "SSIM convention", "SSIM (skimage)",
                "LPIPS", "Size [Bytes]", "#Gaussians"]


def survey_datasets() -> dict[str, str]:
    """The survey's dataset folders, by the dataset patch that trains on each (its ``survey``)."""
    return {n: i.survey for n, i in patch_infos().items() if i.kind == "dataset" and i.survey}


def gaussians_count(row: dict) -> Optional[int]:
    """The survey's #Gaussians of a run: the neural Gaussians its file codes (masks on: every
    one a decoded view can draw), read from the file; None for records kept without it."""
    m = row.get("masks_on") or {}
    return int(m["on"]) if "on" in m else None


def survey_dataset(results: dict) -> str:
    """The survey's dataset folder of a comparison: the dataset its protocol patch names
    (``tandt`` -> TanksAndTemples, ...), else the name of the folder its scene lies in."""
    datasets = survey_datasets()
    for pt in results.get("common_patches") or ():
        if pt in datasets:
            return datasets[pt]
    return Path(results.get("scene", "scenes")).parent.name or "scenes"


def _full(v) -> str:
    """A measurement at full precision (the survey rounds it when it takes it in)."""
    return "" if v is None else f"{v:.6f}"


def survey_rows(results: dict, method: str) -> list[dict]:
    """One method's rows in the 3DGS compression survey's CSV layout (``SURVEY_COLUMNS``): its
    rate points by lambda, highest rate first (the seed means in a comparison with seeds, a
    lambda once every seed has finished). The survey's naming rules: it shows at most two
    named submethods per method (unnamed rows only in its plots) and drops the method's name
    in front of a submethod name, so one point is named by the method alone, and of several the
    highest and lowest rate ``<method>-highrate`` and ``<method>-lowrate``, the others
    unnamed. SSIM: 3DGS's (empty where only scikit-image's was measured); LPIPS empty when
    not measured; #Gaussians: :func:`gaussians_count`."""
    name = label(results, method)
    seeded = bool(seeds_of(results))
    pts = []
    if seeded:
        for pt in seed_mean_points(results, method):
            rs = [r for r in runs_of(results, method) if r["lmbda"] == pt["lmbda"]]
            lp = [r.get("lpips") for r in rs]
            gs = [gaussians_count(r) for r in rs]
            pts.append({"lmbda": pt["lmbda"], "psnr": pt["psnr"],
                        "ssim": pt["ssim"] if pt.get("ssim_convention") == "3dgs" else None,
                        "lpips": None if None in lp else sum(lp) / len(lp),
                        "bytes": f"{pt['bytes']:.1f}" if pt["n"] > 1 else str(int(pt["bytes"])),
                        "gaussians": "" if None in gs else (f"{sum(gs) / len(gs):.1f}"
                                                            if len(gs) > 1 else str(gs[0]))})
    else:
        for r in runs_of(results, method):
            g = gaussians_count(r)
            pts.append({"lmbda": r["lmbda"], "psnr": r["psnr"], "ssim": field_ssim(r),
                        "lpips": r.get("lpips"), "bytes": str(int(r["bytes"])),
                        "gaussians": "" if g is None else str(g)})
    pts.sort(key=lambda p: p["lmbda"])
    rows = []
    for i, p in enumerate(pts):
        sub = (name if len(pts) == 1 else f"{name}-highrate" if i == 0
               else f"{name}-lowrate" if i == len(pts) - 1 else "")
        rows.append({"Submethod": sub, "PSNR": _full(p["psnr"]), "SSIM": _full(p["ssim"]),
                     "LPIPS": _full(p["lpips"]), "Size [Bytes]": p["bytes"],
                     "#Gaussians": p["gaussians"]})
    return rows


def _write_csv(rows: list[dict], columns: list[str], path) -> Path:
    import csv
    import io

    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    write_text_atomic(path, buf.getvalue())
    return Path(path)


def write_survey(results: dict, folder: str | Path, dataset: str | None = None,
                 scene: str | None = None) -> list[Path]:
    """The survey's files, one per method and scene: ``folder/<method>/<Dataset>/<scene>.csv``
    (each method's folder is laid out as the survey asks a method's ``results/`` to be;
    :func:`survey_rows`). ``dataset`` defaults to :func:`survey_dataset`, ``scene`` to the
    scene folder's name."""
    dataset = dataset or survey_dataset(results)
    scene = scene or Path(results.get("scene", "scene")).name
    out = []
    for m in method_names(results):
        rows = survey_rows(results, m)
        if rows:
            out.append(_write_csv(rows, SURVEY_COLUMNS,
                                  Path(folder) / label(results, m) / dataset / f"{scene}.csv"))
    return out


def runs_rows(results: dict) -> list[dict]:
    """Every run of the comparison, one row each (``RUNS_COLUMNS``, ``results.csv``): the
    method as the report names it, lambda, seed, and the decoded file's measurements, SSIM with
    its convention."""
    rows = []
    for r in ordered_runs(results):
        g = gaussians_count(r)
        rows.append({"Method": label(results, r["method"]), "lambda": f"{r['lmbda']:g}",
                     "seed": "" if r.get("seed") is None else str(r["seed"]),
                     "PSNR": _full(r["psnr"]), "SSIM": _full(r.get("ssim")),
                     "SSIM convention": ssim_convention(r),
                     "SSIM (skimage)": _full(r.get("ssim_skimage")),
                     "LPIPS": _full(r.get("lpips")), "Size [Bytes]": str(int(r["bytes"])),
                     "#Gaussians": "" if g is None else str(g)})
    return rows
