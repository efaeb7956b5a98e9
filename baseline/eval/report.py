"""The comparison report: tables for the terminal and ``report.md``, computed from stored results.

Input is the ``results.json`` structure written by :func:`baseline.eval.compare.run_compare`
(``runs``: one flat row per method and lambda, see :func:`baseline.eval.compare.make_row`).
Nothing here measures anything: every figure is a stored measurement or arithmetic on them
(ratios to the baseline, Bjontegaard deltas).

Tables:
  1. quality and size of the decoded file per method and lambda, and against the uncompressed
     reference when the comparison has one (``--reference``);
  2. bit allocation per group, then as the paper's Table 3 (feature vs the rest) with the saving
     in percent against the baseline at the same rate point, then section by section;
  3. per coded attribute, the values coded and bits per value against the baseline's;
  4. speed against error (train time, s/it, encode, decode, FPS with / without the cache);
  5. BD-rate / BD-PSNR against the baseline, and against each contender a method extends
     (PCHIP, :mod:`baseline.eval.bdrate`), for methods with at least 3 rate points; then each
     rate point read against the other curve of each such pair (size at equal PSNR, PSNR at
     equal size), which also serves a curve too short for a BD-rate;
  6. the protocol (scene, resolution, split, background, iterations, threads, backend, versions).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Callable, Optional

from baseline.config import method_specs, patch_infos, patch_labels
from baseline.eval.bdrate import (BDError, bd_psnr, bd_rate, non_monotone, overlap, psnr_at_rate,
                                  rate_at_psnr)
from baseline.fileio import write_text_atomic

MB = 2 ** 20
GROUP_ORDER = ["feature", "anchor", "scaling", "offsets", "masks", "hash", "mlps", "header+framing"]
BD_MIN_POINTS = 3
# A Bjontegaard delta integrates over the PSNR interval both curves cover; below this share of
# the wider curve's PSNR span the report calls the overlap thin (the delta then describes a
# sliver of the curves, and one point moves it far)
BD_THIN_OVERLAP = 1.0 / 3.0


# ------------------------------------------------------------------------------ names
# What users call the methods. A comparison's method ids (run folders, records, --only) are
# "baseline" (the common patches alone) and the contenders' patches joined by "+"; every table,
# legend and CSV shows these names instead: the method a patch selects (its label, declared by
# its method spec or patch file: baseline.config.patch_labels), then the other patches.
BASELINE_LABEL = "HAC"


def base_label(common_patches) -> str:
    """The name of the baseline of a comparison: HAC, or the method its common patches select."""
    labels = patch_labels()
    for pt in common_patches or ():
        if pt in labels:
            return labels[pt]
    return BASELINE_LABEL


def method_label(name: str, common_patches=()) -> str:
    """``baseline`` -> ``HAC``; a method's patch -> its label, followed by the other patches
    (``<method>+masks-lr-scaled``); ``entropy-factorized`` (a HAC variant) ->
    ``HAC+entropy-factorized``. No spaces, so a label is one word in a table."""
    base = base_label(common_patches)
    if name == "baseline":
        return base
    parts = [p for p in name.split("+") if p]
    if not parts:
        return base
    labels, methods = patch_labels(), method_specs()
    # a later patch that is a method of its own is named as one (its label)
    rest = [labels.get(p, p) if p in methods else p for p in parts[1:]]
    if parts[0] in labels:
        return "+".join([labels[parts[0]], *rest])
    return "+".join([base, parts[0], *rest])


def method_notes(topic: str, names=None) -> list[tuple[str, str]]:
    """(label, note) of every method spec that says something on ``topic`` (of those named in
    ``names``, when given), by name."""
    return [(s.label, note) for n, s in sorted(method_specs().items())
            if (names is None or n in names) and (note := s.note(topic))]


def label(results: dict, method: str) -> str:
    """The user-facing name of a method of ``results`` (see :func:`method_label`)."""
    return method_label(method, results.get("common_patches", ()))


# ------------------------------------------------------------------------------ selection
def method_names(results: dict) -> list[str]:
    names = [m["name"] for m in results.get("methods", [])]
    for r in results["runs"]:
        if r["method"] not in names:
            names.append(r["method"])
    return names


def _seed_order(r: dict) -> int:
    return -1 if r.get("seed") is None else int(r["seed"])


def runs_of(results: dict, method: str, seed="any") -> list[dict]:
    """A method's runs by lambda (then seed); ``seed``: only the runs of that seed."""
    return sorted((r for r in results["runs"] if r["method"] == method
                   and (seed == "any" or r.get("seed") == seed)),
                  key=lambda r: (r["lmbda"], _seed_order(r)))


