"""The rules every command follows, one class at a time: what may be written (guard.check_output),
how a user's file is read (bounded, by type), allocation failures as named errors, models far
outside their scene refused, and an infinite PSNR said in words."""
import json
import os
import shutil
import struct
import zlib

import pytest
import torch

from baseline.cli import main
from baseline.guard import OutputError, check_output, write_marker


# ------------------------------------------------------------------------- the output rule
def test_check_output_accepts_new_empty_and_own_outputs_only(tmp_path):
    new = tmp_path / "new"
    assert check_output(new, command="decode", source="a.pgs", folder=True) is False
    new.mkdir()
    (new / ".pgs.lock").write_text("1")                       # the toolkit's lock: still empty
    assert check_output(new, command="decode", source="a.pgs", folder=True) is True
    write_marker(new, "decode", "a.pgs")
    (new / "point_cloud.ply").write_text("x")
    assert check_output(new, command="decode", source="a.pgs", folder=True)
    for cmd, src in (("decode", "b.pgs"), ("render", "a.pgs")):   # another input / command
        with pytest.raises(OutputError, match="holds pgs decode's output for .*a.pgs.*--overwrite"):
            check_output(new, command=cmd, source=src, folder=True)
        assert check_output(new, command=cmd, source=src, folder=True, overwrite=True)
    assert check_output(new, command="eval", source="a.pgs", folder=True, shares=("decode",))
    user = tmp_path / "user"
    user.mkdir()
    (user / "results.json").write_text("{}")
    for ow in (False, True):                          # a folder of the user's: never
        with pytest.raises(OutputError, match=r"holds files pgs did not write \(results.json\)"):
            check_output(user, command="train", source="s", folder=True, overwrite=ow)
    f = tmp_path / "notes.txt"
    f.write_text("mine")
    with pytest.raises(OutputError, match="notes.txt: exists and is not pgs encode's output"):
        check_output(f, command="encode", source="run")
    assert check_output(f, command="encode", source="run", overwrite=True)
    assert check_output(f, command="encode", source="run", own=lambda p: p.name == "notes.txt")
    with pytest.raises(OutputError, match="is a folder"):
        check_output(user, command="encode", source="run")
    with pytest.raises(OutputError, match="not a regular file"):
        check_output("/dev/null", command="encode", source="run", overwrite=True)
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)
    with pytest.raises(OutputError, match="not a regular file"):
        check_output(fifo, command="export-ply", source="run", overwrite=True)
    assert f.read_text() == "mine" and (user / "results.json").read_text() == "{}"


def test_check_output_while_another_command_marks_the_same_new_folder(tmp_path):
    """Two commands started at once into one new folder (``pgs compare --only``, one per
    core): the second sees the first's marker half-written (its atomic temporary file) and
    still finds the folder empty; a file named like it but not one is the user's."""
    from baseline.fileio import atomic_path
    from baseline.guard import MARKER_NAME

    out = tmp_path / "out"
    out.mkdir()
    with atomic_path(out / MARKER_NAME) as tmp:          # the other command's write, in flight
        tmp.write_text("{")
        assert check_output(out, command="compare", source="scene", folder=True) is True
    (out / MARKER_NAME).unlink()
    (out / "..pgs-output.1d4d0c35.tmp").write_text("{")  # the name that write uses
    assert check_output(out, command="compare", source="scene", folder=True) is True
    for name in ("..pgs-output.notahex!.tmp", ".pgs-output.1d4d0c35.tmp", "..pgs-output.1d4d.tmp"):
        (out / name).write_text("x")
        with pytest.raises(OutputError, match="holds files pgs did not write"):
            check_output(out, command="compare", source="scene", folder=True)
        (out / name).unlink()


def test_check_output_for_runs_and_scenes(tmp_path, small_scene):
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.toml").write_text("")
    (run / "results.json").write_text("{}")
    with pytest.raises(OutputError, match="holds a run"):
        check_output(run, command="decode", source="a.pgs", folder=True, overwrite=True)
    assert check_output(run, command="train", source=small_scene, folder=True, may_be_run=True)
    with pytest.raises(OutputError, match="is the results.json of the run"):
        check_output(run / "results.json", command="encode", source=run)
    # inside the run a command reads: the run's own outputs (renders, exports, measurements)
    (run / "renders").mkdir()
    (run / "renders" / "0.png").write_text("x")
    assert check_output(run / "renders", command="eval", source=run, folder=True)
    (run / "point_cloud.ply").write_text("x")
    assert check_output(run / "point_cloud.ply", command="export-ply", source=run)
    with pytest.raises(OutputError, match="inside the scene folder"):
        check_output(small_scene / "out", command="decode", source="a.pgs", folder=True)
    # a started training (scene.json, no checkpoint yet) is train's output for its scene
    started = tmp_path / "started"
    started.mkdir()
    (started / "scene.json").write_text(json.dumps({"path": str(small_scene.resolve()),
                                                    "views_digest": "x"}))
    assert check_output(started, command="train", source=small_scene, folder=True)
    with pytest.raises(OutputError, match="holds pgs train's output for"):
        check_output(started, command="train", source=tmp_path, folder=True)


