"""The experiment runner: ``pgs compare`` (train, encode, decode and measure several methods on one
scene, side by side), ``pgs benchmark`` (one comparison per scene of a dataset) and the executors
that run their jobs.

A *method* is a set of patches on top of the common ones (``--patch``): the baseline is the
plain configuration (Scaffold-GS + HAC unless a common patch says otherwise); each ``--vs
P1+P2`` adds one contender. Every (method, lambda) pair is one *run*, in its own folder
``DIR/runs/<method>-l<lambda>-<config hash>``; the hash covers the whole merged config, so a
changed setting never reuses a stale run.

A run goes through three stages, each recorded as soon as it is done, so an interrupted
comparison picks up where it stopped:

1. **train** -- ``baseline.run.train_run(resume=True)``: a run interrupted mid-training continues
   from its checkpoint; done when ``results.json`` holds the test metrics at the configured
   iteration count.
2. **encode** -- ``encode_model`` to ``model.pgs`` (written atomically); done when
   ``compare.json`` records the encode and the file on disk has the recorded byte count.
3. **decoded** -- ``decode_model`` the file alone and evaluate the *decoded* model on the test
   views (PSNR / SSIM / LPIPS on uint8 images, FPS); models whose feature provider keeps a
   decoded-model cache (``build_cache`` / ``clear_cache``) are timed with and
   without it. Done when ``compare.json`` holds these (with LPIPS if weights are given now);
   the views are in ``RUN/decoded/`` (``renders/``, ``gt/``, ``per_view.json``: 3DGS's layout).

A run folder reduced to its records (``config.toml``, ``scene.json``, ``results.json``,
``compare.json``: no checkpoint, no model file) counts as finished and is reported from them, so
finished runs can be archived and a comparison completed later, on another machine, by copying
them into its ``--out`` folder; only the missing runs are trained.

``--codec PATCH`` (a patch that sets only ``[codec]`` keys, e.g. ``compact-codec``) applies
codec settings at the encode stage of every run without touching training: a run recorded with
other codec settings is encoded, decoded and measured again; its training is reused.

Every number in the report is measured in one of these stages or read from their records.

Modules: :mod:`~baseline.experiment.plan` (methods, run specs), :mod:`~baseline.experiment.records`
(what is done, result rows, archiving), :mod:`~baseline.experiment.stages` (one run's stages),
:mod:`~baseline.experiment.runner` (a comparison), :mod:`~baseline.experiment.executors` (where
jobs run), :mod:`~baseline.experiment.benchmark` (a dataset).
"""
from baseline.experiment.plan import (BASELINE, REFERENCE, Method, RunSpec, parse_methods,
                                      parse_reference, plan_reference, plan_runs, resolve_method,
                                      with_own_lambdas)
from baseline.experiment.records import (RECORD, RECORD_FILES, archive_records, codec_overrides,
                                         is_compare_folder, is_finished, lpips_id, make_row,
                                         mark_untimed, records_only)
from baseline.experiment.runner import paired_fps_bench, run_compare
from baseline.experiment.stages import float32_bytes, run_one, run_reference

__all__ = ["BASELINE", "REFERENCE", "RECORD", "RECORD_FILES", "Method", "RunSpec",
           "archive_records", "codec_overrides", "float32_bytes", "is_compare_folder",
           "is_finished", "lpips_id", "make_row", "mark_untimed", "paired_fps_bench",
           "parse_methods", "parse_reference", "plan_reference", "plan_runs", "records_only",
           "resolve_method", "run_compare", "run_one", "run_reference", "with_own_lambdas"]
