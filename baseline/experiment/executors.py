"""Where the independent runs of a benchmark execute.

A run is a :class:`Job`: a scene, a comparison folder and one run's method, lambda and seed,
all that :func:`run_job` needs to rebuild its :class:`~baseline.experiment.plan.RunSpec` and bring
it to the finished state (train, encode, decode + evaluate; finished stages are skipped, so a
job run twice trains nothing). Records, resume and reports do not know where a job ran.

Executors (registry kind ``executor``):

* ``local``: in this process, one job at a time; with ``jobs=N`` in N worker processes, each
  pinned to its own share of the cores with as many threads (never more threads than cores).
* ``ray``: one Ray task per job (``ray.remote(num_cpus=k)``, or ``num_gpus=1`` on a GPU
  cluster), on the cluster at ``address`` (``"auto"``, ``"HOST:PORT"``) or on a local Ray
  started for the call. A task whose worker dies is retried up to ``retries`` times, and one
  that raises too; what still fails is reported by name. Results come back as each task ends
  (a tqdm bar counts finished runs across the cluster). Every node must see the ``--out``
  folder at the same path (a shared file system).

``execute(jobs) -> {"done": [row...], "failed": [(label, error)...]}``.
"""
from __future__ import annotations

import os
import sys
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional

from tqdm import tqdm

from baseline import registry


@dataclass(frozen=True)
class Job:
    scene: str                      # scene folder (absolute)
    out: str                        # the scene's comparison folder (absolute)
    method: str                     # method name ("baseline" or a --vs value)
    method_patches: tuple           # the method's patches
    lmbda: Optional[float]
    seed: Optional[int]
    common_patches: tuple = ()
    sets: tuple = ()
    lpips_weights: Optional[str] = None
    label: str = ""
    reference: bool = False         # the comparison's uncompressed reference run (--reference)
    codec: Optional[str] = None     # a patch of [codec] settings for the encode stage (--codec)


def job_spec(job: Job):
    """The job's RunSpec, planned exactly as ``pgs compare`` plans it (same folder, same hash)."""
    from baseline.experiment.plan import Method, plan_reference, plan_runs

    if job.reference:
        return plan_reference(job.out, Method(job.method, tuple(job.method_patches)),
                              list(job.common_patches), list(job.sets))
    specs = plan_runs(job.out, [Method(job.method, tuple(job.method_patches))],
                      None if job.lmbda is None else [job.lmbda], list(job.common_patches),
                      list(job.sets), None if job.seed is None else [job.seed])
    return specs[0]


def jobs_of(specs: list, ref_spec, scene: str, out, common_patches=(), sets=(),
            lpips_weights: Optional[str] = None, codec: Optional[str] = None) -> list:
    """The jobs of a comparison's planned runs (and of its uncompressed reference run, when
    ``ref_spec`` is given), in the order given; :func:`job_spec` plans each back to its spec."""
    common = dict(scene=str(scene), out=str(Path(out).resolve()),
                  common_patches=tuple(common_patches), sets=tuple(sets))
    jobs = [Job(method=s.method.name, method_patches=tuple(s.method.patches), lmbda=s.lmbda,
                seed=s.seed, label=s.label, lpips_weights=lpips_weights, codec=codec, **common)
            for s in specs]
    if ref_spec is not None:
        from baseline.experiment.plan import REFERENCE

        jobs.append(Job(method=ref_spec.method.name, method_patches=tuple(ref_spec.method.patches),
                        lmbda=None, seed=None, label=f"{REFERENCE} {ref_spec.method.name}",
                        reference=True, **common))
    return jobs


