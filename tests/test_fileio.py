"""Atomic writes: a failed or interrupted write never loses or tears what was already written."""
import os
import stat

import pytest

import baseline.fileio as fileio_mod
from baseline.codec.container import read_container, write_container
from baseline.fileio import atomic_path, write_bytes_atomic, write_text_atomic


def _umask() -> int:
    m = os.umask(0)
    os.umask(m)
    return m


def test_write_creates_parents_counts_bytes_and_leaves_nothing_else(tmp_path):
    p = tmp_path / "a" / "b" / "x.json"
    assert write_text_atomic(p, "héllo") == len("héllo".encode())
    assert p.read_text(encoding="utf-8") == "héllo"
    assert write_bytes_atomic(p, b"\x00\x01") == 2            # overwrite
    assert p.read_bytes() == b"\x00\x01"
    assert [q.name for q in p.parent.iterdir()] == ["x.json"]
    # umask-derived permissions, not mkstemp's 0600
    assert stat.S_IMODE(p.stat().st_mode) == 0o666 & ~_umask()


@pytest.mark.parametrize("exc", [OSError("disk full"), KeyboardInterrupt()])
def test_failure_inside_the_block_keeps_the_old_file(tmp_path, exc):
    p = tmp_path / "model.bin"
    p.write_bytes(b"old")
    with pytest.raises(type(exc)):
        with atomic_path(p) as tmp:
            assert tmp.parent == p.parent and tmp.suffix == ".bin" and tmp.name.startswith(".")
            tmp.write_bytes(b"half-writ")
            raise exc
    assert p.read_bytes() == b"old"
    assert [q.name for q in tmp_path.iterdir()] == ["model.bin"]


def test_failed_rename_keeps_the_old_container_and_cleans_up(tmp_path, monkeypatch):
    p = tmp_path / "m.pgs"
    n = write_container(p, {"a": 1}, [("s", b"payload")])
    assert n == p.stat().st_size

    def boom(src, dst):
        raise OSError("rename failed")
    monkeypatch.setattr(fileio_mod.os, "replace", boom)
    with pytest.raises(OSError, match="rename failed"):
        write_container(p, {"a": 2}, [("s", b"other")])
    header, sections = read_container(p)
    assert header["a"] == 1 and sections["s"] == b"payload"
    assert [q.name for q in tmp_path.iterdir()] == ["m.pgs"]


def test_writer_that_creates_nothing_is_an_error(tmp_path):
    p = tmp_path / "x.png"
    with pytest.raises(FileNotFoundError, match="did not create"):
        with atomic_path(p):
            pass
    assert not p.exists() and list(tmp_path.iterdir()) == []


def test_no_fsync_path_writes_the_same(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(fileio_mod.os, "fsync", lambda fd: calls.append(fd))
    write_bytes_atomic(tmp_path / "a", b"1", fsync=False)
    assert calls == [] and (tmp_path / "a").read_bytes() == b"1"
    write_bytes_atomic(tmp_path / "b", b"2")
    assert len(calls) == 2                                  # the file, then its folder
