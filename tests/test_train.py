"""End-to-end training on the synthetic scene: loss goes down, resume is exact, export works."""
import json

import numpy as np
import pytest
import torch

from baseline.data.scene import load_scene
from baseline.train.trainer import Trainer
from conftest import demo_cfg


@pytest.fixture(scope="module")
def scene_dir(scene_maker):
    return scene_maker(n_views=16, width=64, height=48, seed=1)


def _cfg(iters, *sets):
    return demo_cfg(iters, *sets)


def test_short_train_lowers_loss(scene_dir, tmp_path):
    cfg = _cfg(200)
    scene = load_scene(scene_dir)
    t = Trainer(cfg, scene, tmp_path / "run", progress=False)
    first = [t.step(i)["l1"] for i in range(1, 11)]
    t.iteration = 10
    for i in range(11, 191):
        t.step(i)
    last = [t.step(i)["l1"] for i in range(191, 201)]
    assert np.mean(last) < 0.7 * np.mean(first), (np.mean(first), np.mean(last))
    assert t.model.n_anchors > 0


def test_resume_is_exact(scene_dir, tmp_path):
    cfg = _cfg(60)
    scene = load_scene(scene_dir)
    a = Trainer(cfg, scene, tmp_path / "a", progress=False)
    a.train(until=30)
    ck = a.save_checkpoint(tmp_path / "a" / "mid.pt")
    losses_a = [a.step(i)["loss"] for i in range(31, 36)]
    b = Trainer(cfg, scene, tmp_path / "b", progress=False)
    b.load_checkpoint(ck)
    losses_b = [b.step(i)["loss"] for i in range(31, 36)]
    assert losses_a == losses_b


def test_train_log_is_one_curve_across_a_resume(scene_dir, tmp_path):
    cfg = _cfg(40, "train.log_every=5", "train.checkpoint_every=0")
    scene = load_scene(scene_dir)
    a = Trainer(cfg, scene, tmp_path / "r", progress=False)
    a.train(until=20)                              # checkpoint at 20, log lines 5..20
    with (tmp_path / "r" / "train_log.jsonl").open("a") as f:   # a killed run: lines past the
        f.write(json.dumps({"it": 25}) + "\n" + '{"it": 3')     # checkpoint, a torn last line
    b = Trainer(cfg, scene, tmp_path / "r", progress=False)
    b.load_checkpoint(tmp_path / "r" / "checkpoint.pt")
    b.train()
    rows = [json.loads(x) for x in (tmp_path / "r" / "train_log.jsonl").read_text().splitlines()]
    assert [r["it"] for r in rows] == list(range(5, 41, 5))
    assert all(np.isfinite(r["loss"]) and r["anchors"] > 0 and r["gaussians"] > 0 for r in rows)
    t = [r["train_time"] for r in rows]
    assert t == sorted(t) and t[0] > 0
    # the growing hook's running counts, carried across the resume: every line's anchors are
    # the initial ones plus those grown minus those pruned so far
    assert {r["anchors"] - r["grown"] + r["pruned"] for r in rows} == {a.model.n_anchors
                                                                       - a.hooks[0].grown
                                                                       + a.hooks[0].pruned}
    assert rows[-1]["grown"] > 0 and rows[-1]["grown"] >= rows[3]["grown"]