def seeds_of(results: dict) -> list[int]:
    """The seeds of a comparison run with ``--seeds`` (empty otherwise)."""
    return sorted({int(r["seed"]) for r in results["runs"] if r.get("seed") is not None})


def seed_mean_points(results: dict, method: str) -> list[dict]:
    """Per lambda, the mean (and min / max) over seeds of a method's size and PSNR: the points
    of its seed-mean curve. A lambda counts only with every seed of the comparison finished."""
    seeds = seeds_of(results)
    out = []
    by_lam: dict = {}
    for r in runs_of(results, method):
        if r.get("seed") is not None:
            by_lam.setdefault(r["lmbda"], []).append(r)
    for lm, rs in sorted(by_lam.items()):
        if sorted(int(r["seed"]) for r in rs) != seeds:
            continue
        pt = {"lmbda": lm, "n": len(rs)}
        convs = {ssim_convention(r) for r in rs}
        pt["ssim_convention"] = convs.pop() if len(convs) == 1 else None
        for key in ("mb", "psnr", "ssim", "bytes", "gaussians_mean", "mask_on_fraction",
                    "anchors"):
            vals = [r.get(key) for r in rs]
            if key == "ssim" and pt["ssim_convention"] is None:
                vals = [None]           # two SSIM conventions make no mean
            if any(v is None for v in vals):
                pt[key] = pt[key + "_min"] = pt[key + "_max"] = None
                continue
            pt[key] = sum(vals) / len(vals)
            pt[key + "_min"], pt[key + "_max"] = min(vals), max(vals)
        out.append(pt)
    return out


def ordered_runs(results: dict) -> list[dict]:
    return [r for m in method_names(results) for r in runs_of(results, m)]


def baseline_partner(results: dict, row: dict) -> Optional[dict]:
    """The baseline run ``row`` is measured against: same lambda; else the only one of each."""
    base = runs_of(results, results.get("baseline", "baseline"))
    same = [b for b in base if b["lmbda"] == row["lmbda"]]
    paired = [b for b in same if b.get("seed") == row.get("seed")]
    if paired:                      # the same seed's run where the comparison has seeds
        return paired[0]
    if same:
        return same[0]
    if len(base) == 1 and len(runs_of(results, row["method"])) == 1:
        return base[0]
    return None


def rate_points(results: dict) -> list[list[dict]]:
    """Runs grouped by rate point.

    By lambda whenever the methods share a lambda (a method missing a run, e.g. a comparison
    still under way, is simply absent from that point); by rank only when their lambdas are
    disjoint (methods with rate points of their own)."""
    names = method_names(results)
    seeds = seeds_of(results)
    if seeds:                       # one point per (lambda, seed)
        keys = list(dict.fromkeys((r["lmbda"], r.get("seed")) for m in names
                                  for r in runs_of(results, m)))
        keys.sort(key=lambda k: (k[0], -1 if k[1] is None else k[1]))
        return [[r for m in names for r in runs_of(results, m)
                 if (r["lmbda"], r.get("seed")) == k] for k in keys]
    per = [runs_of(results, m) for m in names]
    lam_lists = [[r["lmbda"] for r in rs] for rs in per if rs]
    union = list(dict.fromkeys(lm for ls in lam_lists for lm in ls))
    if len(lam_lists) <= 1 or len(union) < sum(len(ls) for ls in lam_lists):
        return [[r for rs in per for r in rs if r["lmbda"] == lm] for lm in union]
    n = max((len(rs) for rs in per), default=0)
    return [[rs[i] for rs in per if i < len(rs)] for i in range(n)]


def others_bytes(row: dict) -> int:
    return row["bytes"] - row["groups"].get("feature", 0)