def run_job(job: Job, threads: int = 0) -> dict:
    """Bring ``job``'s run to the finished state; returns a small summary of its row."""
    if threads > 0:                      # before the trainer starts its thread pools
        os.environ["OMP_NUM_THREADS"] = str(threads)
    from baseline import registry as reg
    from baseline.experiment.records import codec_overrides, lpips_id
    from baseline.experiment.stages import run_one
    from baseline.eval.metrics import load_lpips

    reg.ensure_loaded()
    if threads > 0:                      # a pool worker (not the user's process)
        from baseline.guard import RunLock
        RunLock.wait_by_default = True
    _maybe_fail_for_tests(job)
    spec = job_spec(job)
    if job.reference:
        from baseline.experiment.stages import run_reference

        row = run_reference(spec, job.scene, progress=False)
        return {"label": job.label or f"reference {job.method}", "run_dir": str(spec.dir),
                "psnr": row["psnr"], "bytes": None, "stages_run": row["stages_run"],
                "pid": os.getpid()}
    lpips_fn, _ = load_lpips(job.lpips_weights)
    row = run_one(spec, job.scene, lpips_fn, lpips_id(job.lpips_weights) if lpips_fn else None,
                  progress=False, codec=codec_overrides(job.codec))
    return {"label": job.label or spec.label, "run_dir": str(spec.dir), "psnr": row["psnr"],
            "bytes": row["bytes"], "stages_run": row["stages_run"], "pid": os.getpid()}


def _maybe_fail_for_tests(job: Job) -> None:
    """``PGS_TEST_KILL_ONCE=DIR``: the first attempt of each job kills its own worker process
    (a marker file in DIR remembers it); the retry runs. Used by the executor tests to check
    that a dead worker's job is retried, never silently dropped."""
    d = os.environ.get("PGS_TEST_KILL_ONCE")
    if not d:
        return
    import hashlib
    import signal

    marker = os.path.join(d, hashlib.sha1(repr(job).encode()).hexdigest()[:16])
    if not os.path.exists(marker):
        open(marker, "w").close()
        os.kill(os.getpid(), signal.SIGKILL)


# ---------------------------------------------------------------------------- local
def _worker_init(cores: list, threads: int) -> None:
    """A pool worker's thread count and cores, set before its first job.

    Unpickling this function already imported numba (through ``baseline``), which read its pool
    size from the environment then. numba rereads the environment before every compilation and
    refuses a pool size that changed once its threads run, so the new size is read in at once:
    otherwise a worker that compiles a kernel (a fresh install, no disk cache yet) fails with
    "Cannot set NUMBA_NUM_THREADS to a different value once the threads have been launched"."""
    os.environ["OMP_NUM_THREADS"] = str(threads)
    if "numba" not in sys.modules:
        os.environ["NUMBA_NUM_THREADS"] = str(threads)
    else:
        from numba.core import config as numba_config
        from numba.np.ufunc import parallel

        if not parallel._is_initialized:  # once its threads run, the pool keeps its size
            os.environ["NUMBA_NUM_THREADS"] = str(threads)
            numba_config.reload_config()
    try:
        os.sched_setaffinity(0, cores)
    except (AttributeError, OSError):
        pass


def _cores() -> list:
    try:
        return sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return list(range(os.cpu_count() or 1))