# --------------------------------------------------------------------------- bounded reads
def test_bounded_reads_refuse_special_files_by_type(tmp_path, monkeypatch):
    from baseline.fileio import (
        UnreadableFile,
        check_readable,
        read_bytes_bounded,
        read_json_bounded,
    )

    for path, what in (("/proc/self/pagemap", "/proc or /sys"), ("/proc/self/status", "/proc"),
                       ("/dev/zero", "a device"), (tmp_path, "is a directory"),
                       (tmp_path / "none", "no such file")):
        with pytest.raises(UnreadableFile, match=what):
            read_bytes_bounded(path, "a record")
    fifo = tmp_path / "fifo"
    os.mkfifo(fifo)                              # never opened: an open would block
    with pytest.raises(UnreadableFile, match=r"not a regular file \(a pipe \(FIFO\)\)"):
        check_readable(fifo)
    big = tmp_path / "big.json"
    big.write_text("[" + "0," * (1 << 20) + "0]")
    monkeypatch.setenv("PGS_MAX_FILE_MB", "1")
    with pytest.raises(UnreadableFile, match="above the 1048576-byte cap"):
        read_json_bounded(big)
    monkeypatch.delenv("PGS_MAX_FILE_MB")
    assert len(read_json_bounded(big)) == (1 << 20) + 1
    with pytest.raises(UnreadableFile, match="above the 100-byte cap"):
        read_json_bounded(big, cap=100)
    (tmp_path / "bad.json").write_text("{nope")
    with pytest.raises(UnreadableFile, match="bad.json: not valid JSON"):
        read_json_bounded(tmp_path / "bad.json")


def _with_first_section(data: bytes, length: int) -> bytes:
    """``data`` with its first section's declared length set to ``length`` (table CRC fixed)."""
    from baseline.codec.container import _parse

    _, secs = _parse(data, "x")
    hlen = struct.unpack_from("<I", data, 6)[0]
    t0 = 14 + hlen + 4
    t1 = len(data) - sum(len(p) for p in secs.values()) - 4
    b = bytearray(data)
    struct.pack_into("<Q", b, t0 + 2 + struct.unpack_from("<H", data, t0)[0], length)
    struct.pack_into("<I", b, t1, zlib.crc32(bytes(b[t0:t1])) & 0xFFFFFFFF)
    return bytes(b)


def test_a_pgs_file_is_read_section_by_section(tmp_path):
    """A first section declared 600 MB in a sparse file of that size: its CRC fails after a
    bounded read (the reader never holds the section), and the message names it."""
    import tracemalloc

    from baseline.codec.container import BitstreamError, build_container, read_container

    good = build_container({"a": 1}, [("positions", b"p" * 1000), ("feat", b"f" * 5000)])
    size = 600 << 20
    path = tmp_path / "sparse.pgs"
    with open(path, "wb") as f:
        f.write(_with_first_section(good, size))
        f.truncate(len(good) - 1000 + size)
    tracemalloc.start()
    with pytest.raises(BitstreamError, match="sparse.pgs: CRC mismatch in section 'positions'"):
        read_container(path)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 64 << 20, peak
    path.write_bytes(good)
    assert read_container(path)[0] == {"a": 1}


# ---------------------------------------------------------------------- allocation failures
def test_allocation_failures_become_one_named_line():
    from baseline.memory import AllocationError, allocating

    torch_msg = ("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't "
                 "allocate memory: you tried to allocate 34359738368 bytes. Error code 12")
    with pytest.raises(AllocationError, match=r"^out of memory decoding x.pgs: an allocation of "
                       r"32,768 MiB failed; about 1 MiB planned within the 2 MiB budget \(B\); "
                       r"this process has"), \
            allocating("decoding x.pgs", planned=1 << 20, budget=2 << 20, budget_name="B"):
        raise RuntimeError(torch_msg)
    with pytest.raises(AllocationError, match="rendering: an allocation of 1,536 MiB failed"), \
            allocating("rendering"):
        raise MemoryError("Unable to allocate 1.50 GiB for an array with shape (9,)")
    with pytest.raises(AllocationError, match="training: an allocation failed"), \
            allocating("training"):
        raise MemoryError()
    with pytest.raises(RuntimeError, match="a bug"), allocating("training"):   # unchanged
        raise RuntimeError("a bug")


