"""The comparison report: tables for the terminal and ``report.md``, computed from stored results.

Input is the ``results.json`` structure written by :func:`baseline.experiment.run_compare`
(``runs``: one flat row per method and lambda, see :func:`baseline.experiment.make_row`).
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

The parts, each importing only those above it: :mod:`.names` (what methods and runs are called;
queries of ``results.json``), :mod:`.cells` (one cell; :class:`Table`), :mod:`.bd` (Bjontegaard
deltas), :mod:`.timing` (train time and speed), :mod:`.curves` (training curves), :mod:`.tables`,
:mod:`.verdict`, :mod:`.survey` (CSV files); :mod:`.plots` and :mod:`.panel` draw the figures.
This module joins them into the text report and writes the report folder.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

from baseline.fileio import write_text_atomic
from baseline.eval.report.names import (base_label, BASELINE_LABEL, baseline_partner, field_ssim,
                                        GROUP_ORDER, label, MB, method_label, method_names,
                                        method_notes, ordered_runs, others_bytes, rate_elements,
                                        rate_points, runs_of, seed_mean_points, _seed_order,
                                        seeds_of, ssim_convention)
from baseline.eval.report.cells import (_change, _count, _f, _is_base, _lam, _main_ssim_convention,
                                        _not_shown, _pct, _saving, _share, _ssim_cell, ssim_note,
                                        Table, _with_change)
from baseline.eval.report.bd import (bd_against, _bd_item, BD_MIN_POINTS, bd_pairs, BD_THIN_OVERLAP,
                                     compute_bd, _curve_points, method_patches, nested_references,
                                     point_readings)
from baseline.eval.report.timing import (fps_ratio, _machines_shown, _one_thread_count,
                                         STALL_FLOOR_S, STALL_LIMIT, stall_share, _stall_words,
                                         stalled, _stretches_shown, _threads_shown,
                                         _train_time_line, train_time_pairs, train_time_ratio,
                                         untimed)
from baseline.eval.report.tables import (alive_table, all_tables, _attr_rows, bd_caveats, bd_table,
                                         census_table, _codec_line, curve_table, elements_table,
                                         groups_table, _label, _lpips_note, _overlap_cell,
                                         point_table, protocol_lines, quality_table,
                                         _rate_term_line, _reference_line, reference_table,
                                         section_tables, seed_table, _semantics_line, _SIGNS,
                                         _signs_disagree, speed_table, table3)
from baseline.eval.report.verdict import verdict_lines, verdict_table
from baseline.eval.report.survey import (_full, gaussians_count, RUNS_COLUMNS, runs_rows,
                                         SURVEY_COLUMNS, survey_dataset, survey_datasets,
                                         survey_rows, _write_csv, write_survey)


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
        from baseline.eval.report.panel import write_panels
        from baseline.eval.report.plots import write_plots

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


# the report's API: every part's names, as they were importable from one module
__all__ = ["BASELINE_LABEL", "BD_MIN_POINTS", "BD_THIN_OVERLAP", "GROUP_ORDER", "MB", "RUNS_COLUMNS",
           "STALL_FLOOR_S", "STALL_LIMIT", "SURVEY_COLUMNS", "Table", "_SIGNS", "_attr_rows",
           "_bd_item", "_change", "_codec_line", "_count", "_curve_points", "_f", "_full",
           "_is_base", "_label", "_lam", "_lpips_note", "_machines_shown",
           "_main_ssim_convention", "_missing_text", "_not_shown", "_one_thread_count",
           "_overlap_cell", "_pct", "_rate_term_line", "_reference_line", "_saving",
           "_seed_order", "_semantics_line", "_share", "_signs_disagree", "_ssim_cell",
           "_stall_words", "_stretches_shown", "_threads_shown", "_train_time_line",
           "_with_change", "_write_csv", "alive_table", "all_tables", "base_label",
           "baseline_partner", "bd_against", "bd_caveats", "bd_pairs", "bd_table",
           "census_table", "compute_bd", "curve_table", "elements_table", "field_ssim",
           "format_report", "fps_ratio", "gaussians_count", "groups_table", "label",
           "method_label", "method_names", "method_notes", "method_patches",
           "nested_references", "ordered_runs", "others_bytes", "point_readings", "point_table",
           "protocol_lines", "quality_table", "rate_elements", "rate_points", "reference_table",
           "runs_of", "runs_rows", "section_tables", "seed_mean_points", "seed_table",
           "seeds_of", "speed_table", "ssim_convention", "ssim_note", "stall_share", "stalled",
           "survey_dataset", "survey_datasets", "survey_rows", "table3", "train_time_pairs",
           "train_time_ratio", "untimed", "verdict_lines", "verdict_table", "write_report",
           "write_survey"]
