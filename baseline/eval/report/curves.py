"""A run's training curve in a few numbers: where in its schedule a method falls behind.

The training log (``train_log.jsonl``, one line every ``train.log_every`` iterations) is cut into
``windows`` equal spans of the schedule; each span keeps the mean training L1 of the sampled
views, the mean sampled bits per coded value of the rate term (once it is on), the mean
Gaussians drawn per training view, the anchors at the span's end and the anchors grown and
pruned in the span. A comparison stores this
summary in each run's record (``compare.json``), so archived records keep it without the log.

What the numbers are: L1 and bits are those of the sampled training view of each logged step,
so a span's mean moves between seeds (truck, HAC, seeds 0 and 1: by 1-4% per span); a method that
trains on downsampled views (a progressive schedule: its method spec's training_curve note says where)
has its L1 there on smaller, smoother images.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

from baseline.eval.report.cells import Table, _change, _pct
from baseline.eval.report.names import rate_elements

WINDOWS = 6


def _mean(xs: list) -> Optional[float]:
    return sum(xs) / len(xs) if xs else None


def read_log(path: str | Path) -> list[dict]:
    """The lines of a training log; a torn or foreign line ends it (as the trainer does)."""
    from baseline.fileio import read_text_bounded

    out = []
    for line in read_text_bounded(path, "a training log").splitlines():
        try:
            d = json.loads(line)
            int(d["it"])
        except (ValueError, KeyError, TypeError):
            break
        out.append(d)
    return out


def span_bounds(ends: list[int]) -> list[int]:
    """The bounds of spans ending at the iterations ``ends`` (strictly increasing, positive),
    the first starting at 0."""
    ends = [int(e) for e in ends]
    if not ends or ends[0] < 1 or any(b <= a for a, b in zip(ends, ends[1:])):
        raise ValueError(f"span ends must be positive and increasing, got {ends}")
    return [0] + ends


def summarize(entries: list[dict], iterations: Optional[int] = None,
              windows: int = WINDOWS, ends: Optional[list[int]] = None) -> Optional[dict]:
    """The windowed summary of log ``entries`` over ``[0, iterations]`` (default: the last
    logged iteration), or over the spans ending at ``ends`` when given. None when the log is
    empty. Lists hold one value per window, None for a window with nothing logged (or, for
    ``bits_per_value``, before the rate term is on)."""
    if windows < 1:
        raise ValueError(f"windows must be >= 1, got {windows}")
    if not entries:
        return None
    if ends:
        bounds = span_bounds(ends)
        total = bounds[-1]
    else:
        total = int(iterations) if iterations else max(int(e["it"]) for e in entries)
        bounds = [round(total * k / windows) for k in range(windows + 1)]
    out = {"iterations": total, "bounds": bounds, "l1": [], "bits_per_value": [],
           "gaussians": [], "anchors": [], "grown": [], "pruned": []}
    before: Optional[dict] = None          # the last entry logged at or before the span
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        span = [e for e in entries if lo < int(e["it"]) <= hi]
        out["l1"].append(_mean([float(e["l1"]) for e in span if e.get("l1") is not None]))
        out["bits_per_value"].append(_mean([float(e["bpp"]) for e in span if e.get("bpp") is not None]))
        out["gaussians"].append(_mean([float(e["gaussians"]) for e in span
                                       if e.get("gaussians") is not None]))
        out["anchors"].append(int(span[-1]["anchors"]) if span and "anchors" in span[-1] else None)
        for key in ("grown", "pruned"):
            out[key].append(_added_in(span, before, key))
        before = span[-1] if span else before
    return out


def _added_in(span: list[dict], before: Optional[dict], key: str) -> Optional[int]:
    """How much the log's running count ``key`` rose over a span: its value at the span's last
    entry minus its value at ``before``, the last entry logged before the span (0 without one);
    None for an empty span or where the log does not carry the count."""
    if not span or key not in span[-1]:
        return None
    if before is None:
        return int(span[-1][key])
    return int(span[-1][key]) - int(before[key]) if key in before else None


def train_curve(run_dir: str | Path, iterations: Optional[int] = None,
                windows: int = WINDOWS, ends: Optional[list[int]] = None) -> Optional[dict]:
    """:func:`summarize` of the run's ``train_log.jsonl`` over ``iterations`` (default: the
    run's configured schedule, so a run still training shows its later spans empty) or the
    spans ending at ``ends``; None without a log."""
    from baseline.train.trainer import TRAIN_LOG_NAME

    path = Path(run_dir) / TRAIN_LOG_NAME
    if not path.is_file():
        return None
    return summarize(read_log(path), iterations or _schedule(run_dir), windows, ends)


def _record(run_dir: str | Path) -> dict:
    """The run's comparison record (``compare.json``); {} when it is missing or unreadable."""
    from baseline.fileio import read_json_bounded

    try:
        rec = read_json_bounded(Path(run_dir) / "compare.json", "a run's record")
    except (OSError, ValueError):
        return {}
    return rec if isinstance(rec, dict) else {}