def test_a_resume_at_another_thread_count_keeps_both_counts(scene_dir, tmp_path):
    """A run resumed at another thread count keeps which iterations ran at which count (its
    time per iteration mixes them), through later checkpoints, into results and the report;
    a checkpoint that did not record it shows its stretch as unrecorded."""
    from baseline.eval.report import _threads_shown
    from baseline.train.trainer import set_threads
    scene = load_scene(scene_dir)
    a = Trainer(_cfg(20, "train.checkpoint_every=0"), scene, tmp_path / "t", progress=False)
    a.train(until=10)
    assert a.thread_segments == [[0, 1]]
    try:
        b = Trainer(_cfg(20, "train.threads=2"), scene, tmp_path / "t", progress=False)
        b.load_checkpoint(tmp_path / "t" / "checkpoint.pt")
        two = b.threads                            # 1 on a one-core machine
        b.train(until=15)
        c = Trainer(_cfg(20, "train.threads=2"), scene, tmp_path / "t", progress=False)
        c.load_checkpoint(tmp_path / "t" / "checkpoint.pt")
    finally:
        set_threads(1)
    want = [[0, 1], [10, 2]] if two == 2 else [[0, 1]]
    assert b.thread_segments == want and c.thread_segments == want
    old = torch.load(tmp_path / "t" / "checkpoint.pt", weights_only=False)
    del old["thread_segments"]                     # written before the counts were kept
    torch.save(old, tmp_path / "old.pt")
    d = Trainer(_cfg(20), scene, tmp_path / "d", progress=False)
    d.load_checkpoint(tmp_path / "old.pt")
    assert d.thread_segments == [[0, None], [15, 1]]
    assert _threads_shown({"threads": 1, "threads_by_iteration": d.thread_segments}) == \
        "unrecorded from iteration 0, then 1 from iteration 15"
    assert _threads_shown({"threads": 2, "threads_by_iteration": [[0, 1], [10, 2]]}) == \
        "1 from iteration 0, then 2 from iteration 10"
    assert _threads_shown({"threads": 1}) == "1"


def test_a_resume_by_other_code_keeps_both_codes(scene_dir, tmp_path, monkeypatch):
    """A run records the code it trained by (this checkout's commit, or the package's version
    outside a checkout); one resumed by other code keeps which iterations ran by which, and the
    report leaves its time out of every ratio."""
    import re

    import baseline.train.trainer as tr
    from baseline.device import code_version
    from baseline.eval.report import untimed
    from baseline.run import _finish_run

    here = code_version()
    assert re.fullmatch(r"[0-9a-f]{12}(\+modified)?|pgs \S+", here), here
    scene = load_scene(scene_dir)
    a = Trainer(_cfg(20, "train.checkpoint_every=0"), scene, tmp_path / "t", progress=False)
    a.train(until=10)
    assert a.code == here and a.code_segments == [[0, here]]
    monkeypatch.setattr(tr, "code_version", lambda: "feedfacecafe")
    b = Trainer(_cfg(20, "train.checkpoint_every=0"), scene, tmp_path / "t", progress=False)
    b.load_checkpoint(tmp_path / "t" / "checkpoint.pt")
    b.train()
    want = [[0, here], [10, "feedfacecafe"]]
    assert b.code_segments == want
    res = _finish_run(b, scene, scene_dir, tmp_path / "t", b.cfg, evaluate_after=False)
    assert res["code"] == "feedfacecafe" and res["codes_by_iteration"] == want
    assert untimed(dict(res, stall_s=0.0)) == (
        "resumed by other code or from a checkpoint that did not record it: "
        f"{here} from iteration 0, then feedfacecafe from iteration 10")
    old = torch.load(tmp_path / "t" / "checkpoint.pt", weights_only=False)
    del old["code_segments"]                       # written before codes were kept
    torch.save(old, tmp_path / "old.pt")
    d = Trainer(_cfg(20), scene, tmp_path / "d", progress=False)
    d.load_checkpoint(tmp_path / "old.pt")
    assert d.code_segments == [[0, None], [20, "feedfacecafe"]]


