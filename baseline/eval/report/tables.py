"""The report's tables (quality, bit allocation, sections, coded attributes, speed, census,
training curves, reference, BD, rate points, seeds) and the protocol lines.

About 620 lines: one function per table of report.md, all reading the same cells and names.
"""
from __future__ import annotations

import json
from typing import Optional

from baseline.eval.report.names import (baseline_partner, GROUP_ORDER, label, MB, method_names,
                                        method_notes, ordered_runs, others_bytes, rate_elements,
                                        rate_points, seed_mean_points, seeds_of)
from baseline.eval.report.cells import (_change, _count, _f, _is_base, _lam, _main_ssim_convention,
                                        _not_shown, _pct, _saving, _share, _ssim_cell, ssim_note,
                                        Table, _with_change)
from baseline.eval.report.bd import (bd_against, bd_pairs, BD_THIN_OVERLAP, compute_bd,
                                     point_readings)
from baseline.eval.report.curves import curve_cells, span_headers
from baseline.eval.report.timing import _codes_shown, _machines_shown, _threads_shown, untimed


def _lpips_note(results: dict) -> str:
    runs = results["runs"]
    ids = sorted({str(r.get("lpips_weights")) for r in runs if r["lpips"] is not None})
    if not ids:
        from baseline.eval.metrics import LPIPS_UNAVAILABLE

        return str(results.get("lpips") or LPIPS_UNAVAILABLE)
    note = "LPIPS: VGG16 LPIPS with weights " + "; ".join(ids)
    if any(r["lpips"] is None for r in runs):
        note += " ('unavailable' rows: pass --lpips-weights PATH)"
    return note


def quality_table(results: dict) -> Table:
    rows = []
    for r in ordered_runs(results):
        p = baseline_partner(results, r)
        rows.append([label(results, r["method"]), _lam(r), _f(r["psnr"], 3),
                     _f((r.get("pre_encode") or {}).get("psnr"), 3), _ssim_cell(results, r),
                     "unavailable" if r["lpips"] is None else _f(r["lpips"], 4),
                     _f(r["mb"], 4),
                     "ref" if _is_base(results, r) else _pct(_change(r["bytes"], p and p["bytes"])),
                     str(r["anchors"])])
    notes = ["Decoded .pgs file on the test views; metrics on uint8 images. 'pre-encode': PSNR "
             "of the trained model before entropy coding, its coded values and positions "
             "rounded as the codec rounds them (a trained compressed model: equal to the "
             "decoded file's, since the coding is lossless). MB = file bytes / 2^20; size "
             "change vs the baseline at the same rate point.",
             ssim_note(results), _lpips_note(results)]
    return Table("Quality and size (decoded file)",
                 ["method", "lambda", "PSNR (dB)", "pre-encode", "SSIM", "LPIPS", "size (MB)",
                  f"vs {label(results, 'baseline')}", "anchors"], rows, notes, left=2)


def groups_table(results: dict) -> Table:
    runs = ordered_runs(results)
    present = [g for g in GROUP_ORDER if any(g in r["groups"] for r in runs)]
    extra = sorted({g for r in runs for g in r["groups"]} - set(GROUP_ORDER))
    groups = present + extra
    rows = [[label(results, r["method"]), _lam(r)] + [_f(r["groups"].get(g, 0) / MB, 4) for g in groups]
            + [_f(r["mb"], 4)] for r in runs]
    return Table("Bit allocation by group (MB)", ["method", "lambda"] + groups + ["total"], rows,
                 ["feature = the feature provider's coded attribute(s) and sections (HAC: feat"
                  + "".join(f"; {lab}: {note}" for lab, note in method_notes("feature_sections"))
                  + "); read from each file."], left=2)


def table3(results: dict) -> Table:
    rows = []
    for r in ordered_runs(results):
        p = baseline_partner(results, r)
        feat = r["groups"].get("feature", 0)
        oth = others_bytes(r)
        sav = (["ref"] * 3 if _is_base(results, r) else
               [_pct(_saving(feat, p and p["groups"].get("feature", 0))),
                _pct(_saving(oth, p and others_bytes(p))), _pct(_saving(r["bytes"], p and p["bytes"]))])
        rows.append([label(results, r["method"]), _lam(r), _f(feat / MB, 4), _f(oth / MB, 4), _f(r["mb"], 4)] + sav)
    return Table("Feature vs others (as the paper's Table 3)",
                 ["method", "lambda", "feature (MB)", "others (MB)", "total (MB)",
                  "feature saving", "others saving", "total saving"], rows,
                 ["saving = 1 - size / baseline size at the same rate point (positive = smaller)."],
                 left=2)