def _bd_item(method: str, seed, base: list[dict], rs: list[dict], against: str) -> dict:
    """BD-rate / BD-PSNR of points ``rs`` against ``base`` (each a dict with mb and psnr), the
    points of method ``against``."""
    item = {"method": method, "against": against, "seed": seed, "points": len(rs),
            "baseline_points": len(base), "bd_rate": None, "bd_psnr": None, "note": ""}
    if min(len(rs), len(base)) < BD_MIN_POINTS:
        item["note"] = (f"needs >= {BD_MIN_POINTS} rate points per method "
                        f"(have {len(rs)}, the curve it is measured against {len(base)})")
        return item
    args = ([b["mb"] for b in base], [b["psnr"] for b in base],
            [r["mb"] for r in rs], [r["psnr"] for r in rs])
    lo, hi, share = overlap(args[1], args[3])
    item["psnr_overlap"] = [lo, hi, share] if share > 0 else None
    notes = []
    for who, pts in (("the baseline's", base), ("its", rs)):
        bad = non_monotone([p["mb"] for p in pts], [p["psnr"] for p in pts])
        if bad:
            which = ", ".join(f"{pts[i]['psnr']:.3f} dB at {pts[i]['mb']:.3f} MB" for i in bad)
            notes.append(f"{who} curve does not rise with size ({which}: no more PSNR than a "
                         f"smaller point); the delta runs through points that differ by less "
                         f"than their noise")
    item["non_monotone"] = bool(notes)
    for key, fn in (("bd_rate", bd_rate), ("bd_psnr", bd_psnr)):
        try:
            item[key] = fn(*args)
        except BDError as e:      # each measure needs its own overlap: keep the other
            notes.append(str(e))
    item["note"] = "; ".join(notes)
    return item


def method_patches(results: dict, method: str) -> Optional[frozenset]:
    """The patches that make ``method`` (beyond the common ones): from the comparison's methods,
    else from its runs' records; None when neither names them."""
    for m in results.get("methods", []):
        if m["name"] == method:
            return frozenset(m.get("patches") or [])
    for r in runs_of(results, method):
        if "method_patches" in r:
            return frozenset(r["method_patches"])
    return None


def nested_references(results: dict, method: str) -> list[str]:
    """The contenders (not the baseline) ``method`` extends: those whose patches are a strict
    subset of its own. A method A+B extends A and B, so it is also measured against each: what
    B adds to A, and what A adds on B."""
    base = results.get("baseline", "baseline")
    mine = method_patches(results, method)
    if not mine:
        return []
    refs = []
    for n in method_names(results):
        theirs = method_patches(results, n) if n not in (base, method) else None
        if theirs and theirs < mine:
            refs.append(n)
    return refs


def bd_pairs(results: dict) -> list[tuple[str, str]]:
    """(method, reference) pairs a comparison measures: each method against the baseline, then
    each against every contender it extends (:func:`nested_references`)."""
    base_name = results.get("baseline", "baseline")
    names = method_names(results)
    pairs = [(m, base_name) for m in names if m != base_name]
    return pairs + [(m, ref) for m in names if m != base_name
                    for ref in nested_references(results, m)]


def point_readings(results: dict, method: str, ref: str) -> list[dict]:
    """Each rate point of ``method`` read against ``ref``'s curve: the size ``ref``'s curve
    needs at the point's PSNR and the PSNR it reaches at the point's size
    (:func:`~baseline.eval.bdrate.rate_at_psnr`, :func:`~baseline.eval.bdrate.psnr_at_rate`:
    log-linear between the two points around the value, on the curve's rising envelope, never
    extrapolated: None outside it). Points and curve are the seed means with seeds, else the
    runs. Each item: lmbda, mb, psnr, ref_mb, size_change (percent), ref_psnr, psnr_change (dB)."""
    curve = _curve_points(results, ref)
    rs, ps = [c["mb"] for c in curve], [c["psnr"] for c in curve]
    out = []
    for pt in _curve_points(results, method):
        if pt.get("mb") is None or pt.get("psnr") is None:
            continue
        rm = rate_at_psnr(rs, ps, pt["psnr"])
        rp = psnr_at_rate(rs, ps, pt["mb"])
        out.append({"lmbda": pt["lmbda"], "mb": pt["mb"], "psnr": pt["psnr"], "ref_mb": rm,
                    "size_change": _change(pt["mb"], rm), "ref_psnr": rp,
                    "psnr_change": None if rp is None else pt["psnr"] - rp})
    return out