def recorded_curve(run_dir: str | Path) -> Optional[dict]:
    """The summary a comparison stored in the run's record (``compare.json``), which archived
    runs keep without their log; None when there is none."""
    try:
        c = _record(run_dir)["train_curve"]
        n = len(c["bounds"]) - 1
        if n >= 1 and all(len(c[k]) == n for k in ("l1", "bits_per_value", "gaussians", "anchors")):
            return c
    except (OSError, ValueError, KeyError, TypeError):
        pass
    return None


def _schedule(run_dir: str | Path) -> Optional[int]:
    """``train.iterations`` of a run's config.toml; None when it cannot be read."""
    import tomllib

    from baseline.fileio import read_text_bounded

    try:
        return int(tomllib.loads(read_text_bounded(Path(run_dir) / "config.toml", "a run's config"))
                   ["train"]["iterations"])
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _cell(v: Optional[float], ref: Optional[float], nd: int) -> str:

    if v is None:
        return "-"
    ch = _change(v, ref)
    return f"{v:.{nd}f}" if ch is None else f"{v:.{nd}f} ({_pct(ch)})"


def span_headers(curves: list[dict], prefix: str = "L1 ") -> list[str]:
    """Column heads of the spans (``prefix`` before each): iteration ranges when every curve has
    the same bounds."""
    n = len(curves[0]["l1"])
    b = curves[0]["bounds"]
    if all(c["bounds"] == b for c in curves):
        return [f"{prefix}it {b[k] + 1}-{b[k + 1]}" for k in range(n)]
    return [f"{prefix}{k + 1}/{n} of the schedule" for k in range(n)]


def curve_cells(curve: dict, values_per_anchor: Optional[int], ref: Optional[dict] = None,
                ref_values_per_anchor: Optional[int] = None) -> list[str]:
    """One table row's cells: the L1 of each span and the last span's sampled bits per anchor
    (bits per coded value x ``values_per_anchor``), each with its change vs ``ref`` when given
    (a reference curve with the same number of spans)."""
    paired = ref is not None and len(ref["l1"]) == len(curve["l1"])
    cells = [_cell(v, ref["l1"][k] if paired else None, 4) for k, v in enumerate(curve["l1"])]

    def bits(c, e):
        v = c["bits_per_value"][-1]
        return None if v is None or not e else v * e

    mine = bits(curve, values_per_anchor)
    theirs = bits(ref, ref_values_per_anchor) if paired else None
    return cells + [_cell(mine, theirs, 1)]


def values_per_anchor(run_dir: str | Path) -> Optional[int]:
    """The coded values per anchor a run's rate term divides by: ``entropy.rate_values_per_anchor``
    when set, else the sum of its coded attributes' dims (from its comparison record); None when
    neither is recorded."""
    import tomllib

    from baseline.fileio import read_text_bounded

    run_dir = Path(run_dir)
    row = {}
    try:
        row["rate_values_per_anchor"] = (tomllib.loads(read_text_bounded(run_dir / "config.toml",
                                                                         "a run's config"))
                                         .get("entropy", {}).get("rate_values_per_anchor", 0))
    except (OSError, ValueError, TypeError):
        pass
    try:
        row["attributes"] = _record(run_dir)["encode"]["attributes"]
    except (KeyError, TypeError):
        pass
    return rate_elements(row) or None