def _label(section: dict) -> str:
    """A section's name as the component that owns it calls it (``pgs info``); records kept
    before labels: the file's section name."""
    return section.get("label") or section["section"]


def section_tables(results: dict) -> list[Table]:
    tables = []
    for point in rate_points(results):
        if not point:
            continue
        shared = len({r["lmbda"] for r in point}) == 1
        heads = [label(results, r["method"]) if shared
                 else f"{label(results, r['method'])} (lambda {_lam(r)})" for r in point]
        names: list[tuple[str, str]] = []
        for r in point:
            for s in r["sections"]:
                if (_label(s), s["group"]) not in names:
                    names.append((_label(s), s["group"]))
        names.sort(key=lambda sg: (GROUP_ORDER.index(sg[1]) if sg[1] in GROUP_ORDER else 99, sg[0]))
        per = [{_label(s): s["bytes"] for s in r["sections"]} for r in point]
        rows = [[sec, grp] + [str(d[sec]) if sec in d else "-" for d in per] for sec, grp in names]
        hf = [r["groups"].get("header+framing", 0) for r in point]
        rows.append(["(header + framing)", "header+framing"] + [str(x) for x in hf])
        rows.append(["total (file size)", ""] + [str(r["bytes"]) for r in point])
        title = "Sections (bytes)" + (f" at lambda {_lam(point[0])}" if shared else "")
        tables.append(Table(title, ["section", "group"] + heads, rows, left=2))
    return tables


def _attr_rows(r: dict) -> dict:
    return {a["section"]: a for a in (r.get("attributes") or [])}


def elements_table(results: dict) -> Optional[Table]:
    """Per coded attribute: values coded and bits per value, beside the baseline's same attribute.

    A section grows for two reasons, more values coded (more anchors, more Gaussian masks on) or
    more bits per value; this table separates them. None when no run recorded the counts (runs
    archived before they were kept)."""
    runs = [r for r in ordered_runs(results) if r.get("attributes")]
    if not runs:
        return None
    rows = []
    for r in runs:
        p = baseline_partner(results, r)
        pa = _attr_rows(p) if p is not None and not _is_base(results, r) else {}
        m = r.get("masks_on") or {}
        on = f"{100 * m['on'] / m['total']:.1f}%" if m.get("total") else "-"
        for a in r["attributes"]:
            ref = pa.get(a["section"])
            bpe = a["bits_per_element"]
            rows.append([label(results, r["method"]), _lam(r), a["section"], str(a["elements"]), str(a["bytes"]),
                         _f(bpe, 3),
                         ("ref" if _is_base(results, r) else
                          _pct(_change(a["elements"], ref and ref["elements"]))),
                         ("ref" if _is_base(results, r) else
                          _pct(_change(bpe, ref and ref["bits_per_element"]))),
                         on if a["masked"] else ""])
    notes = ["values = numbers the entropy coder wrote (anchors x dims; offsets only for "
             "Gaussians whose mask is on); bits/value = section bytes x 8 / values. Changes are "
             "against the baseline's same attribute at the same rate point ('-': it has none). "
             "Read from each file."]
    notes += _not_shown(results, lambda r: bool(r.get("attributes")), "these counts were")
    return Table("Coded values and bits per value", ["method", "lambda", "attribute", "values",
                 "bytes", "bits/value", f"values vs {label(results, 'baseline')}",
                 f"bits/value vs {label(results, 'baseline')}",
                 "masks on"], rows, notes, left=3)


