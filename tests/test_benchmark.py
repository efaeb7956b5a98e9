"""`pgs benchmark`: a tiny dataset (two procedural scenes) on the local executor and on a real
local Ray cluster: the same records, a killed worker's run retried, a rerun that trains nothing,
the dataset's tables and survey CSVs."""
from __future__ import annotations

import csv
import os
import subprocess
import sys
import textwrap

import pytest

from baseline.data.synthetic import make_scene
from baseline.experiment.benchmark import benchmark_records, run_benchmark

SETS = ["train.iterations=200", "train.log_every=1000", "model.voxel_size=0.05"]
COMMON = ["demo"]


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("dataset")
    for name, seed in (("alpha", 1), ("beta", 2)):
        make_scene(root / name, n_views=8, width=40, height=30, seed=seed, n_points=300)
    (root / "notes").mkdir()                       # not a scene: ignored
    return root


def _bench(dataset, out, executor, **opts):
    return run_benchmark(dataset, out, vs=["predict-gs"], lambdas=[0.004], common_patches=COMMON,
                         sets=SETS, executor=executor, executor_options=opts, plots=False,
                         progress=False, echo=False)


@pytest.fixture(scope="module")
def local_run(dataset, tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_local")
    return out, _bench(dataset, out, "local", jobs=2)


def test_local_benchmark_tables_and_csvs(local_run):
    out, res = local_run
    assert res["complete"] and res["jobs_run"] == 4 and not res["failed"]
    assert res["scenes"] == ["alpha", "beta"]
    rows = {(r["method"], r["lmbda"]): r for r in res["table"]}
    assert set(rows) == {("baseline", 0.004), ("predict-gs", 0.004)}
    for r in rows.values():
        assert r["n_scenes"] == 2 and 0 < r["psnr"] < 60 and r["mb"] > 0
        assert r["others_mb"] == pytest.approx(r["mb"] - r["feature_mb"])
    for scene in ("alpha", "beta"):
        for method in ("HAC", "Predict-GS"):     # one file per method and scene, one point
            with open(out / "survey" / method / "dataset0" / f"{scene}.csv") as f:
                assert [x["Submethod"] for x in csv.DictReader(f)] == [method]
        assert (out / scene / "report.md").exists()
    # the mean is the mean of the scenes' own results
    import json
    per = [json.loads((out / s / "results.json").read_text()) for s in ("alpha", "beta")]
    base = [next(r for r in p["runs"] if r["method"] == "baseline") for p in per]
    assert rows[("baseline", 0.004)]["psnr"] == pytest.approx(sum(b["psnr"] for b in base) / 2)
    md = (out / "report.md").read_text()
    assert "Mean over the scenes" in md and "BD-rate" in md


def test_ray_benchmark_equals_local_retries_killed_workers_and_resumes(dataset, local_run,
                                                                         tmp_path, monkeypatch):
    pytest.importorskip("ray", reason="Ray is not installed (pip install -e .[cluster])")
    out_local, _ = local_run
    out = tmp_path / "bench_ray"
    kills = tmp_path / "kills"
    kills.mkdir()
    monkeypatch.setenv("PGS_TEST_KILL_ONCE", str(kills))     # every run's first worker dies
    res = _bench(dataset, out, "ray", num_cpus=2, cpus_per_run=1, retries=2)
    assert not res["failed"] and res["jobs_run"] == 4 and res["complete"]
    assert len(os.listdir(kills)) == 4                        # each was killed once, and retried
    a, b = benchmark_records(out_local), benchmark_records(out)
    assert a and a == b                                       # the same records on both executors
    monkeypatch.delenv("PGS_TEST_KILL_ONCE")
    again = _bench(dataset, out, "ray", num_cpus=2, cpus_per_run=1)
    assert again["jobs_run"] == 0 and again["complete"]        # a rerun trains nothing


def test_a_run_that_keeps_failing_is_reported_by_name(dataset, tmp_path):
    """A run that fails on every attempt is reported with its name and error, not dropped."""
    from baseline.experiment.executors import Job, LocalExecutor
    bad = Job(scene=str(dataset / "alpha"), out=str(tmp_path / "x"), method="baseline",
              method_patches=(), lmbda=0.004, seed=None, common_patches=("demo",),
              sets=("train.iterations=5", "data.images=\"nosuch\""), label="alpha: broken")
    r = LocalExecutor(retries=1, progress=False).execute([bad])
    assert r["done"] == [] and r["failed"][0][0] == "alpha: broken"
    assert "nosuch" in r["failed"][0][1]


def test_dataset_bd_keeps_each_reference_apart():
    """A method measured against the baseline and against a contender it extends gets one row
    per reference (per scene and their mean), not one overwriting the other."""
    from baseline.experiment.benchmark import dataset_bd

    def item(m, ref, rate, seed="mean"):
        d = {"method": m, "seed": seed, "bd_rate": rate, "bd_psnr": 0.1}
        if ref is not None:                    # None: a record from before references were named
            d["against"] = ref
        return d

    per_scene = {
        "alpha": {"baseline": "baseline", "bd": [
            item("hacpp", None, -30.0), item("predict-gs+hacpp", "baseline", -40.0),
            item("predict-gs+hacpp", "hacpp", -10.0), item("predict-gs+hacpp", "hacpp", 5.0, 0)]},
        "beta": {"baseline": "baseline", "bd": [
            item("hacpp", "baseline", -20.0), item("predict-gs+hacpp", "baseline", -30.0),
            item("predict-gs+hacpp", "hacpp", -6.0)]}}
    rows = {(r["method"], r["against"]): r for r in dataset_bd(per_scene)}
    assert set(rows) == {("hacpp", "baseline"), ("predict-gs+hacpp", "baseline"),
                         ("predict-gs+hacpp", "hacpp")}
    assert rows[("hacpp", "baseline")]["mean_bd_rate"] == pytest.approx(-25.0)
    assert rows[("predict-gs+hacpp", "hacpp")]["mean_bd_rate"] == pytest.approx(-8.0)
    assert rows[("predict-gs+hacpp", "baseline")]["per_scene"]["alpha"]["bd_rate"] == -40.0


def test_a_stalled_training_time_leaves_its_rows_train_mean_out():
    """A run that stalled over 5% of its training time (paused, or sharing its core), or marked
    untimed, leaves the dataset row's training-time mean empty ('-', with a note) instead of
    averaging its wait."""
    from baseline.experiment.benchmark import dataset_table, format_benchmark

    def run(m, t, stall):
        return {"method": m, "lmbda": 0.004, "psnr": 25.0, "ssim": 0.9, "mb": 3.0, "fps": 50.0,
                "groups": {"feature": 2 ** 20}, "train_time_s": t, "encode_s": 1.0,
                "decode_s": 1.0, **({} if stall is None else {"stall_s": stall})}

    per_scene = {"alpha": {"runs": [run("baseline", 1000.0, 10.0), run("hacpp", 1000.0, 300.0)]},
                 "beta": {"runs": [run("baseline", 3000.0, None), run("hacpp", 2000.0, 20.0)]}}
    rows = {r["method"]: r for r in dataset_table(per_scene)}
    assert rows["baseline"]["train_s"] == pytest.approx(2000.0)   # 1% and unrecorded: kept
    assert rows["hacpp"]["train_s"] is None and rows["hacpp"]["psnr"] == pytest.approx(25.0)
    per_scene["beta"]["runs"][0]["untimed"] = "paused"           # a marked record: left out too
    assert {r["method"]: r for r in dataset_table(per_scene)}["baseline"]["train_s"] is None
    res = {"dataset": "d", "scenes": ["alpha", "beta"], "common_patches": [], "sets": [],
           "table": list(rows.values()), "bd": [], "executor": "local", "executor_options": {},
           "jobs_run": 0, "wall_s_this_invocation": 0.0, "failed": [], "complete": True}
    assert "train (s) '-': a run of that row stalled over 5%" in format_benchmark(res)
    rows["hacpp"]["train_s"] = 1.0
    assert "stalled" not in format_benchmark(res)


def test_a_pool_worker_compiles_kernels_with_its_own_thread_count():
    """A pool worker imports numba (unpickling its initializer) before it is given its thread
    count; compiling a kernel afterwards, as a fresh install without numba's disk cache does,
    must not fail on the changed NUMBA_NUM_THREADS."""
    code = textwrap.dedent("""
        import os
        import numba
        from baseline.experiment.executors import _worker_init
        _worker_init(sorted(os.sched_getaffinity(0)), 1)
        numba.get_num_threads()                       # starts the pool

        @numba.njit(cache=False)
        def f(x):
            return x + 1

        assert f(1) == 2                              # compiling rereads the environment
        print(numba.config.NUMBA_NUM_THREADS)
    """)
    env = dict(os.environ, NUMBA_NUM_THREADS="2")     # the pool size read at import
    r = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split()[-1] == "1"
