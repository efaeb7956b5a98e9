"""Hostile input, end to end: crafted `.pgs` files (truncations, flips, header fields edited
with valid CRCs, sections swapped between a HAC and a Predict-GS file or removed, declared-size
bombs, deep edits inside sections with the file re-signed) decoded in a worker whose address
space is capped at 1 GiB over its start-up size, through `decode_model`, `pgs info` and
`pgs decode`: zero tracebacks, hangs, cap hits, or silent decodes of a case that must fail.

``PGS_HOSTILE_RANDOM`` sets the random flips per file (default 60: the suite's budget)."""
from __future__ import annotations

import os

from baseline.testing.hostile import crafted_cases, run_cases


def test_hostile_files_are_refused_cleanly(decoded_files, tmp_path):
    import dataclasses

    from baseline.modelfile import encode_model
    from baseline.run import load_run

    files = {name: (decoded_files[name] / "model.pgs").read_bytes()
             for name in ("baseline", "predict-gs")}
    # the compact codec too: sorted positions (their count not fixed by the section's length),
    # mask patterns, used grid entries
    run = decoded_files["predict-gs"]
    t, _ = load_run(run, device="cpu")
    cfg = dataclasses.replace(t.cfg, codec=dataclasses.replace(
        t.cfg.codec, positions="sorted", masks="patterns", grids="used"))
    encode_model(cfg, t.model, t.entropy, tmp_path / "compact.pgs",
                 extra_header={"scene": str(decoded_files["scene"])})
    files["compact"] = (tmp_path / "compact.pgs").read_bytes()
    n = int(os.environ.get("PGS_HOSTILE_RANDOM", "60"))
    cases = crafted_cases(files, n_random=n, seed=0)
    kinds = {k: sum(k in c.name for c in cases) for k in
             ("truncated", "flipped", "header", "taken from", "removed", "re-signed",
              "n_anchors")}
    assert kinds["taken from"] >= 10 and kinds["header"] >= 250 and kinds["re-signed"] >= 50
    # the plugin's config section (in every file's config, as every registered section is),
    # edited past the caps its RANGES declare
    assert sum("header config.predict.residual_dim = 1000000" in c.name for c in cases) == 3
    assert sum("header config.predict.mgrd_hidden" in c.name for c in cases) == 3
    st = run_cases(cases, cap_mb=1024, timeout=120.0)
    assert not st["findings"], "\n".join(f"{n}: {f}" for n, f in st["findings"][:30])
    assert st["decoded"] == sum(not c.must_fail for c in cases)
    assert st["refused"] == sum(c.must_fail for c in cases)


def test_hostile_lattice_position_files_are_refused_cleanly(decoded_files, tmp_path):
    """A file with lattice positions (HAC++'s kind of coding): its octree stream's head edited
    (depth, origin, voxel size), its payload replaced (dense all-ones claims, zeros, none) and
    the file truncated or flipped: refused cleanly, never a crash or a blow-up."""
    import dataclasses

    from baseline.modelfile import encode_model
    from baseline.run import load_run

    run = decoded_files["baseline"]
    t, _ = load_run(run, device="cpu")
    cfg = dataclasses.replace(t.cfg, codec=dataclasses.replace(t.cfg.codec, positions="lattice"))
    encode_model(cfg, t.model, t.entropy, tmp_path / "lattice.pgs",
                 extra_header={"scene": str(decoded_files["scene"])})
    files = {"lattice": (tmp_path / "lattice.pgs").read_bytes()}
    cases = [c for c in crafted_cases(files, n_random=20, seed=1)
             if "positions" in c.name or "truncated" in c.name or "flipped" in c.name]
    assert sum("positions:" in c.name for c in cases) >= 15
    st = run_cases(cases, cap_mb=1024, timeout=120.0)
    assert not st["findings"], "\n".join(f"{n}: {f}" for n, f in st["findings"][:30])
    assert st["refused"] == sum(c.must_fail for c in cases)


def test_special_and_sparse_inputs_are_refused_cleanly(decoded_files):
    """Inputs that are not a file's bytes: /proc/self/pagemap (size 0, never ends), /dev/zero,
    a FIFO nothing writes to, and a file whose first section is declared 1.5 GiB (table CRC
    valid) and extended sparsely to match: each refused with one line naming it, within the
    worker's 1 GiB memory cap (a reader that kept the section before its CRC failed would hit
    it) and its timeout (a blocking open or an endless read would hang)."""
    from baseline.testing.hostile import special_cases

    files = {"baseline": (decoded_files["baseline"] / "model.pgs").read_bytes()}
    cases = special_cases(files)
    assert [c.path for c in cases[:2]] == ["/proc/self/pagemap", "/dev/zero"] and cases[2].fifo
    assert cases[3].size > (3 << 29)
    st = run_cases(cases, cap_mb=1024, timeout=120.0)
    assert not st["findings"], "\n".join(f"{n}: {f}" for n, f in st["findings"])
    assert st["refused"] == len(cases) == 4
