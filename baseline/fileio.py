"""Atomic file writing, the one way every output of the toolkit reaches the disk, and bounded
reading, the one way a user's file is read.

A reader (a resumed comparison, ``pgs info``, a user's viewer) never sees a half-written file,
and a write that fails or is interrupted leaves the previous file, if any, untouched:

1. the writer writes a temporary file in the destination folder (same file system, so the
   rename is atomic), named ``.<stem>.<random>.tmp<suffix>`` so writers that pick a format from
   the extension (OpenImageIO, matplotlib) still see it;
2. the temporary file is flushed to disk (``fsync``), then renamed over the destination with
   ``os.replace``; the folder entry is synced too, where the platform allows;
3. on any error (including ``KeyboardInterrupt``) the temporary file is removed and the error
   propagates.

The temporary file is created by the writer itself (not pre-created with ``mkstemp``, whose
0600 mode would stick), so written files get the usual umask-derived permissions.

The standard library has no atomic writer, and the small packages that offer one
(``atomicwrites``, archived) would add a dependency for these thirty lines.

Reading (:func:`read_bytes_bounded`, :func:`read_text_bounded`, :func:`read_json_bounded`,
:func:`open_checked`): a path is checked by its type before it is opened (a folder, a FIFO, a
device, a socket or a file of the kernel's pseudo-file systems ``/proc`` and ``/sys`` is refused:
it could block the open or never end), then read in bounded chunks up to a cap: the file's own
size where the OS reports one, and in any case :func:`max_file_bytes` (``PGS_MAX_FILE_MB``), which
is also the whole bound for a file that reports size 0. Every refusal is one
:class:`UnreadableFile` (a ``ValueError``) naming the path.
"""
from __future__ import annotations

import os
import secrets
import stat as _stat
from contextlib import contextmanager
from pathlib import Path
from typing import BinaryIO, Iterator, Union

PathLike = Union[str, "os.PathLike[str]"]