class LocalExecutor:
    name = "local"

    def __init__(self, jobs: int = 1, retries: int = 1, progress: bool = True, **_):
        self.jobs, self.retries, self.progress = max(1, int(jobs)), int(retries), progress

    def execute(self, jobs: list, on_done: Optional[Callable] = None) -> dict:
        res = {"done": [], "failed": []}
        bar = tqdm(total=len(jobs), desc="runs", unit="run", disable=not self.progress)
        if self.jobs == 1:
            for j in jobs:
                self._one(res, j, lambda: run_job(j), on_done)
                bar.update(1)
            bar.close()
            return res
        import concurrent.futures as cf
        import multiprocessing as mp

        cores = _cores()
        n = min(self.jobs, len(cores)) if cores else self.jobs
        share = [cores[i::n] for i in range(n)]
        threads = max(1, len(cores) // n)
        # one pool per core share: a worker keeps its cores for every job it runs
        pools = [cf.ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"),
                                        initializer=_worker_init, initargs=(share[i], threads))
                 for i in range(n)]
        attempts = {j: 0 for j in jobs}
        try:
            pending = {}
            queue = list(jobs)

            def submit(i, j):
                attempts[j] += 1
                pending[pools[i].submit(run_job, j, threads)] = (i, j)

            for i in range(min(n, len(queue))):
                submit(i, queue.pop(0))
            while pending:
                fin, _ = cf.wait(list(pending), return_when=cf.FIRST_COMPLETED)
                for f in fin:
                    i, j = pending.pop(f)
                    try:
                        row = f.result()
                        res["done"].append(row)
                        if on_done:
                            on_done(row)
                        bar.update(1)
                    except Exception as e:           # a crashed worker breaks its pool
                        if isinstance(e, cf.process.BrokenProcessPool):
                            pools[i] = cf.ProcessPoolExecutor(
                                1, mp_context=mp.get_context("spawn"), initializer=_worker_init,
                                initargs=(share[i], threads))
                        err = f"{type(e).__name__}: {' '.join(str(e).split())}"
                        if attempts[j] <= self.retries:
                            # said at once (the final failure alone would hide the cause)
                            print(f"run attempt {attempts[j]} failed, retrying: {j.label}: "
                                  f"{err}", file=sys.stderr, flush=True)
                            queue.insert(0, j)
                        else:
                            res["failed"].append((j.label, err))
                            bar.update(1)
                    if queue:
                        submit(i, queue.pop(0))
        finally:
            for p in pools:
                p.shutdown(wait=True, cancel_futures=True)
            bar.close()
        return res

    def _one(self, res, j, fn, on_done):
        for attempt in range(self.retries + 1):
            try:
                row = fn()
                res["done"].append(row)
                if on_done:
                    on_done(row)
                return
            except KeyboardInterrupt:
                raise
            except Exception as e:  # noqa: BLE001 - reported by name below
                err = f"{type(e).__name__}: {' '.join(str(e).split())}"
                if attempt == self.retries:
                    res["failed"].append((j.label, err))
                    # one line (the failure list names it again); PGS_TRACEBACK=1 for the stack
                    print(f"run failed: {j.label}: {err}", file=sys.stderr)
                    if os.environ.get("PGS_TRACEBACK"):
                        traceback.print_exc()


# ---------------------------------------------------------------------------- Ray
class RayExecutor:
    """Ray tasks (``pip install -e .[cluster]``)."""

    name = "ray"

    def __init__(self, address: Optional[str] = None, cpus_per_run: int = 1, gpus_per_run: float = 0,
                 retries: int = 2, progress: bool = True, num_cpus: Optional[int] = None, **_):
        try:
            import ray  # noqa: F401
        except ImportError:
            raise ImportError("the ray executor needs Ray: pip install -e .[cluster] "
                              "(or pip install ray)") from None
        self.address, self.cpus, self.gpus = address, int(cpus_per_run), float(gpus_per_run)
        self.retries, self.progress, self.num_cpus = int(retries), progress, num_cpus

    def execute(self, jobs: list, on_done: Optional[Callable] = None) -> dict:
        import ray

        started = False
        if not ray.is_initialized():
            # a local Ray gets the cores this process may use (e.g. under taskset), not all
            kw = ({"address": self.address} if self.address else
                  {"num_cpus": self.num_cpus or len(_cores())})
            ray.init(include_dashboard=False, log_to_driver=False, **kw)
            started = True
        res = {"done": [], "failed": []}
        try:
            remote = ray.remote(_ray_job).options(
                num_cpus=self.cpus, num_gpus=self.gpus, max_retries=self.retries,
                retry_exceptions=True)
            refs = {remote.remote(asdict(j), self.cpus): j for j in jobs}
            bar = tqdm(total=len(refs), desc="runs (ray)", unit="run", disable=not self.progress)
            waiting = list(refs)
            while waiting:
                ready, waiting = ray.wait(waiting, num_returns=1)
                j = refs[ready[0]]
                try:
                    row = ray.get(ready[0])
                    res["done"].append(row)
                    if on_done:
                        on_done(row)
                except Exception as e:  # noqa: BLE001 - retries exhausted: reported by name
                    res["failed"].append((j.label, f"{type(e).__name__}: {str(e)[:500]}"))
                bar.update(1)
            bar.close()
        finally:
            if started:
                ray.shutdown()
        return res


def _ray_job(job: dict, threads: int) -> dict:
    d = dict(job)
    d["method_patches"] = tuple(d["method_patches"])
    d["common_patches"] = tuple(d["common_patches"])
    d["sets"] = tuple(d["sets"])
    return run_job(Job(**d), threads)


registry.register("executor", "local", LocalExecutor)
registry.register("executor", "ray", RayExecutor)


def make_executor(name: str, **options):
    return registry.get("executor", name)(**options)