def speed_table(results: dict) -> Table:
    rows = []
    any_cache = False
    for r in ordered_runs(results):
        any_cache |= bool(r["has_cache"])
        rows.append([label(results, r["method"]), _lam(r), _f(r["psnr"], 3), _f(r["mb"], 4), _f(r["train_time_s"], 1),
                     _f(r["s_per_it"], 4), _f(r["encode_s"], 3), _f(r["decode_s"], 3),
                     _f(r["fps"], 1), _f(r["fps_nocache"], 1) if r["has_cache"] else "(no cache)",
                     _with_change(results, r, "gaussians_mean", _count)])
    notes = ["FPS = 1 / mean per-view time of prefilter + Gaussian decoding + rasterization on the "
             "test views (the first 5 views skipped when there are more), decoded model.",
             "Train time is the optimization loop only (summed over the parts of a resumed run); "
             "every timing is one measurement on the machine as it was loaded at the time.",
             "FPS of runs measured at different times do not make a speed ratio (the machine's "
             "load changes between them): `pgs bench fps --run A --run B` times decoded files "
             "in one process, rounds in rotated order.",
             "Gaussians/view: neural Gaussians kept (mask on, opacity > 0) per test view, mean; "
             "a count, not a timing, and what rasterization time follows (change vs the "
             "baseline at the same rate point)."]
    waited = [r for r in ordered_runs(results) if untimed(r)]
    if waited:
        notes.append("Train time not a measurement of its cost (stalled: ran on no core, paused "
                     "or sharing its core with other work; marked so in its record; or resumed on "
                     "another machine): "
                     + "; ".join(f"{label(results, r['method'])} {_lam(r)}: {untimed(r)}"
                                 for r in waited) + ".")
    if any_cache:
        notes.append("FPS with the decoded-model cache (per-anchor predicted features computed once "
                     "at decode, inside the decode time) in 'FPS'; 'FPS w/o cache' recomputes "
                     "them every view. "
                     "'(no cache)': the model has none, its one FPS is in 'FPS'.")
    return Table("Speed against error", ["method", "lambda", "PSNR (dB)", "size (MB)", "train (s)",
                                         "s/it", "encode (s)", "decode (s)", "FPS",
                                         "FPS w/o cache", "Gaussians/view"], rows, notes, left=2)


def alive_table(results: dict) -> Optional[Table]:
    """Where the Gaussians per view come from: visible anchors x K candidates x the share whose
    mask is on x the share of those with opacity > 0. Two methods can keep different numbers of
    Gaussians (and so render at different speeds) for either reason. None when no run recorded
    the breakdown (runs archived before it was kept)."""
    runs = [r for r in ordered_runs(results) if r.get("mask_on_fraction") is not None]
    if not runs:
        return None
    rows = [[label(results, r["method"]), _lam(r), _with_change(results, r, "visible_anchors_mean", _count),
             _with_change(results, r, "mask_on_fraction", _share),
             _with_change(results, r, "opacity_kept_fraction", _share),
             _with_change(results, r, "gaussians_mean", _count)] for r in runs]
    notes = ["Per test view of the decoded model: anchors in the view, the share of their "
             "candidate Gaussians whose mask is on, the share of those with opacity > 0 "
             "(rasterized); Gaussians/view = visible x K x both shares. In brackets: the change vs "
             "the baseline at the same rate point."]
    notes += _not_shown(results, lambda r: r.get("mask_on_fraction") is not None,
                        "this breakdown was")
    return Table("Where the Gaussians per view come from", ["method", "lambda",
                 "visible anchors/view", "masks on", "opacity > 0 of mask-on", "Gaussians/view"],
                 rows, notes, left=2)


