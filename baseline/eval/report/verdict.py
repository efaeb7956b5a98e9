"""The verdict: what the stored measurements say of each contender against the baseline, in a
few lines and one table."""
from __future__ import annotations

from baseline.eval.report.names import label, method_names, runs_of, seeds_of
from baseline.eval.report.cells import _change, _pct, Table
from baseline.eval.report.bd import (bd_against, compute_bd, _curve_points, nested_references,
                                     point_readings)
from baseline.eval.report.timing import fps_ratio, _train_time_line, train_time_ratio
from baseline.eval.report.tables import bd_caveats


def verdict_lines(results: dict) -> list[str]:
    """Which method wins, by how much, at what speed, each sign spelt out: per contender, the
    BD-rate and BD-PSNR against the baseline and against each contender it extends (on the
    seed-mean curves when there are seeds), the size and PSNR changes at each lambda, the paired
    FPS ratio when one was measured (``results["fps_pair"]``) and the training-time ratio.
    ``results["scope"]`` (e.g. the demo's "synthetic scene" caveat) closes it."""
    base = results.get("baseline", "baseline")
    bname = label(results, base)
    seeds = seeds_of(results)
    bd = {(b["method"], bd_against(results, b), b["seed"]): b
          for b in (results.get("bd") or compute_bd(results))}
    curve = (f"on the seed-mean curves of {len(seeds)} seeds" if len(seeds) > 1 else
             f"one seed ({seeds[0]})" if seeds else "one seed")

    def bd_lines(name: str, m: str, ref: str) -> list[str]:
        rname = label(results, ref)
        out = []
        b = bd.get((m, ref, "mean" if seeds else None))
        if b is not None and b["bd_rate"] is not None:
            r = b["bd_rate"]
            out.append(f"{name} is {abs(r):.1f}% {'smaller' if r < 0 else 'larger'} than {rname} "
                       f"at equal quality (BD-rate {r:+.2f}%, {curve}{bd_caveats(b)})")
        elif b is not None:
            out.append(f"{name} vs {rname}: no BD-rate ({b['note'] or 'curves do not overlap'})")
            reads = []
            for it in point_readings(results, m, ref):
                cells = []
                if it["size_change"] is not None:
                    c = it["size_change"]
                    cells.append(f"{abs(c):.1f}% {'smaller' if c < 0 else 'larger'} at equal PSNR")
                if it["psnr_change"] is not None:
                    d = it["psnr_change"]
                    cells.append(f"{abs(d):.3f} dB {'better' if d > 0 else 'worse'} at equal size")
                if cells:
                    reads.append(f"lambda {it['lmbda']:g} " + ", ".join(cells))
            if reads:
                out.append(f"  point by point against {rname}'s curve (readings, not a "
                           f"BD-rate): " + "; ".join(reads))
        if b is not None and b["bd_psnr"] is not None:
            d = b["bd_psnr"]
            out.append(f"{name} is {abs(d):.3f} dB {'better' if d > 0 else 'worse'} than {rname} "
                       f"at equal size (BD-PSNR {d:+.3f} dB)")
        if seeds:
            per = [x for (mm, rr, sd), x in bd.items() if mm == m and rr == ref and sd != "mean"
                   and x["bd_rate"] is not None]
            if len(per) > 1:
                v = [x["bd_rate"] for x in per]
                out.append("  per seed: " + ", ".join(f"{x['bd_rate']:+.2f}% (seed {x['seed']})"
                                                       for x in per)
                           + f"; spread {max(v) - min(v):.2f} points")
        return out

    lines = []
    for m in method_names(results):
        if m == base or not runs_of(results, m):
            continue
        name = label(results, m)
        lines += bd_lines(name, m, base)
        for ref in nested_references(results, m):
            if runs_of(results, ref):
                lines += bd_lines(name, m, ref)
        eq = []
        bpts = {p["lmbda"]: p for p in _curve_points(results, base)}
        for pt in _curve_points(results, m):
            q = bpts.get(pt["lmbda"])
            if q is None:
                continue
            ds = 100.0 * (pt["bytes"] / q["bytes"] - 1.0)
            dp = pt["psnr"] - q["psnr"]
            size = ("the same size" if abs(ds) < 0.05 else
                    f"{abs(ds):.1f}% {'smaller' if ds < 0 else 'larger'}")
            qual = ("the same PSNR" if abs(dp) < 0.0005 else
                    f"{abs(dp):.3f} dB {'higher' if dp > 0 else 'lower'} PSNR")
            eq.append(f"lambda {pt['lmbda']:g}: {size}, {qual}")
        if eq:
            lines.append(f"at equal lambda (not equal rate pressure), {name} vs {bname}: "
                         + "; ".join(eq))
        fp = fps_ratio(results, m)
        if fp:
            ratio = fp["ratio"]
            spread = (f"; the per-round ratios {fp['ratio_rounds'][0]:.2f}-"
                      f"{fp['ratio_rounds'][1]:.2f}" if fp.get("ratio_rounds") else "")
            lines.append(f"{name} renders at {ratio:.2f}x {bname}'s FPS ({'faster' if ratio > 1 else 'slower'}; "
                         f"decoded files timed in one process, {fp['rounds']} rounds, lambda "
                         f"{fp['lmbda']:g}: {fp['fps']:.1f} vs {fp['fps_ref']:.1f} FPS (median "
                         f"over rounds), {fp['threads']} thread(s){spread})")
        tl = _train_time_line(results, m, base, name, bname)
        if tl:
            lines.append(tl)
    if results.get("scope"):
        lines.append(results["scope"])
    return lines


