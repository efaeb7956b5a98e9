"""Comparison plots (matplotlib, Agg backend, PNG) drawn from stored comparison results.

* ``rd.png``    -- rate-distortion: decoded file size (MB) vs test PSNR (dB), one line per method;
* ``bits.png``  -- bit allocation: one stacked bar per method at each rate point, stacked by group;
* ``speed.png`` -- speed vs quality: render FPS vs PSNR (with / without the decoded-model cache)
  and training time vs PSNR (runs whose time is no measurement, :func:`report.untimed`,
  hollow and named).

Figures are built with ``matplotlib.figure.Figure`` + the Agg canvas, so no GUI backend or global
pyplot state is touched.
"""
from __future__ import annotations

from pathlib import Path

from baseline.eval.report.names import (GROUP_ORDER, MB, label, method_names, rate_points, runs_of,
                                        seed_mean_points, seeds_of)
from baseline.eval.report.timing import untimed
from baseline.fileio import atomic_path

GROUP_COLORS = {"feature": "#d62728", "anchor": "#1f77b4", "scaling": "#2ca02c",
                "offsets": "#ff7f0e", "masks": "#9467bd", "hash": "#8c564b", "mlps": "#7f7f7f",
                "header+framing": "#bcbd22"}
MARKERS = "osD^vP*Xh<>"


def _figure(w: float, h: float):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(w, h), dpi=110, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _style(results: dict) -> dict:
    import matplotlib

    cmap = matplotlib.colormaps["tab10"]
    return {m: (cmap(i % 10), MARKERS[i % len(MARKERS)]) for i, m in enumerate(method_names(results))}


def _save(fig, path: Path) -> Path:
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path


def plot_rd(results: dict, path: Path) -> Path:
    fig = _figure(6.4, 4.6)
    ax = fig.add_subplot()
    style = _style(results)
    if seeds_of(results):
        _rd_seeded(results, ax, style)
    for m in (method_names(results) if not seeds_of(results) else []):
        rs = sorted(runs_of(results, m), key=lambda r: r["mb"])
        if not rs:
            continue
        c, mk = style[m]
        ax.plot([r["mb"] for r in rs], [r["psnr"] for r in rs], marker=mk, color=c, lw=1.8, ms=7,
                label=label(results, m))
        spots: dict = {}          # points that coincide on the plot share one label
        for r in rs:
            key = (f"{r['mb']:.3g}", f"{r['psnr']:.2f}")
            spots.setdefault(key, (r["mb"], r["psnr"], []))[2].append(f"{r['lmbda']:g}")
        for x, y, lams in spots.values():
            ax.annotate("λ=" + ", ".join(lams), (x, y), textcoords="offset points",
                        xytext=(5, -11), fontsize=7.5, color=c)
    ref = results.get("reference")
    if ref:
        ax.axhline(ref["psnr"], color="0.35", ls="--", lw=1.2,
                   label=f"uncompressed {label(results, ref['method'])} ({ref['mb']:.3g} MB as float32)")
    ax.set_xlabel("size of the .pgs file (MB = 2^20 bytes)")
    ax.set_ylabel("PSNR on the test views (dB)")
    ax.set_title(f"Rate-distortion: {Path(results.get('scene', '')).name}")
    ax.grid(True, alpha=0.3)
    ax.legend(title="method", fontsize=9)
    return _save(fig, path)


def _rd_seeded(results: dict, ax, style) -> None:
    """Seed-mean curves (lines, error bars = min..max over the seeds) over each seed's runs
    (small hollow markers)."""
    for m in method_names(results):
        c, mk = style[m]
        rs = runs_of(results, m)
        ax.plot([r["mb"] for r in rs], [r["psnr"] for r in rs], ls="", marker=mk, ms=4,
                mfc="none", color=c, alpha=0.6)
        pts = seed_mean_points(results, m)
        if not pts:
            continue
        x = [p["mb"] for p in pts]
        y = [p["psnr"] for p in pts]
        ax.errorbar(x, y, xerr=[[p["mb"] - p["mb_min"] for p in pts],
                                [p["mb_max"] - p["mb"] for p in pts]],
                    yerr=[[p["psnr"] - p["psnr_min"] for p in pts],
                          [p["psnr_max"] - p["psnr"] for p in pts]],
                    marker=mk, color=c, lw=1.8, ms=7, capsize=3,
                    label=label(results, m) if pts[0]["n"] < 2
                    else f"{label(results, m)} (mean of {pts[0]['n']} seeds)")
        for p in pts:
            ax.annotate(f"λ={p['lmbda']:g}", (p["mb"], p["psnr"]), textcoords="offset points",
                        xytext=(5, -11), fontsize=7.5, color=c)