def census_table(results: dict) -> Optional[Table]:
    """The Gaussian census of each run (:mod:`baseline.eval.census`): the opacity test's pass
    rate with the refiner's corrections on and off, how many Gaussians visible anchors draw,
    whether neighbours draw the same K-slot pattern, initial vs grown anchors, and the PSNR a
    run keeps when its count is cut to the baseline's at the same rate point. None when no run
    has one (runs archived before it was kept)."""
    from baseline.eval.census import _hist_parts, psnr_at_gaussians

    runs = [r for r in ordered_runs(results) if r.get("census")]
    if not runs:
        return None
    rows = []
    for r in runs:
        c = r["census"]
        births = c.get("by_birth") or {}
        grown = " / ".join(_share(b["kept_share"]) if b["kept_share"] is not None else "-"
                           for b in births.values()) or "-"
        p = None if _is_base(results, r) else baseline_partner(results, r)
        cut = "-"
        if p is not None and p.get("census") and c["gaussians"] > p["census"]["gaussians"]:
            v = psnr_at_gaussians(c["sweep"], p["census"]["gaussians"])
            cut = "-" if v is None else f"{v:.3f} ({v - c['sweep'][0]['psnr']:+.3f})"
        rows.append([label(results, r["method"]), _lam(r), _count(c["gaussians"]), _share(c["kept_share"]),
                     _share(c["kept_share_coarse"]) if c["refiner"] else "-",
                     (f"{_share(c['revived_share'])} / {_share(c['removed_share'])}"
                      if c["refiner"] else "-"),
                     " / ".join(_share(x) for x in _hist_parts(c["kept_per_anchor"])),
                     f"{_share(c['pattern']['equal_nn'])} / {_share(c['pattern']['equal_random'])}",
                     grown, cut])
    notes = ["Measured on the run's coded state (what its file holds), test views. kept: the share "
             "of mask-on candidate Gaussians with opacity > 0; corrections off: the same with the "
             "refiner's corrections removed (the provider's features alone), and the candidates "
             "the corrections revive / remove; anchors drawing 0 / 1-3 / 4-7 / 8+: visible anchors "
             "by their number of drawn Gaussians; same pattern: the share of visible anchors whose "
             "K-slot drawn/not pattern equals their nearest visible neighbour's / a random one's; "
             "kept by birth: initial / grown anchors"
             + "".join(f" ({lab}: {note})" for lab, note in method_notes("grown_anchors"))
             + "; cut: the PSNR left when the opacity threshold is raised until the run draws the "
             "baseline's Gaussians per view (same rate point), and its change. `pgs census RUN "
             "[RUN2 ...]` prints the whole census."]
    notes += _not_shown(results, lambda r: bool(r.get("census")), "the census was")
    return Table("Gaussian census", ["method", "lambda", "Gaussians/view", "kept",
                                     "corrections off", "revived / removed",
                                     "anchors drawing 0 / 1-3 / 4-7 / 8+", "same pattern: nn / random",
                                     "kept by birth", f"cut to {label(results, 'baseline')}'s count: PSNR"],
                 rows, notes, left=2)


def curve_table(results: dict) -> Optional[Table]:
    """Where in the schedule a method falls behind (:mod:`baseline.eval.report.curves`): each run's
    mean training L1 per span of its schedule (six equal spans), and the sampled bits per anchor
    of the rate term in the last span, with the change vs the baseline's run at the same rate
    point and seed. None when no run kept its curve (records archived before it was kept)."""

    runs = [r for r in ordered_runs(results) if r.get("train_curve")]
    if not runs:
        return None
    curves = [r["train_curve"] for r in runs]
    n = len(curves[0]["l1"])
    rows = []
    for r, c in zip(runs, curves):
        p = None if _is_base(results, r) else baseline_partner(results, r)
        pc = p.get("train_curve") if p else None
        rows.append([label(results, r["method"]), _lam(r)]
                    + curve_cells(c, rate_elements(r), pc, rate_elements(p) if pc else None))
    notes = [f"From each run's training log: the mean L1 of the sampled training views over "
             f"each of {n} equal spans of the schedule, and the rate term's sampled bits per "
             "anchor (bits per coded value x coded values per anchor) over the last span; in "
             "brackets the change vs the baseline's run at the same rate point and seed (read a "
             "change against the spread between one method's seeds)."]
    used = {p for r in runs for p in r.get("method_patches", ())}
    for lab, note in method_notes("training_curve", used):
        notes[0] += f" {lab}'s {note}"
    notes += _not_shown(results, lambda r: bool(r.get("train_curve")), "the training curve was")
    return Table("Training curves", ["method", "lambda"] + span_headers(curves)
                 + ["bits/anchor, last span"], rows, notes, left=2)


