"""Atomic file writing: the one way every output of the toolkit reaches the disk.

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
"""
from __future__ import annotations

import os
import secrets
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Union

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
    tmp = folder / f".{path.stem}.{secrets.token_hex(4)}.tmp{path.suffix}"
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