def test_a_resume_on_another_machine_keeps_both_machines(scene_dir, tmp_path, monkeypatch):
    """A run resumed on another machine keeps which iterations ran on which (its training time
    then sums two machines' speeds): through later checkpoints and into its results, where the
    report leaves its time out of every ratio; a checkpoint that did not keep its machine shows
    that stretch as unrecorded."""
    import baseline.train.trainer as tr
    from baseline.device import machine_name
    from baseline.eval.report import _machines_shown, untimed
    from baseline.run import _finish_run

    here = machine_name(torch.device("cpu"))
    assert here.endswith(" CPUs)") and len(here) > len(" (1 CPUs)")
    scene = load_scene(scene_dir)
    a = Trainer(_cfg(20, "train.checkpoint_every=0"), scene, tmp_path / "t", progress=False)
    a.train(until=10)
    assert a.machine == here and a.machine_segments == [[0, here]]
    monkeypatch.setattr(tr, "machine_name", lambda dev: "Other CPU (8 CPUs)")
    b = Trainer(_cfg(20, "train.checkpoint_every=0"), scene, tmp_path / "t", progress=False)
    b.load_checkpoint(tmp_path / "t" / "checkpoint.pt")
    b.train()
    want = [[0, here], [10, "Other CPU (8 CPUs)"]]
    assert b.machine_segments == want
    c = Trainer(_cfg(20), scene, tmp_path / "t", progress=False)
    c.load_checkpoint(tmp_path / "t" / "checkpoint.pt")
    assert c.machine_segments == want               # the same machine again: no new stretch
    res = _finish_run(b, scene, scene_dir, tmp_path / "t", b.cfg, evaluate_after=False)
    assert res["machine"] == "Other CPU (8 CPUs)" and res["machines_by_iteration"] == want
    assert untimed(dict(res, stall_s=0.0)) == (
        f"resumed on another machine or from one not recorded: {here} from iteration 0, then "
        "Other CPU (8 CPUs) from iteration 10")
    old = torch.load(tmp_path / "t" / "checkpoint.pt", weights_only=False)
    del old["machine_segments"]                    # written before machines were kept
    torch.save(old, tmp_path / "old.pt")
    d = Trainer(_cfg(20), scene, tmp_path / "d", progress=False)
    d.load_checkpoint(tmp_path / "old.pt")
    assert d.machine_segments == [[0, None], [20, "Other CPU (8 CPUs)"]]
    assert _machines_shown({"machine": "X", "machines_by_iteration": d.machine_segments}) == \
        "unrecorded from iteration 0, then Other CPU (8 CPUs) from iteration 20"
    assert _machines_shown({"machine": "X"}) == "X" and _machines_shown({}) == "-"
    # one machine throughout: no stretches in the results, and the time stands
    e = Trainer(_cfg(5, "train.checkpoint_every=0"), scene, tmp_path / "e", progress=False)
    e.train()
    res = _finish_run(e, scene, scene_dir, tmp_path / "e", e.cfg, evaluate_after=False)
    assert "machines_by_iteration" not in res and untimed(dict(res, stall_s=0.0)) is None


def test_a_pause_inside_training_is_recorded_as_stall_time(scene_dir, tmp_path, monkeypatch):
    """Time in which the process ran on no core (here a sleep inside each step, as a SIGSTOP
    pause or a shared core) is counted as stall time, kept through a checkpoint into the log;
    a checkpoint that did not keep it counts it from its iteration on."""
    import time
    scene = load_scene(scene_dir)
    cfg = _cfg(12, "train.log_every=4", "train.checkpoint_every=0")
    a = Trainer(cfg, scene, tmp_path / "p", progress=False)
    a.train(until=4)
    assert a.stall_time is not None and 0 <= a.stall_time <= a.train_time and a.stall_from == 0
    before = a.stall_time
    step = Trainer.step
    monkeypatch.setattr(Trainer, "step", lambda self, it: (time.sleep(0.2), step(self, it))[1])
    b = Trainer(cfg, scene, tmp_path / "p", progress=False)
    b.load_checkpoint(tmp_path / "p" / "checkpoint.pt")
    assert b.stall_time == before
    b.train(until=8)                               # four sleeping steps: at least 0.8 s stalled
    assert b.stall_time - before >= 0.8 - 1e-3 and b.stall_time <= b.train_time
    rows = [json.loads(x) for x in (tmp_path / "p" / "train_log.jsonl").read_text().splitlines()]
    assert [r["it"] for r in rows] == [4, 8] and rows[1]["stall_time"] == round(b.stall_time, 3)
    old = torch.load(tmp_path / "p" / "checkpoint.pt", weights_only=False)
    del old["stall_time"], old["stall_from"]       # written before the stall time was kept
    torch.save(old, tmp_path / "old.pt")
    c = Trainer(cfg, scene, tmp_path / "c", progress=False)
    c.load_checkpoint(tmp_path / "old.pt")
    assert c.stall_time == 0.0 and c.stall_from == 8