def reference_table(results: dict) -> Optional[Table]:
    """Every run against the uncompressed reference (``pgs compare --reference``): PSNR change
    and how many times smaller its file is than the reference's float32 model. None without one."""
    ref = results.get("reference")
    if not ref:
        return None
    rows = [[f"reference: {ref['method']}", "-", _f(ref["psnr"], 3), "ref", _ssim_cell(results, ref),
             _f(ref["mb"], 4), "1x"]]
    for r in ordered_runs(results):
        rows.append([label(results, r["method"]), _lam(r), _f(r["psnr"], 3), f"{r['psnr'] - ref['psnr']:+.3f}",
                     _ssim_cell(results, r), _f(r["mb"], 4),
                     f"{ref['float32_bytes'] / r['bytes']:.1f}x"])
    notes = [f"Reference: the uncompressed run `{' + '.join(ref['patches'])}` on the same "
             f"protocol ({ref['iterations']} iterations, {ref['anchors']} anchors, "
             f"{ref['float32_bytes']} bytes). Its quality is the trained model's on the test "
             f"views (nothing coded); its size counts every value the renderer reads as float32 "
             f"(anchor positions, features, offsets, scalings, networks). 'x smaller' = that "
             f"size / the .pgs file's size; 'vs ref' = PSNR change in dB."]
    other = sorted({f"{label(results, r['method'])} {_lam(r)}" for r in ordered_runs(results)
                    if r["iterations"] != ref["iterations"]})
    if other:
        notes.append("trained for another number of iterations than the reference: "
                     + ", ".join(other))
    return Table("Against the uncompressed reference", ["method", "lambda", "PSNR (dB)",
                 "vs ref (dB)", "SSIM", "size (MB)", "x smaller"], rows, notes, left=2)


def _overlap_cell(b: dict) -> str:
    ov = b.get("psnr_overlap")
    if not ov:
        return "-"
    lo, hi, share = ov
    return f"{lo:.2f}-{hi:.2f} dB ({share:.0%}{', thin' if share < BD_THIN_OVERLAP else ''})"


def bd_caveats(b: dict) -> str:
    """'' or the verdict's caveats: the BD-rate's PSNR overlap is thin, a curve does not rise
    with size."""
    if b.get("bd_rate") is None:
        return ""
    out = ""
    ov = b.get("psnr_overlap")
    if ov and ov[2] < BD_THIN_OVERLAP:
        out += (f"; over {ov[0]:.2f}-{ov[1]:.2f} dB only, {ov[2]:.0%} of the wider curve's "
                f"PSNR span: a thin overlap, more rate points where the curves meet make it a "
                f"measurement")
    if b.get("non_monotone"):
        out += "; a curve does not rise with size (see the BD table's note)"
    if _signs_disagree(b):
        out += ("; BD-rate and BD-PSNR disagree in sign (one says better, the other worse): "
                + _SIGNS)
    return out


_SIGNS = "the curves cross or run through noise, and neither delta is a measurement"


def _signs_disagree(b: dict) -> bool:
    """A BD item whose two deltas point opposite ways: fewer bytes at equal PSNR (BD-rate < 0)
    but less PSNR at equal size (BD-PSNR < 0), or the reverse."""
    r, d = b.get("bd_rate"), b.get("bd_psnr")
    return r is not None and d is not None and r * d > 0


def bd_table(results: dict) -> Table:
    bd = results.get("bd") or compute_bd(results)
    base = results.get("baseline", "baseline")
    seeded = any(b.get("seed") is not None for b in bd)
    nested = any(bd_against(results, b) != base for b in bd)
    rows, foot = [], []
    one_seed = seeded and len(seeds_of(results)) == 1
    for b in bd:
        if one_seed and b.get("seed") != "mean":
            continue  # one seed: its curve is the seed-mean curve; one row, not two equal ones
        mark = ""
        ref = bd_against(results, b)
        note = b["note"]
        if _signs_disagree(b):
            note = (((note + "; ") if note else "")
                    + "BD-rate and BD-PSNR disagree in sign: " + _SIGNS)
        if note:
            vs = f" vs {label(results, ref)}" if ref != base else ""
            foot.append(f"({len(foot) + 1}) {label(results, b['method'])}{vs}: {note}")
            mark = f"({len(foot)})"
        sd = b.get("seed")
        curve = ([(f"seed {seeds_of(results)[0]}" if one_seed else
                   "seed-mean curves" if sd == "mean" else f"seed {sd}")] if seeded else [])
        rows.append([label(results, b["method"])] + ([label(results, ref)] if nested else [])
                    + curve + [f"{b['points']} vs {b['baseline_points']}",
                     "-" if b["bd_rate"] is None else f"{b['bd_rate']:+.2f}",
                     "-" if b["bd_psnr"] is None else f"{b['bd_psnr']:+.3f}",
                     _overlap_cell(b), mark])
    notes = foot + ["Piecewise cubic (PCHIP) interpolation of log10(size) vs PSNR (BD-rate) "
                    "and PSNR vs log10(size) (BD-PSNR), integrated over the overlapping "
                    "interval; size = file MB. Negative BD-rate = fewer bytes at equal PSNR. "
                    "PSNR overlap: the interval the BD-rate integrates over and its share of the "
                    "wider curve's PSNR span (thin below "
                    f"{BD_THIN_OVERLAP:.0%}: the delta then describes a sliver of the curves). "
                    "This, not a pair of runs at one lambda, is the rate-distortion comparison: "
                    "lambda only moves each method along its own curve."]
    if one_seed:
        notes.append("One seed: its curves only, no spread measured (a comparison with "
                     "--seeds 0 1 gives the per-seed rows and the seed-mean curves).")
    elif seeded:
        notes.append("Per seed: the method's and the baseline's runs of that seed; seed-mean "
                     "curves: per lambda the mean size and PSNR over the seeds (a lambda "
                     "counts once every seed has finished), the comparison's answer; the "
                     "per-seed rows show how far one seed moves it.")
    if nested:
        notes.append(f"Against: the reference curve. Every method is measured against "
                     f"{label(results, base)}, and a method that extends other contenders (its "
                     f"patches include all of theirs) also against each of them: the delta its "
                     f"extra patches make on their own.")
    title = (f"Bjontegaard deltas against {label(results, base)}" if not nested else
             f"Bjontegaard deltas against {label(results, base)} and the methods each extends")
    return Table(title, ["method"] + (["against"] if nested else []) + (["curve"] if seeded else [])
                 + ["points", "BD-rate (%)", "BD-PSNR (dB)", "PSNR overlap", "note"], rows, notes,
                 left=1 + int(nested) + int(seeded))