def compute_bd(results: dict) -> list[dict]:
    """BD-rate (size in MB) and BD-PSNR (decoded PSNR) of each method against the baseline, then
    of each method against every contender it extends (:func:`nested_references`); each item
    names its reference in ``against``.

    With seeds (``pgs compare --seeds``): one item per seed (the method's and the reference's
    runs of that seed) and one on the seed-mean curves (``seed`` = "mean": per lambda the mean
    size and PSNR over the seeds), the comparison's answer; the per-seed items show its spread.
    """
    seeds = seeds_of(results)
    out = []
    for m, ref in bd_pairs(results):
        if not seeds:
            out.append(_bd_item(m, None, runs_of(results, ref), runs_of(results, m), ref))
            continue
        for sd in seeds:
            out.append(_bd_item(m, sd, runs_of(results, ref, sd), runs_of(results, m, sd), ref))
        out.append(_bd_item(m, "mean", seed_mean_points(results, ref),
                            seed_mean_points(results, m), ref))
    return out


def bd_against(results: dict, item: dict) -> str:
    """The method a BD item measures against (records from before nested references: the
    baseline)."""
    return item.get("against") or results.get("baseline", "baseline")


# ------------------------------------------------------------------------------ formatting
def _f(x, nd: int, unit: str = "") -> str:
    if x is None:
        return "-"
    if isinstance(x, float) and not math.isfinite(x):
        return str(x)
    return f"{x:.{nd}f}{unit}"


def _pct(x: Optional[float]) -> str:
    return "-" if x is None else f"{x:+.1f}%"


def _saving(value: float, ref: Optional[float]) -> Optional[float]:
    """Saving in percent against ``ref`` (positive = smaller than the baseline)."""
    if ref is None or ref == 0:
        return None
    return 100.0 * (1.0 - value / ref)


def _change(value: float, ref: Optional[float]) -> Optional[float]:
    if ref is None or ref == 0:
        return None
    return 100.0 * (value / ref - 1.0)


def _is_base(results: dict, r: dict) -> bool:
    return r["method"] == results.get("baseline", "baseline")


def _lam(r: dict) -> str:
    """The rate point of a run: its lambda, and its seed in a comparison with seeds."""
    return f"{r['lmbda']:g}" + (f" s{r['seed']}" if r.get("seed") is not None else "")


def ssim_convention(r: dict) -> str:
    """Which SSIM a row's "ssim" is (:data:`baseline.eval.metrics.SSIM_CONVENTIONS`): rows and
    records from before the convention was kept hold scikit-image's."""
    return r.get("ssim_convention") or "skimage"


def field_ssim(r: dict) -> float | None:
    """A row's SSIM as 3DGS / HAC compute it (the field's tables), None where it was not
    measured (records that hold scikit-image's only)."""
    return r.get("ssim") if ssim_convention(r) == "3dgs" else None


def _ssim_cell(results: dict, r: dict) -> str:
    """A row's SSIM; where the report's rows mix conventions, the rows of the minority
    convention say theirs ("0.9521 (skimage)"), so no two conventions stand side by side
    unmarked."""
    v = _f(r.get("ssim"), 4)
    conv = ssim_convention(r)
    return v if conv == _main_ssim_convention(results) or v == "-" else f"{v} ({conv})"


def _main_ssim_convention(results: dict) -> str:
    rows = list(results.get("runs", [])) + ([results["reference"]] if results.get("reference")
                                            else [])
    convs = [ssim_convention(r) for r in rows]
    if not convs:
        return "3dgs"
    return max(sorted(set(convs)), key=lambda c: (convs.count(c), c == "3dgs"))