def verdict_table(results: dict) -> Table | None:
    """The verdict's opening table, one row per contender and the curve it is measured against
    (the baseline, then each contender it extends): BD-rate and BD-PSNR (on the seed-mean
    curves with seeds), its size and PSNR change at each lambda both have, the paired FPS ratio
    (against the baseline) and the training-time ratio, each ratio beside the two values it is
    computed from. None when the comparison has no contender with runs."""
    base = results.get("baseline", "baseline")
    seeds = seeds_of(results)
    bd = {(b["method"], bd_against(results, b), b["seed"]): b
          for b in (results.get("bd") or compute_bd(results))}
    pairs = []
    for m in method_names(results):
        if m == base or not runs_of(results, m):
            continue
        pairs += [(m, ref) for ref in [base] + nested_references(results, m)
                  if runs_of(results, ref)]
    if not pairs:
        return None
    shared = {}
    for m, ref in pairs:
        rp = {p["lmbda"]: p for p in _curve_points(results, ref)}
        shared[(m, ref)] = {p["lmbda"]: (p, rp[p["lmbda"]]) for p in _curve_points(results, m)
                            if p["lmbda"] in rp}
    lams = sorted({lm for v in shared.values() for lm in v})
    rows = []
    for m, ref in pairs:
        b = bd.get((m, ref, "mean" if seeds else None)) or {}
        cells = [label(results, m), label(results, ref),
                 "-" if b.get("bd_rate") is None else f"{b['bd_rate']:+.1f}%",
                 "-" if b.get("bd_psnr") is None else f"{b['bd_psnr']:+.3f} dB"]
        for lm in lams:
            pq = shared[(m, ref)].get(lm)
            if pq is None:
                cells.append("-")
                continue
            p, q = pq
            cells.append(f"{_pct(_change(p['bytes'], q['bytes']))} / "
                         f"{p['psnr'] - q['psnr']:+.3f} dB")
        fp = fps_ratio(results, m) if ref == base else None
        cells.append("-" if fp is None else
                     f"{fp['ratio']:.2f}x ({fp['fps']:.1f} / {fp['fps_ref']:.1f} FPS)")
        tr = train_time_ratio(results, m, ref)
        cells.append("-" if tr is None else
                     f"{tr['ratio']:.2f}x ({tr['mean_s']:.0f} / {tr['ref_mean_s']:.0f} s)")
        rows.append(cells)
    curve = (f"the seed-mean curves of {len(seeds)} seeds" if len(seeds) > 1 else
             f"one seed ({seeds[0]})" if seeds else "one seed")
    notes = [(f"Contender against the curve named in 'against', on {curve}: BD-rate (negative = "
             "fewer bytes at equal PSNR) and BD-PSNR (positive = better at equal size); at each "
             "lambda both have, the contender's size change and PSNR change against it (equal "
             "lambda is not equal rate pressure); FPS: decoded files timed in one process "
             "(median over rounds); training time: mean per run over the pairs of one rate "
             "point and thread count. Each ratio = the first value in brackets / the second. "
             "Caveats and readings below.")]
    return Table("Verdict", ["contender", "against", "BD-rate", "BD-PSNR"]
                 + [f"lambda {lm:g}: size / PSNR" for lm in lams]
                 + ["FPS ratio", "training-time ratio"], rows, notes, left=2)