def point_table(results: dict) -> Optional[Table]:
    """Each rate point of the two methods of every BD pair read against the other one's curve
    (:func:`point_readings`), the points outside that curve on both axes left out; None when
    no point lies within another curve's range."""
    rows = []
    done = set()
    for m, ref in bd_pairs(results):
        for a, b in ((m, ref), (ref, m)):
            if (a, b) in done:
                continue
            done.add((a, b))
            for it in point_readings(results, a, b):
                if it["ref_mb"] is None and it["ref_psnr"] is None:
                    continue            # outside the other curve on both axes: nothing to read
                rows.append([label(results, a), f"{it['lmbda']:g}", _f(it["psnr"], 3),
                             _f(it["mb"], 4), label(results, b), _f(it["ref_mb"], 4),
                             _pct(it["size_change"]), _f(it["ref_psnr"], 3),
                             "-" if it["psnr_change"] is None else f"{it['psnr_change']:+.3f}"])
    if not rows:
        return None
    seeds = seeds_of(results)
    pts = ("per lambda the mean over the seeds of size and PSNR (a lambda counts once every "
           "seed has finished)" if len(seeds) > 1 else
           f"the runs of seed {seeds[0]}" if seeds else "the runs")
    notes = ["Each point (" + pts + ") read against the curve named in 'against': the size that "
             "curve needs at the point's PSNR and the PSNR it reaches at the point's size, "
             "interpolating log10(size) linearly between the curve's two points around the "
             "value, on its rising envelope (a point with no more PSNR than a smaller point of "
             "the same curve is left out); '-' outside the curve, which is never extrapolated (a "
             "point outside it on both axes is not listed). "
             "Size change: the point's size against the curve's (negative = smaller at equal "
             "PSNR); PSNR change: positive = better at equal size. A reading at one point, not a "
             "Bjontegaard delta: it moves with the point's own noise (read it against the seed "
             "spread), and it serves where a curve has too few points for a BD-rate."]
    return Table("Each rate point against the other curves", ["method", "lambda", "PSNR (dB)",
                 "size (MB)", "against", "its size at this PSNR", "size change",
                 "its PSNR at this size", "PSNR change (dB)"], rows, notes, left=2)