def ssim_note(results: dict) -> str:
    """One line: which SSIM the report's figures are (and which rows are the other one's)."""
    from baseline.eval.metrics import SSIM_CONVENTIONS

    main = _main_ssim_convention(results)
    note = f"SSIM: {SSIM_CONVENTIONS.get(main, main)}"
    rows = list(results.get("runs", [])) + ([results["reference"]] if results.get("reference")
                                            else [])
    other = sorted({ssim_convention(r) for r in rows} - {main})
    if other:
        note += ("; rows marked " + ", ".join(f"({c})" for c in other) + " hold "
                 + "; ".join(SSIM_CONVENTIONS.get(c, c) for c in other)
                 + ", measured before the field's SSIM was (their records were written then)")
    elif main == "skimage":
        note += ": these records were measured before the field's SSIM was kept"
    return note + "."


class Table:
    def __init__(self, title: str, headers: list[str], rows: list[list[str]], notes=(),
                 left: int = 1):
        self.title, self.headers, self.rows, self.notes, self.left = title, headers, rows, list(notes), left

    def text(self) -> str:
        cols = list(zip(self.headers, *self.rows)) if self.rows else [(h,) for h in self.headers]
        w = [max(len(str(c)) for c in col) for col in cols]

        def line(cells):
            return "  ".join(str(c).ljust(w[i]) if i < self.left else str(c).rjust(w[i])
                             for i, c in enumerate(cells)).rstrip()

        out = [self.title, "=" * len(self.title), line(self.headers),
               "  ".join("-" * x for x in w)]
        out += [line(r) for r in self.rows]
        out += [f"  {n}" for n in self.notes]
        return "\n".join(out)

    def markdown(self) -> str:
        align = ["---" if i < self.left else "---:" for i in range(len(self.headers))]
        out = [f"### {self.title}", "", "| " + " | ".join(self.headers) + " |",
               "|" + "|".join(align) + "|"]
        out += ["| " + " | ".join(str(c) for c in r) + " |" for r in self.rows]
        if self.notes:
            out.append("")
            out += [f"{n}  " for n in self.notes]
        return "\n".join(out)


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
             "of the trained model before coding. MB = file bytes / 2^20; size change vs the "
             "baseline at the same rate point.",
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
    """Where in the schedule a method falls behind (:mod:`baseline.eval.curves`): each run's
    mean training L1 per span of its schedule (six equal spans), and the sampled bits per anchor
    of the rate term in the last span, with the change vs the baseline's run at the same rate
    point and seed. None when no run kept its curve (records archived before it was kept)."""
    from baseline.eval.curves import curve_cells, span_headers

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


def _with_change(results: dict, r: dict, key: str, fmt: Callable[[float], str]) -> str:
    """``r[key]`` formatted, with its change vs the baseline at the same rate point in brackets
    (none on the baseline's own row); '-' when the record has no such value."""
    v = r.get(key)
    if v is None:
        return "-"
    if _is_base(results, r):
        return fmt(v)
    p = baseline_partner(results, r)
    return f"{fmt(v)} ({_pct(_change(v, p and p.get(key)))})"


def _count(v: float) -> str:
    return f"{v:.0f}"


def _share(v: float) -> str:
    return f"{100 * v:.1f}%"


def _not_shown(results: dict, kept: Callable[[dict], bool], what: str) -> list[str]:
    """A note naming the runs a table leaves out: records archived before ``what`` kept."""
    skipped = [f"{label(results, r['method'])} {_lam(r)}" for r in ordered_runs(results) if not kept(r)]
    return ([f"not shown (records archived before {what} kept): " + ", ".join(skipped)]
            if skipped else [])


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


def _one_thread_count(r: dict) -> Optional[int]:
    """The thread count a run trained at throughout; None where it changed on a resume or was
    not recorded (such a run's training time mixes counts and compares with no other)."""
    segs = r.get("threads_by_iteration")
    counts = {t for _, t in segs} if segs else {r.get("threads")}
    return counts.pop() if len(counts) == 1 and None not in counts else None


# A training time whose stall share (time the process ran on no core) exceeds this measures
# the machine's load, not the method: a healthy one-thread run beside another measured 1%.
STALL_LIMIT = 0.05
# ... and whose stall time exceeds this many seconds: a short run's start-up (kernels loaded
# from numba's cache, images read) stalls a few seconds on a quiet machine (a 100 s demo run:
# 6 s, 6%), which is no load; a paused or core-sharing run stalls minutes.
STALL_FLOOR_S = 30.0


