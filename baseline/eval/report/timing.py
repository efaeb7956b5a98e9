"""Train-time and speed figures of the runs: stalls, untimed runs, time ratios against the
baseline, and how threads and machines are shown."""
from __future__ import annotations

from typing import Optional

from baseline.eval.report.names import runs_of
from baseline.eval.report.cells import _lam


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
    record cannot show, or resumed on another machine or by other code (or from a checkpoint
    that did not keep them): its time then sums stretches of different machines or codes.
    Every reason that holds, joined."""
    why = [_stall_words(r) if stalled(r) else None, r.get("untimed") or None,
           "resumed on another machine or from one not recorded: " + _machines_shown(r)
           if r.get("machines_by_iteration") else None,
           "resumed by other code or from a checkpoint that did not record it: " + _codes_shown(r)
           if r.get("codes_by_iteration") else None]
    return "; ".join(w for w in why if w) or None


def train_time_pairs(results: dict, method: str, base: str) -> tuple[list, list]:
    """The (method run, baseline run) pairs whose training times compare: the same lambda and
    seed, each trained at one thread count throughout, the same count for both, neither
    untimed (stalled beyond STALL_LIMIT of its time and STALL_FLOOR_S, or marked), on the same
    machine and by the same code where both records name them (a record that names neither
    code, from before codes were kept, pairs only with another such record); and the
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
        elif r.get("code") != b.get("code"):
            left.append((r, f"trained by code {r.get('code') or 'unrecorded'}, the baseline run "
                            f"by {b.get('code') or 'unrecorded'}"))
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


def _codes_shown(r: dict) -> str:
    """The code a run trained by (``-`` in records from before codes were kept); a run
    resumed by other code names each from its first iteration, as _threads_shown."""
    return _stretches_shown(r, "code", "codes_by_iteration")


def _stretches_shown(r: dict, key: str, by_iteration: str) -> str:
    segs = r.get(by_iteration)
    if not segs:
        return str(r.get(key) or "-")
    return ", then ".join(f"{'unrecorded' if v is None else v} from iteration {i}"
                          for i, v in segs)