def test_the_cli_names_allocation_failures_and_keeps_internal_error_for_bugs(
        decoded_files, tmp_path, monkeypatch, capsys):
    import baseline.modelfile as mc

    f = decoded_files["noscene"]

    def fail(msg):
        def boom(*a, **kw):
            raise RuntimeError(msg)
        return boom

    monkeypatch.setattr(mc, "_decode_model",
                        fail("DefaultCPUAllocator: can't allocate memory: you tried to allocate "
                             "1073741824 bytes"))
    assert main(["decode", str(f), "-o", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"pgs decode: error: out of memory decoding {f}: an allocation of "
                          f"1,024 MiB failed") and "internal error" not in err
    assert len(err.splitlines()) == 1 and not (tmp_path / "o").exists()
    monkeypatch.setattr(mc, "_decode_model", fail("an index out of range"))
    assert main(["decode", str(f), "-o", str(tmp_path / "o")]) == 2
    assert "internal error (RuntimeError: an index out of range)" in capsys.readouterr().err


def test_a_decode_over_the_machine_under_a_raised_budget_is_named(decoded_files, tmp_path):
    """PGS_DECODE_MEMORY_MB raised beyond an address-space limit: a header planning 32 GiB of
    hash-grid tables (re-signed, so every check but the budget passes) fails its allocation:
    one line naming the file, the size and the budget, exit 2."""
    import subprocess
    import sys

    from baseline.codec.container import _parse
    from baseline.testing.hostile import _edit, _resign

    h, s = _parse((decoded_files["baseline"] / "model.pgs").read_bytes(), "x")
    for path, v in (("entropy.grid.log2_table_3d", 24), ("entropy.grid.n_features", 16),
                    ("entropy.grid.resolutions_3d", [65536] * 32)):
        h = _edit(h, path, v)
    bomb = tmp_path / "bomb.pgs"
    bomb.write_bytes(_resign(h, list(s.items())))
    code = ("import resource, sys; from baseline.cli import main; import torch; "
            "v = int(open('/proc/self/statm').read().split()[0]) * 4096; "
            "resource.setrlimit(resource.RLIMIT_AS, (v + (2 << 30), v + (2 << 30))); "
            f"sys.exit(main(['decode', {str(bomb)!r}, '-o', {str(tmp_path / 'o')!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=False,
                       env=dict(os.environ, PGS_DECODE_MEMORY_MB="100000000"))
    err = r.stderr.strip()
    assert r.returncode == 2 and len(err.splitlines()) == 1, err
    assert f"out of memory decoding {bomb}" in err and "PGS_DECODE_MEMORY_MB" in err, err
    assert "MiB failed" in err and "internal error" not in err
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------ models outside their scene
@pytest.fixture()
def run_copy(decoded_files, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(decoded_files["baseline"], run)
    return run


@pytest.mark.parametrize("key,value,what", [("per_anchor.xyz", 1e30, "anchor positions"),
                                            ("per_anchor.scaling", 200.0, "Gaussian scales"),
                                            ("per_anchor.offsets", 1e36, "Gaussian offsets")])
def test_anchors_far_outside_the_scene_are_refused(run_copy, key, value, what, capsys):
    from baseline.run import load_run

    ck = run_copy / "checkpoint.pt"
    s = torch.load(ck, weights_only=False)
    s["model"][key][3] = value
    torch.save(s, ck)
    with pytest.raises(ValueError, match=f"checkpoint .*: 1 of [0-9]+ anchors have {what} "
                                         f"non-finite or beyond 10000 x the scene extent"):
        load_run(run_copy, device="cpu")
    assert main(["encode", str(run_copy), "-o", str(run_copy.parent / "m.pgs")]) == 2
    err = capsys.readouterr().err
    assert what in err and "the worst is" in err and not (run_copy.parent / "m.pgs").exists()


def test_a_file_far_outside_its_scene_is_refused_at_encode_and_decode(decoded_files, tmp_path,
                                                                    capsys):
    from baseline.modelfile import encode_model
    from baseline.data.scene import load_scene, scene_bounds
    from baseline.run import load_run

    run = tmp_path / "run"
    shutil.copytree(decoded_files["baseline"], run)
    t, scene = load_run(run, device="cpu")
    with torch.no_grad():
        t.model.per_anchor["xyz"][0] = 1e30
    with pytest.raises(ValueError, match=r"encoding .*: 1 of .* anchor positions .* the worst "
                                         r"is 1e\+30"):
        encode_model(t.cfg, t.model, t.entropy, tmp_path / "x.pgs",
                     scene_bounds=scene_bounds(scene))
    assert not (tmp_path / "x.pgs").exists()
    # a file written without the check (an older toolkit, whose runs trained at the float
    # positions: no box to clamp them into) is refused where its scene is known
    t.model.position_box = None
    encode_model(t.cfg, t.model, t.entropy, tmp_path / "far.pgs",
                 extra_header={"scene": str(decoded_files["scene"])})
    assert main(["decode", str(tmp_path / "far.pgs"), "-o", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "1 of" in err and "anchor positions" in err and not (tmp_path / "d").exists()
    assert scene_bounds(load_scene(decoded_files["scene"]))[1] > 0


def test_an_infinite_psnr_is_said_in_words():
    import math

    from baseline.eval.metrics import format_psnr, psnr

    img = torch.zeros(8, 8, 3)
    assert psnr(img, img) == math.inf
    assert format_psnr(math.inf).startswith("infinite (the images compared are identical")
    assert "dB" not in format_psnr(math.inf) and format_psnr(float("nan")).startswith("undefined")
    assert format_psnr(25.314) == "25.31 dB" and format_psnr(25.3149, 3) == "25.315 dB"