def test_checkpoint_with_nan_is_refused(scene_dir, tmp_path):
    cfg = _cfg(5)
    scene = load_scene(scene_dir)
    t = Trainer(cfg, scene, tmp_path / "n", progress=False)
    with torch.no_grad():
        t.model.per_anchor["offsets"][0, 0, 0] = float("nan")
    ck = tmp_path / "n" / "checkpoint.pt"          # written around save_checkpoint's own check
    ck.parent.mkdir(parents=True, exist_ok=True)
    torch.save(t.state_dict(), ck)
    t2 = Trainer(cfg, scene, tmp_path / "n2", progress=False)
    with pytest.raises(ValueError, match="per_anchor.offsets.*NaN"):
        t2.load_checkpoint(ck)


def test_threads_follow_the_cpu_affinity():
    """`set_threads(0)` uses the cores this process may run on (e.g. under taskset), never more."""
    import os
    import subprocess
    import sys

    if not hasattr(os, "sched_setaffinity"):
        pytest.skip("no CPU affinity on this platform")
    code = ("import os; os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]}); "
            "import torch; from baseline.train.trainer import set_threads; "
            "print(set_threads(0), torch.get_num_threads())")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1", "1"]


@pytest.mark.parametrize("env, want", [("1", 1), ("64", None), ("", None), ("x", None)])
def test_default_threads_follow_omp_num_threads(env, want):
    """`train.threads = 0` with OMP_NUM_THREADS set uses at most that many threads (the printed
    and recorded thread count is then the one used); unset, empty or invalid: every core."""
    import os
    import subprocess
    import sys

    from baseline.train.trainer import available_cores

    code = ("import torch; from baseline.train.trainer import set_threads; "
            "print(set_threads(0), torch.get_num_threads())")
    e = dict(os.environ, OMP_NUM_THREADS=env)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         env=e)
    n = want or available_cores()
    assert out.stdout.split() == [str(n), str(n)]


_ONE_THREAD_CODE = {
    "trainer": "from baseline.train.trainer import set_threads; set_threads(1); ",
    "renderer": "torch.set_num_threads(1); ",
}


@pytest.mark.parametrize("path, layer", [("trainer", ""), ("trainer", "omp"),
                                         ("trainer", "workqueue"), ("renderer", "omp")])
def test_one_thread_stays_one_thread_once_numba_starts(path, layer):
    """One thread asked for (by `set_threads(1)`, or by torch before the first kernel) stays one
    thread in torch and the CPU kernels after numba's pool starts, whatever its threading layer.
    Starting numba's OpenMP layer resets the thread's OpenMP count to NUMBA_NUM_THREADS (torch
    shares the libgomp): `train.threads = 1` ran torch and the kernels on 2 threads, and two
    such trainings side by side ran 8x slower than they should."""
    import os
    import subprocess
    import sys

    from baseline.train.trainer import available_cores

    if available_cores() < 2:
        pytest.skip("needs 2 cores to tell 1 thread from all")
    # torch.get_num_threads() first, as the CLI does before training: it initializes torch's
    # OpenMP state, after which (here) starting numba's OpenMP pool resets the count
    code = ("import torch; torch.get_num_threads(); " + _ONE_THREAD_CODE[path]
            + "from baseline.render import cpu; k = cpu._apply_threads(); import numba; "
              "print(torch.get_num_threads(), k, numba.get_num_threads(), numba.threading_layer())")
    env = {k: v for k, v in os.environ.items()
           if k not in ("OMP_NUM_THREADS", "NUMBA_NUM_THREADS", "NUMBA_THREADING_LAYER")}
    if layer:
        env["NUMBA_THREADING_LAYER"] = layer
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env)
    if out.returncode and "threading layer" in out.stderr.lower():
        pytest.skip(f"numba's {layer} layer is not available here")
    assert out.returncode == 0, out.stderr
    torch_n, kernel_n, numba_n, used = out.stdout.split()
    assert (torch_n, kernel_n, numba_n) == ("1", "1", "1"), used
    if layer:
        assert used == layer