def stall_share(r: dict) -> Optional[float]:
    """The share of a run's training time in which it ran on no core (paused, or sharing its
    core), from its record; None where not recorded (GPU runs, older records)."""
    if r.get("stall_s") is None or not r.get("train_time_s"):
        return None
    return float(r["stall_s"]) / float(r["train_time_s"])


def stalled(r: dict) -> bool:
    """A run whose training time stalled beyond STALL_LIMIT of it and beyond STALL_FLOOR_S
    seconds: it measures no cost."""
    sh = stall_share(r)
    return sh is not None and sh > STALL_LIMIT and float(r["stall_s"]) > STALL_FLOOR_S


def _stall_words(r: dict) -> str:
    """"840 s (12%) stalled", with where counting began when not at iteration 0."""
    frm = f", counted from iteration {r['stall_from']}" if r.get("stall_from") else ""
    return f"{r['stall_s']:.0f} s ({stall_share(r):.0%}{frm}) stalled"


def untimed(r: dict) -> Optional[str]:
    """Why a run's training time is no measurement of its cost, or None where it stands:
    stalled beyond STALL_LIMIT, marked in its record (``pgs compare --untimed``) for what the
    record cannot show, or resumed on another machine (or from a checkpoint that did not keep
    its machine): its time then sums stretches of different machines. Every reason that
    holds, joined."""
    why = [_stall_words(r) if stalled(r) else None, r.get("untimed") or None,
           "resumed on another machine or from one not recorded: " + _machines_shown(r)
           if r.get("machines_by_iteration") else None]
    return "; ".join(w for w in why if w) or None


def train_time_pairs(results: dict, method: str, base: str) -> tuple[list, list]:
    """The (method run, baseline run) pairs whose training times compare: the same lambda and
    seed, each trained at one thread count throughout, the same count for both, neither
    untimed (stalled beyond STALL_LIMIT of its time and STALL_FLOOR_S, or marked); and the
    method's runs whose
    time does not compare with the baseline's run at their rate point, each as (run, why). A
    rate point the baseline has no run at is neither (nothing to compare with)."""
    pairs, left = [], []
    bruns = runs_of(results, base)
    for r in runs_of(results, method):
        b = next((x for x in bruns if x["lmbda"] == r["lmbda"]
                  and x.get("seed") == r.get("seed")), None)
        if b is None:
            continue
        t, tb = _one_thread_count(r), _one_thread_count(b)
        if t is None:
            left.append((r, "its thread count changed on a resume or is unrecorded"))
        elif tb is None:
            left.append((r, "the baseline run's thread count changed on a resume or is "
                            "unrecorded"))
        elif t != tb:
            left.append((r, f"{t} thread(s) against {tb}"))
        elif why := untimed(r):
            left.append((r, why))
        elif why := untimed(b):
            left.append((r, f"the baseline run: {why}"))
        elif r.get("machine") and b.get("machine") and r["machine"] != b["machine"]:
            left.append((r, f"trained on {r['machine']}, the baseline run on {b['machine']}"))
        else:
            pairs.append((r, b))
    return pairs, left


def train_time_ratio(results: dict, m: str, base: str) -> dict | None:
    """The training-time ratio of ``m`` to ``base`` over the pairs of train_time_pairs only (a
    mean over runs of other lambdas or thread counts would mix the schedule's cost with the
    machine's): ``{ratio, mean_s, ref_mean_s, pairs}``, the ratio computed from the two means
    it is printed beside; None without a pair."""
    pairs, _ = train_time_pairs(results, m, base)
    if not pairs:
        return None
    tm = sum(r["train_time_s"] for r, _ in pairs) / len(pairs)
    tb = sum(b["train_time_s"] for _, b in pairs) / len(pairs)
    return {"ratio": tm / tb, "mean_s": tm, "ref_mean_s": tb, "pairs": len(pairs)}


def fps_ratio(results: dict, m: str) -> dict | None:
    """The paired FPS measurement of ``m`` against the baseline (``results["fps_pair"]``) with
    its ratio recomputed from the two FPS figures it is printed beside (records written before
    kept the median of per-round ratios, which need not equal their ratio)."""
    fp = (results.get("fps_pair") or {}).get(m)
    if not fp or not fp.get("fps_ref"):
        return None
    return dict(fp, ratio=fp["fps"] / fp["fps_ref"])