def seed_table(results: dict) -> Optional[Table]:
    """Per method and lambda: the seed mean and spread (max - min) of PSNR, size and the counts
    that move with the masks. None without seeds."""
    seeds = seeds_of(results)
    if not seeds:
        return None
    rows = []
    for m in method_names(results):
        for pt in seed_mean_points(results, m):
            def ms(key, nd, pct=False):
                v = pt.get(key)
                if v is None:
                    return "-"
                if len(seeds) < 2:  # one seed measures no spread: a bracketed 0 would claim one
                    return f"{100 * v:.1f}%" if pct else f"{v:.{nd}f}"
                lo, hi = pt[key + "_min"], pt[key + "_max"]
                if pct:
                    return f"{100 * v:.1f}% ({100 * (hi - lo):.1f})"
                sp = (f"{100 * (hi - lo) / v:.1f}%" if key in ("mb", "gaussians_mean", "anchors")
                      and v else f"{hi - lo:.{nd}f}")
                return f"{v:.{nd}f} ({sp})"
            sv = ms("ssim", 4)
            if sv != "-" and pt.get("ssim_convention") != _main_ssim_convention(results):
                sv += f" ({pt.get('ssim_convention')})"
            rows.append([label(results, m), f"{pt['lmbda']:g}", str(pt["n"]), ms("psnr", 3), sv,
                         ms("mb", 4), ms("mask_on_fraction", 1, pct=True),
                         ms("gaussians_mean", 0), ms("anchors", 0)])
    if len(seeds) < 2:
        title = f"Per run (one seed ({seeds[0]}): no spread measured)"
        note = ("One seed measures no spread: a difference between methods is a measured "
                "difference only where it is larger than the seed spread the scene shows with "
                "two seeds (a comparison with --seeds 0 1).")
    else:
        title = f"Seed mean and spread (seeds {', '.join(map(str, seeds))})"
        note = ("Each cell: the mean over the seeds and, in brackets, the spread (max - min; "
                "for size, Gaussians and anchors in percent of the mean). Differences between "
                "methods smaller than the spread are not measured differences. A lambda is "
                "shown once every seed has finished.")
    return Table(title, ["method", "lambda", "seeds", "PSNR (dB)", "SSIM", "size (MB)", "masks on",
                         "Gaussians/view", "anchors"], rows, [note], left=2)


def protocol_lines(results: dict) -> list[tuple[str, str]]:
    runs = ordered_runs(results)
    prot = runs[0].get("protocol", {}) if runs else {}

    def per_method(key: str, show=None) -> str:
        vals = {}
        for r in runs:
            v = show(r) if show else str(r.get(key, "cpu" if key == "device" else "-"))
            vals.setdefault(v, []).append(f"{label(results, r['method'])} {_lam(r)}")
        if len(vals) <= 1:
            return next(iter(vals), "-")
        return "; ".join(f"{v} ({', '.join(who)})" for v, who in vals.items())

    size = prot.get("image_size")
    items = [
        ("scene", results.get("scene", "-")),
        ("format", str(prot.get("format", "-"))),
        ("resolution", f"{size[0]} x {size[1]} px (downscale {prot.get('downscale', '-')}, "
                       f"resolution setting {prot.get('resolution', '-')})"
         if isinstance(size, list) and len(size) == 2 and not isinstance(size[0], list)
         else str(size)),
        ("split", f"{prot.get('split', '-')} ({prot.get('n_train', '?')} train / "
                  f"{prot.get('n_test', '?')} test views)"),
        ("background", str(prot.get("background", "-"))),
        ("methods", "; ".join(f"{label(results, m['name'])} = common patches"
                              + (" + " + " + ".join(m["patches"]) if m["patches"] else "")
                              + ("" if label(results, m["name"]) == m["name"]
                                 else f" (runs: {m['name']}-*)")
                              for m in results.get("methods", []))),
        ("common patches", ", ".join(results.get("common_patches", [])) or "(none)"),
        ("--set", ", ".join(results.get("sets", [])) or "(none)"),
        ("codec", _codec_line(results, runs)),
        ("rate term", _rate_term_line(results, runs)),
        ("training semantics", _semantics_line(runs)),
        ("iterations", per_method("iterations")),
        ("threads", per_method("threads", _threads_shown)),
        ("machine", per_method("machine", _machines_shown)),
        ("code", per_method("code", _codes_shown)),
        ("device", per_method("device")),
        ("backend", per_method("backend")),
        ("evaluated on", per_method("split")),
        ("LPIPS", str(results.get("lpips", "unavailable"))),
        ("versions", ", ".join(f"{k} {v}" for k, v in results.get("versions", {}).items())),
    ]
    if results.get("reference_method"):
        items.insert(7, ("reference", _reference_line(results)))
    tv = {tuple(sorted(r.get("train_versions", {}).items())) for r in runs}
    cur = tuple(sorted(results.get("versions", {}).items()))
    if any(v and v != cur for v in tv):
        items.append(("note", "some runs were trained with other versions: see each run's "
                              "results.json"))
    kept = [f"{label(results, r['method'])} {_lam(r)}" for r in runs if r.get("records_only")]
    if kept:
        items.append(("from records", ", ".join(kept) + ": reported from their archived records "
                      "(measured when they were trained; no model file here)"))
    return items