def _curve_of(run: str | Path, windows: int, ends: Optional[list[int]]) -> dict:
    """A run folder's curve from its log, or else from its record when the record's spans are
    the ones asked for (``windows`` equal spans of the schedule, or the spans ending at
    ``ends``); ValueError naming what is missing otherwise."""
    c = train_curve(run, None, windows, ends)
    if c is not None:
        return c
    rec = recorded_curve(run)
    if rec is None:
        raise ValueError(f"{run}: no training log (train_log.jsonl) in this folder")
    b = rec["bounds"]
    if (b == span_bounds(ends)) if ends else len(b) == windows + 1:
        return rec
    raise ValueError(f"{run}: no training log (train_log.jsonl) in this folder, and its record "
                     f"holds only the spans ending at {' '.join(str(x) for x in b[1:])} "
                     f"(--windows {len(b) - 1})")


def _growth_cell(c: dict, k: int) -> str:
    """'anchors / Gaussians' of span k in thousands ('-' for what was not logged)."""
    a, g = c["anchors"][k], c["gaussians"][k]
    if a is None and g is None:
        return "-"
    return " / ".join("-" if v is None else f"{v / 1e3:.1f}k" for v in (a, g))


def format_curves(runs: list[str | Path], windows: int = WINDOWS,
                  ends: Optional[list[int]] = None) -> str:
    """``pgs curves``: the curves of run folders as tables (training L1 and the rate's bits;
    anchors and Gaussians drawn), the first run as the reference; ``ends``: span ends in
    iterations instead of ``windows`` equal spans of each schedule."""

    items = []
    for r in runs:
        items.append((Path(r).name, _curve_of(r, windows, ends), values_per_anchor(r)))
    ref = items[0]
    rows = [[name] + curve_cells(c, e, None if i == 0 else ref[1], ref[2])
            for i, (name, c, e) in enumerate(items)]
    spans = (f"each span ending at {', '.join(str(x) for x in ends)}" if ends
             else f"each of {windows} equal spans of each run's schedule")
    notes = [f"The mean L1 of the sampled training views over {spans}, and the rate term's "
             "sampled bits per anchor over the last span ('-' where not recorded); in brackets "
             f"the change vs {ref[0]}."]
    curves = [c for _, c, _ in items]
    l1 = Table("Training curves", ["run"] + span_headers(curves) + ["bits/anchor, last span"],
               rows, notes).text()
    growth = Table("Anchors and Gaussians", ["run"] + span_headers(curves, prefix=""),
                   [[name] + [_growth_cell(c, k) for k in range(len(c["anchors"]))]
                    for name, c, _ in items],
                   ["Each span: the anchors at its last logged step / the mean neural Gaussians "
                    "drawn per sampled training view (a progressive schedule's early views are "
                    "downsampled)."]).text()
    text = l1 + "\n" + growth
    if any(v is not None for c in curves for v in c.get("grown", [])):
        text += "\n" + Table(
            "Growing and pruning", ["run"] + span_headers(curves, prefix=""),
            [[name] + [_grown_pruned_cell(c, k) for k in range(len(c["anchors"]))]
             for name, c, _ in items],
            ["Each span: anchors grown / anchors pruned in it ('-' where the log does not count "
             "them: logs written before the counts were kept)."]).text()
    return text


def _grown_pruned_cell(c: dict, k: int) -> str:
    """'+grown / -pruned' of span k in thousands ('-' where not counted)."""
    g, p = (c.get(key, [None] * (k + 1))[k] for key in ("grown", "pruned"))
    if g is None or p is None:
        return "-"
    return f"+{g / 1e3:.1f}k / -{p / 1e3:.1f}k"
