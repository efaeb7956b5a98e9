"""What a command may write: run folders owned by one process, no output onto a run's records or
into a scene, and resumes that check what they resume.

* :class:`RunLock`: a run folder is written by one process at a time (``fcntl.flock`` on
  ``RUN/.pgs.lock``; the kernel releases it when the process ends, however it ends, so a crash
  never leaves it held).
* :func:`scene_identity` / :func:`check_resume`: a run records what it was trained on (scene
  path, format, the views' names and sizes, the protocol); resuming it on another scene or with
  another training configuration is refused, with the difference named.
* :func:`check_output`: the one rule every command that writes applies to its output paths
  (the command line and the Python API alike). An output that does not exist, an empty folder,
  or the command's own earlier output for the same input (a folder holding the toolkit's
  marker file :data:`MARKER_NAME` naming that command and input, a run being resumed, a report
  being rebuilt) is accepted; ``overwrite`` also accepts another output of the toolkit or an
  existing file; a folder holding files the toolkit did not write is never written into. Every
  refusal is one :class:`OutputError` line naming the path and the flag.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Optional, Union

# the files that make a folder a run (pgs train / pgs compare write them)
RUN_FILES = ("checkpoint.pt", "config.toml", "results.json", "scene.json", "train_log.jsonl",
             "compare.json", "model.pgs")
LOCK_NAME = ".pgs.lock"
# written by the toolkit into every output folder it creates (decode, render, compare, ...):
# {"command": ..., "input": ...}; a folder holding it is the toolkit's own
MARKER_NAME = ".pgs-output"


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
    executes, ``train.device``, and how often it saves, ``train.checkpoint_every``, are not
    differences)."""
    from baseline.config import EXECUTION_KEYS, SAVING_KEYS, to_dict

    a, b = to_dict(old_cfg, drop_meta=True), to_dict(new_cfg, drop_meta=True)
    for sec, key in list(EXECUTION_KEYS) + list(SAVING_KEYS):
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
        from baseline.fileio import read_json_bounded

        try:
            rec = read_json_bounded(sj, "a run's scene record", cap=1 << 20)
        except (OSError, ValueError):
            rec = {}
        rec = rec if isinstance(rec, dict) else {}
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


# ---------------------------------------------------------------------------- the output rule
Source = Union[str, "os.PathLike[str]", dict, None]


def _source_key(source: Source):
    """What a marker records as a command's input: a path as its absolute resolved form, a dict
    of parameters (``make-scene``) as it is."""
    if source is None or isinstance(source, dict):
        return source
    return str(Path(source).expanduser().resolve())


def _shown(source) -> str:
    if isinstance(source, dict):
        return ", ".join(f"{k}={v}" for k, v in source.items())
    return str(source)


def read_marker(folder) -> dict | None:
    """The marker of a toolkit output folder (``{"command", "input"}``), else None."""
    from baseline.fileio import read_json_bounded

    m = Path(folder) / MARKER_NAME
    if not m.is_file():
        return None
    try:
        rec = read_json_bounded(m, "an output marker", cap=1 << 20)
    except ValueError:
        return None
    return rec if isinstance(rec, dict) and "command" in rec else None


def write_marker(folder, command: str, source: Source = None) -> None:
    """Mark ``folder`` (created if missing) as ``command``'s output for ``source`` (atomic)."""
    from baseline.fileio import write_text_atomic

    write_text_atomic(Path(folder) / MARKER_NAME,
                      json.dumps({"command": command, "input": _source_key(source)}, indent=1))


def folder_entries(folder) -> list[str]:
    """The entries of ``folder`` other than the toolkit's lock and marker files, a marker
    another process is writing included (two commands started at once into one new folder,
    one per core, each see the other's temporary marker)."""
    from baseline.fileio import is_temporary_of

    return sorted(x for x in os.listdir(folder)
                  if x not in (LOCK_NAME, MARKER_NAME) and not is_temporary_of(x, MARKER_NAME))