def plot_bits(results: dict, path: Path) -> Path:
    points = [p for p in rate_points(results) if p]
    bars = [r for p in points for r in p]
    groups = [g for g in GROUP_ORDER if any(r["groups"].get(g, 0) for r in bars)]
    groups += sorted({g for r in bars for g in r["groups"]} - set(GROUP_ORDER))
    # x positions: one cluster per rate point, one bar per method, a gap between clusters
    xs, labels, x = [], [], 0.0
    for p in points:
        for r in p:
            xs.append(x)
            labels.append(f"{label(results, r['method'])}\nλ={r['lmbda']:g}"
                          + (f" s{r['seed']}" if r.get("seed") is not None else ""))
            x += 1.0
        x += 0.6
    fig = _figure(max(6.0, 1.6 + 1.0 * len(bars)), 5.2)
    ax = fig.add_subplot()
    bottom = [0.0] * len(bars)
    for g in groups:
        h = [r["groups"].get(g, 0) / MB for r in bars]
        ax.bar(xs, h, bottom=bottom, width=0.8, color=GROUP_COLORS.get(g), label=g,
               edgecolor="white", linewidth=0.5)
        bottom = [b + v for b, v in zip(bottom, h)]
    for xi, r in zip(xs, bars):
        ax.text(xi, r["mb"], f"{r['mb']:.3g}", ha="center", va="bottom", fontsize=7.5)
    ax.set_xticks(xs, labels, rotation=30 if len(bars) > 4 else 0, ha="right" if len(bars) > 4
                  else "center", fontsize=8)
    ax.set_ylabel("size (MB = 2^20 bytes)")
    ax.set_title("Bit allocation of the .pgs file by group")
    ax.grid(True, axis="y", alpha=0.3)
    ax.legend(title="group", fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.set_ylim(0, max(r["mb"] for r in bars) * 1.12 if bars else 1)
    return _save(fig, path)


def plot_speed(results: dict, path: Path) -> Path:
    fig = _figure(10.0, 4.4)
    ax_f, ax_t = fig.subplots(1, 2)
    style = _style(results)
    any_cache = any_untimed = False
    for m in method_names(results):
        rs = sorted(runs_of(results, m), key=lambda r: r["psnr"])
        if not rs:
            continue
        c, mk = style[m]
        ax_f.plot([r["fps"] for r in rs], [r["psnr"] for r in rs], ls="", marker=mk, color=c, ms=8,
                  label=label(results, m) + (" (cached)" if any(r["has_cache"] for r in rs) else ""))
        cached = [r for r in rs if r["has_cache"] and r["fps_nocache"] is not None]
        if cached:
            any_cache = True
            ax_f.plot([r["fps_nocache"] for r in cached], [r["psnr"] for r in cached], ls="",
                      marker=mk, color=c, ms=8, mfc="none", label=f"{label(results, m)} (no cache)")
            for r in cached:
                ax_f.annotate("", xy=(r["fps"], r["psnr"]), xytext=(r["fps_nocache"], r["psnr"]),
                              arrowprops=dict(arrowstyle="->", color=c, alpha=0.5))
        timed = [r for r in rs if not untimed(r)]
        ax_t.plot([r["train_time_s"] for r in timed], [r["psnr"] for r in timed], ls="",
                  marker=mk, color=c, ms=8, label=label(results, m))
        waited = [r for r in rs if untimed(r)]
        if waited:       # left out of the verdict's ratio: drawn hollow, named
            any_untimed = True
            ax_t.plot([r["train_time_s"] for r in waited], [r["psnr"] for r in waited], ls="",
                      marker=mk, color=c, ms=8, mfc="none",
                      label=f"{label(results, m)} (untimed)")
            for r in waited:
                ax_t.annotate(f"λ={r['lmbda']:g}: untimed", (r["train_time_s"], r["psnr"]),
                              textcoords="offset points", xytext=(5, 5), fontsize=7, color=c)
    ax_f.set_xlabel("render speed of the decoded model (FPS)")
    ax_f.set_title("Rendering speed vs quality" + (" (hollow: without cache)" if any_cache else ""),
                   fontsize=10)
    ax_t.set_xlabel("training time (s)")
    ax_t.set_title("Training time vs quality" + (" (hollow: untimed, stalled or marked; left "
                                                 "out of the ratio)" if any_untimed else ""),
                   fontsize=10)
    for ax in (ax_f, ax_t):
        ax.set_ylabel("PSNR on the test views (dB)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
    fig.suptitle("Speed against error")
    return _save(fig, path)


def write_plots(results: dict, out_dir: str | Path) -> dict:
    out_dir = Path(out_dir)
    return {"rd": plot_rd(results, out_dir / "rd.png"),
            "bits": plot_bits(results, out_dir / "bits.png"),
            "speed": plot_speed(results, out_dir / "speed.png")}