def test_mask_lr_scales_with_the_schedule_only_when_asked(scene_dir, tmp_path):
    """lr.mask_schedule_scaled multiplies the mask logits' lr (start and end) by
    schedule_base / iterations, and no other group's; off by default."""
    scene = load_scene(scene_dir)

    def groups(*sets):
        t = Trainer(_cfg(600, *sets), scene, tmp_path / "r", progress=False)
        return {g["name"]: (g["lr_init"], g["lr_final"]) for g in t.optimizer.param_groups}, t

    plain, t = groups()
    scaled, _ = groups("lr.mask_schedule_scaled=true")
    ext = t.extent
    assert plain["mask"] == pytest.approx((0.01 * ext, 0.0001 * ext))
    assert scaled["mask"] == pytest.approx((0.01 * ext * 50, 0.0001 * ext * 50))   # 30000 / 600
    assert {k: v for k, v in scaled.items() if k != "mask"} == \
        {k: v for k, v in plain.items() if k != "mask"}


@pytest.mark.parametrize("mode", ["noise", "ste"])
def test_decoder_quant_sets_what_the_decoder_sees_in_training(scene_dir, tmp_path, mode):
    """entropy.decoder_quant: in the noise phase (step q0) and the adaptive phase (per-anchor
    steps from the entropy model), the decoder receives values on the quantization grid with
    "ste" and noisy values off it with "noise" (HAC's default)."""
    scene = load_scene(scene_dir)
    t = Trainer(_cfg(60, f"entropy.decoder_quant={mode}"), scene, tmp_path / mode, progress=False)
    seen = {}
    decode = t.model.decode

    def spy(cam_center, idx, values=None, xyz=None, visible=None):
        seen["values"] = {k: v.detach().clone() for k, v in values.items()}
        with torch.no_grad():   # the steps of this forward (the update after it changes them)
            P = t.entropy.params(xyz.detach())      # the positions training drew
        seen["q"] = {k: P[k][2] for k in seen["values"]}
        return decode(cam_center, idx, values, xyz=xyz, visible=visible)

    t.model.decode = spy
    q0 = {a.name: a.q0 for a in t.model.coded_attributes()}
    on_grid = {}
    for it in range(1, 31):
        t.step(it)
        t.iteration = it
        if t.phase == "noise":
            steps = {k: torch.tensor(q) for k, q in q0.items()}
        elif t.phase == "adaptive":
            steps = seen["q"]
        else:
            continue
        for k, v in seen["values"].items():
            r = v / steps[k]
            on_grid.setdefault((t.phase, k), []).append(
                bool(torch.all((r - torch.round(r)).abs() < 1e-3)))
    assert {ph for ph, _ in on_grid} == {"noise", "adaptive"}
    for key, flags in on_grid.items():
        assert all(flags) if mode == "ste" else not any(flags), (key, flags)


def test_saving_more_often_trains_the_same_run(scene_dir, tmp_path):
    """``train.checkpoint_every`` says when a run saves its state, not what it trains: the same
    folder hash, no config difference on resume, and the same parameters bit for bit."""
    from baseline.config import config_hash
    from baseline.guard import config_difference

    often, never = _cfg(24, "train.checkpoint_every=10000"), _cfg(24, "train.checkpoint_every=0")
    assert config_hash(often) == config_hash(never) == config_hash(_cfg(24))
    assert config_difference(often, never) == []
    assert config_hash(_cfg(24, "train.seed=3")) != config_hash(_cfg(24))  # a training setting
    scene = load_scene(scene_dir)
    states, saves = [], []
    for name, cfg in (("often", often), ("never", never)):
        t = Trainer(cfg, scene, tmp_path / name, progress=False)
        calls = []
        save = t.save_checkpoint
        t.save_checkpoint = lambda *a, **k: calls.append(t.iteration) or save(*a, **k)
        t.train()
        saves.append(calls)
        states.append({k: v.detach().clone() for k, v in t.model.state_dict().items()})
    assert saves[0][:2] == [8, 16] and saves[1] == [24]   # every 8 of 24 iterations / at the end
    assert states[0].keys() == states[1].keys()
    assert all(torch.equal(states[0][k], states[1][k]) for k in states[0])