def check_output(path, *, command: str, source: Source = None, folder: bool = False,
                 overwrite: bool = False, own: Callable[[Path], bool] | None = None,
                 may_be_run: bool = False, shares: tuple = (),
                 flag: str = "--overwrite") -> bool:
    """May ``command`` (``"decode"``, ``"encode"``, ...) write its output at ``path``?

    Args:
        path: the output file, or with ``folder`` the output folder.
        command: the writing command's name, as its marker records it.
        source: its input (a path, or a dict of parameters); an output of the same command for
            another input is not its own.
        overwrite: the user asked to replace: an existing file, or a folder holding another
            output of the toolkit, is accepted (a folder holding files the toolkit did not
            write is still refused: nothing would say which of them it may replace).
        own: ``own(path) -> bool`` for outputs the command recognises as its own without a
            marker (a ``.pgs`` file its run's record names, a folder written before markers).
        may_be_run: the folder may be a run (``train --resume``).
        shares: other commands whose output for the same input may share the folder (``pgs
            eval`` of a ``.pgs`` file renders into the folder ``pgs decode`` writes).
        flag: the option that sets ``overwrite``, named in refusals.

    Accepted: a path that does not exist; an empty folder (lock and marker files aside); a
    folder whose marker names ``command`` (or one of ``shares``) and ``source``; a path inside
    the run folder ``source`` names (the run's own outputs: renders, exports, measurements,
    but never its record files without ``overwrite``); anything ``own`` accepts; with
    ``overwrite`` an existing file or a folder of the toolkit's. Never: a path inside a scene
    folder, a run's record file (without ``overwrite``), a folder that holds a run (without
    ``may_be_run`` or ``overwrite``), a special file (device, pipe, socket).

    Returns True when ``path`` exists (the caller writes over its own earlier output); raises
    :class:`OutputError` (one line, the path and ``flag`` named) otherwise. Writers then write
    through :mod:`baseline.fileio` (atomic) and mark the folders they create
    (:func:`write_marker`).
    """
    import stat as _stat

    p = Path(path).expanduser().absolute()
    root = scene_root(p if folder else p.parent)
    if root is not None and not (command == "make-scene" and root == p):
        raise OutputError(f"{p}: inside the scene folder {root}; the toolkit never writes into "
                          f"a scene: choose a path outside it")
    try:
        st = os.stat(p)
    except FileNotFoundError:
        return False
    except OSError as e:
        raise OutputError(f"{p}: cannot be checked ({e.strerror or e})") from None
    want = _source_key(source)
    in_run = (isinstance(want, str) and is_run_folder(Path(want))
              and Path(want) in p.resolve().parents)
    if not folder:
        if _stat.S_ISDIR(st.st_mode):
            raise OutputError(f"{p}: is a folder; give a file name")
        if not _stat.S_ISREG(st.st_mode):
            raise OutputError(f"{p}: not a regular file (a device, pipe or socket); choose "
                              f"another path ({flag} does not apply to it)")
        if p.name in RUN_FILES and is_run_folder(p.parent) and not overwrite:
            raise OutputError(f"{p}: is the {p.name} of the run {p.parent}; writing there would "
                              f"replace it (choose another path, or {flag})")
        if overwrite or in_run or (own is not None and own(p)):
            return True
        raise OutputError(f"{p}: exists and is not pgs {command}'s output for {_shown(want)}; "
                          f"it is left as it is (choose another path, or {flag} to replace it)")
    if not _stat.S_ISDIR(st.st_mode):
        raise OutputError(f"{p}: exists and is not a folder")
    if is_run_folder(p):
        if may_be_run:
            return True
        raise OutputError(f"{p}: holds a run (config.toml with a checkpoint or results); "
                          f"writing there would replace its records (choose another folder"
                          + (f", or {flag})" if command == "train" else ")"))
    entries = folder_entries(p)
    if not entries or in_run:
        return True
    mark = read_marker(p) or _implied_marker(p)
    if mark is not None:
        if (mark.get("command") in (command, *shares) and mark.get("input") == want) \
                or overwrite:
            return True
        had = mark.get("input")
        if mark.get("command") == command and isinstance(had, dict) and isinstance(want, dict):
            diff = ", ".join(f"{k}: {had.get(k)} -> {want.get(k)}" for k in want
                             if had.get(k) != want.get(k))
            raise OutputError(f"{p}: holds pgs {command}'s output for other arguments ({diff}); "
                              f"choose another folder, or {flag} to replace it")
        held = f"pgs {mark.get('command')}'s output for {_shown(had)}"
        raise OutputError(f"{p}: holds {held}; choose another folder, or {flag} to write "
                          f"pgs {command}'s output into it")
    if own is not None and own(p):
        return True
    shown = ", ".join(entries[:4]) + (f" and {len(entries) - 4} more" if len(entries) > 4 else "")
    raise OutputError(f"{p}: holds files pgs did not write ({shown}); choose an empty or new "
                      f"folder ({flag} writes only into the toolkit's own folders)")


def _implied_marker(folder: Path) -> dict | None:
    """The toolkit's own records read as a marker where a folder has none: a run (its
    ``scene.json``, written before the first checkpoint) is ``pgs train``'s output for its
    scene; a synthetic scene (its ``synthetic.json``) is ``pgs make-scene``'s for its
    arguments; a comparison or a benchmark (its ``results.json``, also in an archive of its
    records) is ``pgs compare``'s for its scene or ``pgs benchmark``'s for its root."""
    from baseline.fileio import read_json_bounded

    def rec(name):
        f = folder / name
        if not f.is_file():
            return None
        try:
            r = read_json_bounded(f, "a record", cap=1 << 20)
        except ValueError:
            return None
        return r if isinstance(r, dict) else None

    run = rec("scene.json")
    if run is not None and isinstance(run.get("path"), str) and "views_digest" in run:
        return {"command": "train", "input": run["path"]}
    syn = rec("synthetic.json")
    if syn is not None and syn.get("generator") == "baseline.data.synthetic":
        return {"command": "make-scene",
                "input": {k: v for k, v in syn.items() if k != "generator"}}
    res = rec("results.json")
    fmt = res.get("format") if res is not None else None
    if fmt == "pgs-compare/1" and isinstance(res.get("scene"), str):
        return {"command": "compare", "input": res["scene"]}
    if fmt == "pgs-benchmark/1" and isinstance(res.get("root"), str):
        return {"command": "benchmark", "input": res["root"]}
    return None
