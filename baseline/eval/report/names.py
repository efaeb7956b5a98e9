"""What the report calls methods and runs, and the queries of a comparison's ``results.json``
(its ``runs`` rows by method, seed and rate point)."""
from __future__ import annotations

from typing import Optional

from baseline.config import method_specs, patch_labels


MB = 2 ** 20
GROUP_ORDER = ["feature", "anchor", "scaling", "offsets", "masks", "hash", "mlps", "header+framing"]


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


def ssim_convention(r: dict) -> str:
    """Which SSIM a row's "ssim" is (:data:`baseline.eval.metrics.SSIM_CONVENTIONS`): rows and
    records from before the convention was kept hold scikit-image's."""
    return r.get("ssim_convention") or "skimage"


def field_ssim(r: dict) -> float | None:
    """A row's SSIM as 3DGS / HAC compute it (the field's tables), None where it was not
    measured (records that hold scikit-image's only)."""
    return r.get("ssim") if ssim_convention(r) == "3dgs" else None


def rate_elements(row: dict) -> Optional[int]:
    """Coded values per anchor of a run (the sum of its coded attributes' dims; offsets count
    all K x 3 whatever the masks), read from its record; None for records kept without them."""
    fixed = int(row.get("rate_values_per_anchor") or 0)
    if fixed > 0:       # entropy.rate_values_per_anchor set: every method divides by it
        return fixed
    attrs = row.get("attributes")
    return sum(int(a["dims"]) for a in attrs) if attrs else None