def _semantics_line(runs: list) -> str:
    """The training-semantics version of the runs (baseline.config.TRAINING_SEMANTICS): the
    version is part of each run's config hash, so one comparison holds one version."""
    from baseline.config import semantics_note

    vs = sorted({int(r.get("training_semantics", 1)) for r in runs}) or ["-"]
    if len(vs) > 1:
        return ("MIXED: " + ", ".join(semantics_note(v) for v in vs)
                + " (runs of different versions are not comparable)")
    comps = {}
    for r in runs:
        for k, v in (r.get("component_semantics") or {}).items():
            comps.setdefault(k, set()).add(int(v))
    extra = "".join(f"; {k} {'/'.join(str(v) for v in sorted(vals))}"
                    + (" (MIXED)" if len(vals) > 1 else "") for k, vals in sorted(comps.items()))
    return semantics_note(vs[0]) + extra


def _codec_line(results: dict, runs: list) -> str:
    """How the files were coded: HAC's layout, or the --codec patch's settings (encode only)."""
    c = results.get("codec")
    if c and c.get("patch"):
        sets = ", ".join(f"{k} = {v}" for k, v in c.get("settings", {}).items())
        return f"--codec {c['patch']} ({sets}), applied when encoding; training unchanged"
    kinds = {json.dumps(r.get("codec"), sort_keys=True) for r in runs if r.get("codec")}
    return "each run's own configuration" + (" (several settings)" if len(kinds) > 1 else "")


def _rate_term_line(results: dict, runs: list) -> str:
    """What one lambda means per method: the rate term is HAC's bits per coded parameter,
    lambda x bits / (sampled anchors x E), so a method coding fewer values per anchor (E) weighs
    each bit more at the same lambda (a 25-dim residual: E = 25 + 6 + 30 = 61 against HAC's 86)."""
    per_method = {}
    for r in runs:
        e = rate_elements(r)
        if e is not None:
            per_method.setdefault(r["method"], e)
    line = ("lambda x (bits / (sampled anchors x E) x valid share + hash bits / (anchors x E)), "
            "E = coded values per anchor (HAC's bits per parameter; entropy.rate_values_per_anchor)")
    if not per_method:
        return line + " (E not in these records)"
    line += ": " + ", ".join(f"{label(results, m)} {e}" for m, e in per_method.items())
    ref_name = results.get("baseline", "baseline")
    ref_m = ref_name if ref_name in per_method else next(iter(per_method))
    ref_e = per_method[ref_m]
    other = [f"{label(results, m)} {ref_e / e:.2f}x" for m, e in per_method.items() if e != ref_e]
    if other:
        line += (f"; at one lambda a coded bit weighs, against {label(results, ref_m)}'s: " + ", ".join(other)
                 + " (equal lambda is not equal rate pressure: compare at equal PSNR, BD-rate)")
    return line


def _reference_line(results: dict) -> str:
    """The protocol's line on the uncompressed reference (only when the comparison has one)."""
    ref, meth = results.get("reference"), results.get("reference_method")
    if ref:
        return (f"{ref['method']} = common patches + {' + '.join(ref['method_patches'])}, "
                f"uncompressed, {ref['iterations']} iterations, {ref['s_per_it']:.4f} s/it"
                + (" (from records)" if ref.get("records_only") else ""))
    return f"{meth['name']}: not trained yet"


def all_tables(results: dict) -> list[Table]:
    elements, alive = elements_table(results), alive_table(results)
    ref, seeds = reference_table(results), seed_table(results)
    cen, curves = census_table(results), curve_table(results)
    points = point_table(results)
    return ([quality_table(results)] + ([seeds] if seeds is not None else [])
            + ([ref] if ref is not None else [])
            + [groups_table(results), table3(results)]
            + section_tables(results) + ([elements] if elements is not None else [])
            + [speed_table(results)] + ([alive] if alive is not None else [])
            + ([cen] if cen is not None else [])
            + ([curves] if curves is not None else [])
            + [bd_table(results)] + ([points] if points is not None else []))
