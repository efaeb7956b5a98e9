"""What a command may write: run folders owned by one process, no output onto a run's records or
into a scene, and resumes that check what they resume.

* :class:`RunLock`: a run folder is written by one process at a time (``fcntl.flock`` on
  ``RUN/.pgs.lock``; the kernel releases it when the process ends, however it ends, so a crash
  never leaves it held).
* :func:`check_output_file` / :func:`check_output_folder`: an output path that would replace a
  run's records (checkpoint, config, results, log, model file) or lies inside a scene folder is
  refused with the path and what it holds; ``overwrite`` allows the run's records (never a
  scene: the toolkit does not write into scenes).
* :func:`scene_identity` / :func:`check_resume`: a run records what it was trained on (scene
  path, format, the views' names and sizes, the protocol); resuming it on another scene or with
  another training configuration is refused, with the difference named.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
from pathlib import Path
from typing import Optional

# the files that make a folder a run (pgs train / pgs compare write them)
RUN_FILES = ("checkpoint.pt", "config.toml", "results.json", "scene.json", "train_log.jsonl",
             "compare.json", "model.pgs")
LOCK_NAME = ".pgs.lock"


class OutputError(ValueError):
    """An output path that would replace someone's work."""


def is_run_folder(path: Path) -> bool:
    """A folder holding a run (a config beside a checkpoint or results)."""
    p = Path(path)
    return p.is_dir() and (p / "config.toml").is_file() and (
        (p / "checkpoint.pt").is_file() or (p / "results.json").is_file())


def scene_root(path: Path) -> Optional[Path]:
    """The scene folder ``path`` is (or lies inside), else None: a COLMAP folder (``sparse/``
    beside images) or a Blender / instant-ngp one (``transforms*.json``)."""
    p = Path(path).expanduser().absolute()
    for d in [p, *p.parents]:
        try:
            if (d / "sparse").is_dir() and any((d / x).is_dir() for x in os.listdir(d)
                                               if x.startswith("images")):
                return d
            if any(d.glob("transforms*.json")):
                return d
        except OSError:
            continue
    return None


def check_output_file(path, *, overwrite: bool = False) -> None:
    """Refuse an output file that would replace a run's record (unless ``overwrite``) or that
    lies inside a scene folder."""
    p = Path(path).expanduser().absolute()
    if p.is_dir():
        raise OutputError(f"{p}: is a folder; give a file name")
    root = scene_root(p.parent)
    if root is not None:
        raise OutputError(f"{p}: inside the scene folder {root}; the toolkit never writes into "
                          f"a scene: choose a path outside it")
    if p.name in RUN_FILES and is_run_folder(p.parent) and not overwrite:
        raise OutputError(f"{p}: is the {p.name} of the run {p.parent}; writing there would "
                          f"replace it (choose another path, or --overwrite)")


def check_output_folder(path, *, overwrite: bool = False, may_be_run: bool = False) -> None:
    """Refuse an output folder that is a run (unless ``may_be_run`` or ``overwrite``) or lies
    inside a scene folder."""
    p = Path(path).expanduser().absolute()
    root = scene_root(p)
    if root is not None:
        raise OutputError(f"{p}: inside the scene folder {root}; the toolkit never writes into "
                          f"a scene: choose a folder outside it")
    if p.exists() and not p.is_dir():
        raise OutputError(f"{p}: exists and is not a folder")
    if not may_be_run and not overwrite and is_run_folder(p):
        raise OutputError(f"{p}: holds a run (config.toml with a checkpoint or results); "
                          f"writing there would replace its records (choose another folder, "
                          f"or --overwrite)")


