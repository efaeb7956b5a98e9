"""How the report writes one cell (numbers, percentages, changes against the baseline, SSIM
conventions), and :class:`Table`, the one table type every part of the report renders."""
from __future__ import annotations

import math
from typing import Callable, Optional

from baseline.eval.report.names import baseline_partner, label, ordered_runs, ssim_convention


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
