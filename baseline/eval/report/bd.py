"""Bjontegaard deltas of a comparison: which curves are paired, each pair's BD-rate / BD-PSNR
(:mod:`baseline.eval.bdrate`), and each rate point read against the other curve."""
from __future__ import annotations

from typing import Optional

from baseline.eval.bdrate import (bd_psnr, bd_rate, BDError, non_monotone, overlap, psnr_at_rate,
                                  rate_at_psnr)
from baseline.eval.report.names import method_names, runs_of, seed_mean_points, seeds_of
from baseline.eval.report.cells import _change


BD_MIN_POINTS = 3
# A Bjontegaard delta integrates over the PSNR interval both curves cover; below this share of
# the wider curve's PSNR span the report calls the overlap thin (the delta then describes a
# sliver of the curves, and one point moves it far)
BD_THIN_OVERLAP = 1.0 / 3.0


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


def _curve_points(results: dict, method: str) -> list[dict]:
    """A method's points (lmbda, bytes, psnr): the seed means with seeds, else its runs."""
    if seeds_of(results):
        return seed_mean_points(results, method)
    return [{"lmbda": r["lmbda"], "bytes": r["bytes"], "mb": r["mb"], "psnr": r["psnr"]}
            for r in runs_of(results, method)]