def _train_time_line(results: dict, m: str, base: str, name: str, bname: str) -> Optional[str]:
    """The verdict's training-time ratio (:func:`train_time_ratio`) and the runs left out."""
    pairs, left = train_time_pairs(results, m, base)
    if not pairs:
        return None if not left else (
            f"{name}'s training time compares with no {bname} run (the same rate point, one "
            f"thread count throughout, the same for both)")
    tr = train_time_ratio(results, m, base)
    th = "/".join(str(t) for t in sorted({_one_thread_count(r) for r, _ in pairs}))
    out = (f"{name} trains in {tr['ratio']:.2f}x {bname}'s time ({tr['mean_s']:.0f} s vs "
           f"{tr['ref_mean_s']:.0f} s per run; {len(pairs)} pair(s) at the same rate point, "
           f"{th} thread(s) each")
    if left:
        out += "; left out: " + ", ".join(f"{_lam(r)} ({why})" for r, why in left)
    return out + ")"


def _threads_shown(r: dict) -> str:
    """A run's thread count; a run resumed at another count names each from its first
    iteration ("1 from iteration 0, then 2 from iteration 2669"; "unrecorded" where the
    checkpoint it resumed from did not keep it)."""
    return _stretches_shown(r, "threads", "threads_by_iteration")


def _machines_shown(r: dict) -> str:
    """A run's machine (``-`` in records from before machines were kept); a run resumed on
    another one names each from its first iteration, as _threads_shown."""
    return _stretches_shown(r, "machine", "machines_by_iteration")


def _stretches_shown(r: dict, key: str, by_iteration: str) -> str:
    segs = r.get(by_iteration)
    if not segs:
        return str(r.get(key) or "-")
    return ", then ".join(f"{'unrecorded' if v is None else v} from iteration {i}"
                          for i, v in segs)


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


def rate_elements(row: dict) -> Optional[int]:
    """Coded values per anchor of a run (the sum of its coded attributes' dims; offsets count
    all K x 3 whatever the masks), read from its record; None for records kept without them."""
    fixed = int(row.get("rate_values_per_anchor") or 0)
    if fixed > 0:       # entropy.rate_values_per_anchor set: every method divides by it
        return fixed
    attrs = row.get("attributes")
    return sum(int(a["dims"]) for a in attrs) if attrs else None


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


def _curve_points(results: dict, method: str) -> list[dict]:
    """A method's points (lmbda, bytes, psnr): the seed means with seeds, else its runs."""
    if seeds_of(results):
        return seed_mean_points(results, method)
    return [{"lmbda": r["lmbda"], "bytes": r["bytes"], "mb": r["mb"], "psnr": r["psnr"]}
            for r in runs_of(results, method)]


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


def _missing_text(results: dict) -> str:
    missing = results.get("missing") or []
    if not missing:
        return "some runs have not finished."
    return (f"{len(missing)} run(s) not run yet ({', '.join(missing)}); the same `pgs compare` "
            f"without --report-only trains them.")