def _fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_dir(folder: Path) -> None:
    try:                                    # not every platform can open a folder (Windows)
        fd = os.open(folder, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


_TOKEN_HEX = 8      # the random part of a temporary name: 4 bytes as hex


def _temporary_name(path: Path) -> str:
    return f".{path.stem}.{secrets.token_hex(_TOKEN_HEX // 2)}.tmp{path.suffix}"


def is_temporary_of(name: str, target: str) -> bool:
    """Whether the folder entry ``name`` is a temporary file that :func:`atomic_path` writes
    for a file named ``target`` (another process's write in flight, or one a killed process
    left behind)."""
    t = Path(target)
    head, tail = f".{t.stem}.", f".tmp{t.suffix}"
    token = name[len(head):len(name) - len(tail)]
    return (name.startswith(head) and name.endswith(tail) and len(token) == _TOKEN_HEX
            and all(c in "0123456789abcdef" for c in token))


@contextmanager
def atomic_path(path: PathLike, *, fsync: bool = True) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; when the block ends cleanly, move it onto ``path``.

    The block must create the file at the yielded path (``torch.save(obj, tmp)``,
    ``fig.savefig(tmp)``, ...). Parent folders are created. On an error inside the block or in
    the final rename, the temporary file is removed and the error re-raised; ``path`` is left as
    it was.
    """
    path = Path(path)
    folder = path.parent
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / _temporary_name(path)
    try:
        yield tmp
        if not tmp.is_file():
            raise FileNotFoundError(f"atomic write of {path}: the writer did not create {tmp}")
        if fsync:
            _fsync_file(tmp)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    if fsync:
        _fsync_dir(folder)


def write_bytes_atomic(path: PathLike, data: bytes, *, fsync: bool = True) -> int:
    """Write ``data`` to ``path`` atomically; returns the byte count."""
    with atomic_path(path, fsync=fsync) as tmp:
        with open(tmp, "wb") as f:
            f.write(data)
    return len(data)


def write_text_atomic(path: PathLike, text: str, *, fsync: bool = True) -> int:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the byte count."""
    return write_bytes_atomic(path, text.encode("utf-8"), fsync=fsync)


# ------------------------------------------------------------------------------ bounded reading
DEFAULT_MAX_FILE_MB = 4096
CHUNK = 1 << 24                 # bytes read at a time where the size is not known in advance
RECORD_CAP = 256 << 20          # JSON / TOML records, logs, scene text files


class UnreadableFile(ValueError):
    """A user's file that is missing, not a regular file, or larger than its cap."""


def max_file_bytes() -> int:
    """The largest file a reader accepts: ``PGS_MAX_FILE_MB`` (MiB, a finite number above 0),
    else 4 GiB (truck ``.pgs`` files are 4-6 MB, checkpoints tens of MB)."""
    env = os.environ.get("PGS_MAX_FILE_MB", "").strip()
    if not env:
        return DEFAULT_MAX_FILE_MB << 20
    try:
        mb = float(env)
    except ValueError:
        raise ValueError(f"PGS_MAX_FILE_MB={env!r} is not a number of MiB") from None
    if not (mb > 0 and mb < float(1 << 40)):
        raise ValueError(f"PGS_MAX_FILE_MB={env!r} must be a finite number of MiB above 0")
    return int(mb * (1 << 20))


def _pseudo_devices() -> set:
    """Device ids of the kernel's pseudo-file systems (procfs, sysfs): their files report size
    0 or 4096 whatever they hold, and some never end (``/proc/self/pagemap``)."""
    devs = set()
    for root in ("/proc", "/sys"):
        try:
            devs.add(os.stat(root).st_dev)
        except OSError:
            pass
    return devs


def _type_error(where: str, st: os.stat_result, what: str) -> str | None:
    if _stat.S_ISDIR(st.st_mode):
        return f"{where}: is a directory, not {what}"
    if not _stat.S_ISREG(st.st_mode):
        kind = ("a pipe (FIFO)" if _stat.S_ISFIFO(st.st_mode) else
                "a device" if _stat.S_ISCHR(st.st_mode) or _stat.S_ISBLK(st.st_mode) else
                "a socket" if _stat.S_ISSOCK(st.st_mode) else "a special file")
        return f"{where}: not a regular file ({kind}), not {what}"
    if st.st_dev in _pseudo_devices():
        return f"{where}: a file of the kernel's /proc or /sys, not {what}"
    return None


def check_readable(path: PathLike, what: str = "a file") -> os.stat_result:
    """``os.stat`` of a regular file the toolkit may read, else :class:`UnreadableFile`
    naming it (missing, a folder, a FIFO, a device, a socket, a /proc or /sys file)."""
    where = str(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise UnreadableFile(f"{where}: no such file") from None
    except OSError as e:
        raise UnreadableFile(f"{where}: cannot read it ({e.strerror or e})") from None
    msg = _type_error(where, st, what)
    if msg:
        raise UnreadableFile(msg)
    return st


def _cap_for(cap: int | None) -> tuple[int, str]:
    env_cap = max_file_bytes()
    if cap is None or cap >= env_cap:
        return env_cap, "PGS_MAX_FILE_MB raises it"
    return cap, "the limit for this kind of file"


def open_checked(path: PathLike, what: str = "a file",
                 cap: int | None = None) -> tuple[BinaryIO, int, int]:
    """Open a regular file for reading after :func:`check_readable`: ``(file, size, cap)``.

    ``size``: the size the OS reports (0: not reported, the file may still hold bytes);
    ``cap``: the most a reader may take (``cap`` and :func:`max_file_bytes`, the smaller). A
    file whose reported size is above the cap is refused before it is opened; the open itself
    never blocks (``O_NONBLOCK``, and the type is checked again on the open file, so a path
    swapped for a FIFO meanwhile is refused too)."""
    where = str(path)
    st = check_readable(path, what)
    limit, why = _cap_for(cap)
    if st.st_size > limit:
        raise UnreadableFile(f"{where}: {st.st_size} bytes, above the {limit}-byte cap for "
                             f"{what} ({why})")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
    except OSError as e:
        raise UnreadableFile(f"{where}: cannot read it ({e.strerror or e})") from None
    st = os.fstat(fd)
    msg = _type_error(where, st, what)
    if msg:
        os.close(fd)
        raise UnreadableFile(msg)
    return os.fdopen(fd, "rb"), int(st.st_size), limit


def read_bytes_bounded(path: PathLike, what: str = "a file", cap: int | None = None) -> bytes:
    """The bytes of a regular file, read in bounded chunks, never more than the cap (see
    :func:`open_checked`); a file longer than the cap is refused once the cap is passed."""
    where = str(path)
    f, size, limit = open_checked(path, what, cap)
    _, why = _cap_for(cap)
    parts, got = [], 0
    try:
        with f:
            # read(n) allocates n bytes up front: ask for the reported size (plus one byte to
            # see a file that grew), then bounded chunks up to the cap
            first = min(size, limit) + 1 if size else min(CHUNK, limit + 1)
            while got <= limit:
                more = f.read(first if not parts else min(CHUNK, limit + 1 - got))
                if not more:
                    break
                parts.append(more)
                got += len(more)
    except OSError as e:
        raise UnreadableFile(f"{where}: cannot read it ({e.strerror or e})") from None
    if got > limit:
        raise UnreadableFile(f"{where}: more than the {limit}-byte cap for {what} ({why})")
    return b"".join(parts)


def read_text_bounded(path: PathLike, what: str = "a text file",
                      cap: int | None = RECORD_CAP) -> str:
    """A UTF-8 text file read as :func:`read_bytes_bounded` reads (capped at ``cap``)."""
    try:
        return read_bytes_bounded(path, what, cap).decode("utf-8")
    except UnicodeDecodeError as e:
        raise UnreadableFile(f"{path}: not UTF-8 text ({e.reason} at byte {e.start}), not "
                             f"{what}") from None


def read_json_bounded(path: PathLike, what: str = "a JSON record",
                      cap: int | None = RECORD_CAP):
    """A JSON file's value, read as :func:`read_text_bounded` reads; invalid JSON is an
    :class:`UnreadableFile` naming the line."""
    import json

    text = read_text_bounded(path, what, cap)
    try:
        return json.loads(text)
    except ValueError as e:
        raise UnreadableFile(f"{path}: not valid JSON ({e}), not {what}") from None