class RunLock:
    """Exclusive ownership of a run folder for the life of a ``with`` block (or the process).
    Re-entrant within a process (``pgs compare`` holds a run's lock around the training that
    takes it again)."""

    _held: dict = {}              # resolved folder -> [fd, depth] held by this process
    # a worker of an executor waits for a run another process holds (a retried job whose first
    # attempt still runs finds it finished) instead of failing; a user's command never waits
    wait_by_default = False

    def __init__(self, folder, wait: Optional[bool] = None):
        self.folder = Path(folder)
        self.wait = RunLock.wait_by_default if wait is None else wait
        self._fd: Optional[int] = None
        self._key: Optional[str] = None

    def acquire(self) -> "RunLock":
        import fcntl

        self.folder.mkdir(parents=True, exist_ok=True)
        self._key = str(self.folder.resolve())
        if self._key in RunLock._held:
            RunLock._held[self._key][1] += 1
            return self
        path = self.folder / LOCK_NAME
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            try:
                holder = os.pread(fd, 64, 0).decode("ascii", "replace").strip() or "?"
            except OSError:
                holder = "?"
            if not self.wait:
                os.close(fd)
                raise OutputError(f"{self.folder}: in use by another pgs process (pid {holder}); "
                                  f"wait for it to end or stop it") from None
            print(f"{self.folder}: in use by pid {holder}; waiting for it", file=sys.stderr,
                  flush=True)
            fcntl.flock(fd, fcntl.LOCK_EX)
        os.ftruncate(fd, 0)
        os.pwrite(fd, str(os.getpid()).encode("ascii"), 0)
        RunLock._held[self._key] = [fd, 1]
        return self

    def release(self) -> None:
        held = RunLock._held.get(self._key) if self._key else None
        if held is None:
            return
        held[1] -= 1
        if held[1] > 0:
            return
        import fcntl

        del RunLock._held[self._key]
        try:
            fcntl.flock(held[0], fcntl.LOCK_UN)
        finally:
            os.close(held[0])

    def __enter__(self):
        return self.acquire()

    def __exit__(self, *exc):
        self.release()
        return False


# ---------------------------------------------------------------------------- resume checks
def scene_identity(scene, scene_path) -> dict:
    """What a run was trained on: the scene's path and format, its views (names and sizes, in
    split order) as a digest with their counts, and the protocol."""
    views = [[c.name, int(c.width), int(c.height), split]
             for split, cams in (("train", scene.train_cameras), ("test", scene.test_cameras))
             for c in cams]
    digest = hashlib.sha256(json.dumps(views).encode()).hexdigest()[:16]
    return {"path": str(Path(scene_path).resolve()),
            "n_train": len(scene.train_cameras), "n_test": len(scene.test_cameras),
            "views_digest": digest}


def identity_difference(recorded: dict, now: dict) -> Optional[str]:
    """In words, how the scene a run was trained on differs from ``now``; None when the same
    (records written before identities were kept compare by path only)."""
    if recorded.get("path") and recorded["path"] != now["path"]:
        return f"trained on {recorded['path']}, this is {now['path']}"
    if "views_digest" in recorded and recorded["views_digest"] != now["views_digest"]:
        return (f"its views differ (trained on {recorded.get('n_train')} train / "
                f"{recorded.get('n_test')} test views, now {now['n_train']} / {now['n_test']}, "
                f"names or sizes changed)")
    return None


def config_difference(old_cfg, new_cfg) -> list[str]:
    """``section.key: old -> new`` for every training setting that differs (where a run
    executes, ``train.device``, is not a difference)."""
    from baseline.config import EXECUTION_KEYS, to_dict

    a, b = to_dict(old_cfg, drop_meta=True), to_dict(new_cfg, drop_meta=True)
    for sec, key in EXECUTION_KEYS:
        a.get(sec, {}).pop(key, None)
        b.get(sec, {}).pop(key, None)
    out = []

    def walk(x, y, prefix):
        for k in sorted(set(x) | set(y)):
            u, v = x.get(k, "<absent>"), y.get(k, "<absent>")
            if isinstance(u, dict) and isinstance(v, dict):
                walk(u, v, f"{prefix}{k}.")
            elif u != v:
                out.append(f"{prefix}{k}: {u!r} -> {v!r}")

    walk(a, b, "")
    return out


def check_resume(run: Path, cfg, scene, scene_path) -> None:
    """Refuse to resume ``run`` on another scene or with another training configuration."""
    from baseline.config import config_hash, from_toml

    run = Path(run)
    sj = run / "scene.json"
    if sj.is_file():
        try:
            rec = json.loads(sj.read_text())
        except (OSError, ValueError):
            rec = {}
        diff = identity_difference(rec, scene_identity(scene, scene_path))
        if diff:
            raise OutputError(f"{run}: cannot resume on this scene: {diff}; use another --out "
                              f"folder for another scene")
    ct = run / "config.toml"
    if ct.is_file():
        old = from_toml(ct)
        if config_hash(old) != config_hash(cfg):
            diff = config_difference(old, cfg)
            raise OutputError(f"{run}: cannot resume with another training configuration ("
                              + ("; ".join(diff[:6]) + ("; ..." if len(diff) > 6 else "")
                                 if diff else "the training semantics changed")
                              + "): drop the changes, or train into another --out folder")