def format_report(results: dict, markdown: bool = False) -> str:
    tables = all_tables(results)
    prot = protocol_lines(results)
    if markdown:
        parts = ["# Comparison report", "",
                 f"Scene `{results.get('scene', '-')}`; baseline "
                 f"{label(results, results.get('baseline', 'baseline'))}; "
                 f"every number is measured on the decoded `.pgs` file or read from the runs' "
                 f"records ({len(results['runs'])} runs)."]
        if not results.get("complete", True):
            parts.append("\n**Incomplete comparison**: " + _missing_text(results))
        verdict = verdict_lines(results)
        vt = verdict_table(results)
        if vt is not None:
            parts += ["", vt.markdown()]
        if verdict:
            parts += ["", "### Verdict" if vt is None else "Caveats and readings:", ""]
            parts += [f"- {v}" if not v.startswith("  ") else f"  - {v.strip()}"
                      for v in verdict]
        for t in tables:
            parts += ["", t.markdown()]
        parts += ["", "### Protocol", ""] + [f"- **{k}**: {v}" for k, v in prot]
        plots = results.get("plots") or {}
        if plots:
            parts += ["", "### Plots", ""] + [f"![{k}]({Path(v).name})" for k, v in plots.items()]
        panels = results.get("panels") or []
        if panels:
            parts += ["", "### Where the methods differ", "",
                      "Per rate point and test view, from each method's decoded file: its "
                      "render, its per-pixel error against the ground truth (mean over RGB, "
                      "grey levels; one colour scale per panel) and its bit map (each anchor's "
                      "coded bits, under the file's own probabilities, at the pixel its centre "
                      "projects to; one colour scale per panel). The bit map holds per-anchor "
                      "bits only: under it, the file's total split into per-anchor bits and the "
                      "shared sections no pixel owns (positions, masks, grids, networks, header), "
                      "which methods split very differently. Single images (with their colour "
                      "bars) and arrays beside each panel in `panels/`."]
            for p in panels:
                rel = Path(p["panel"]).relative_to(Path(p["panel"]).parents[2])
                parts += ["", f"![lambda {p['lmbda']:g}, view {p['view']}]({rel.as_posix()})"]
                if p.get("missing"):
                    parts.append(f"(not drawn, no model file: {', '.join(p['missing'])})")
        parts += ["", "### CSV files", "",
                  "`results.csv` beside this report: every run, one row each (method, lambda, "
                  "seed, PSNR, SSIM with its convention, LPIPS, size, #Gaussians). "
                  f"`survey/<method>/{survey_dataset(results)}/"
                  f"{Path(results.get('scene', 'scene')).name}.csv`: each method's points in "
                  "the 3DGS compression survey's layout (Submethod, PSNR, SSIM, LPIPS, Size "
                  "[Bytes], #Gaussians; one file per method and scene, the highest and lowest "
                  "rate named <method>-highrate / -lowrate, the others unnamed as the survey "
                  "asks" + ("; seed means" if seeds_of(results) else "")
                  + "). #Gaussians counts the neural Gaussians the file codes (Gaussian masks "
                  "on: every Gaussian a view of the decoded model can draw); LPIPS is empty "
                  "when it was not measured, SSIM when only scikit-image's was."]
        return "\n".join(parts) + "\n"
    parts = [t.text() for t in tables]
    if not results.get("complete", True):
        parts.insert(0, "Incomplete comparison: " + _missing_text(results))
    w = max(len(k) for k, _ in prot)
    parts.append("Protocol\n========\n" + "\n".join(f"{k.ljust(w)}  {v}" for k, v in prot))
    verdict = verdict_lines(results)
    vt = verdict_table(results)
    if vt is not None:   # last, where a terminal leaves the reader
        parts.append(vt.text() + ("\n\n" + "\n".join(verdict) if verdict else ""))
    elif verdict:
        parts.append("Verdict\n=======\n" + "\n".join(verdict))
    return "\n\n".join(parts)


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


def write_report(results: dict, out_dir: str | Path, plots: bool = True,
                 panel_views: Optional[list] = None) -> dict:
    """Write ``report.md`` (+ the PNG plots, the survey CSV and, with ``plots``, the panels of
    test views ``panel_views``, default ``[0]``; ``[]`` for none) into ``out_dir``; returns the
    written paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    results["bd"] = compute_bd(results)
    paths = {}
    if plots and results["runs"]:
        from baseline.eval.panel import write_panels
        from baseline.eval.plots import write_plots

        results["plots"] = {k: str(v) for k, v in write_plots(results, out_dir).items()}
        paths.update({k: Path(v) for k, v in results["plots"].items()})
        results["panels"] = write_panels(results, out_dir, panel_views)
        for i, p in enumerate(results["panels"]):
            paths[f"panel{i}"] = Path(p["panel"])
    paths["csv"] = _write_csv(runs_rows(results), RUNS_COLUMNS, out_dir / "results.csv")
    for i, f in enumerate(write_survey(results, out_dir / "survey")):
        paths[f"survey{i}"] = f
    md = out_dir / "report.md"
    write_text_atomic(md, format_report(results, markdown=True))
    paths["report"] = md
    return paths
