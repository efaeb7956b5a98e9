"""Hostile ``.pgs`` inputs and a decoder harness that runs them under a memory cap.

``crafted_cases(files)`` builds, from valid files (files of different methods), the inputs
a hostile but fair tester tries (``special_cases(files)`` adds those that are not bytes: a
``/proc`` file that never ends, a device, a FIFO, a sparse file declaring a 1.5 GiB section):
truncations, byte and bit flips, header fields edited (CRCs
recomputed, so the container is valid), sections swapped between the files or removed, declared
sizes far beyond the bytes present, and "deep" edits inside a section's payload with the whole
file re-signed (section digests recomputed) so they reach the inner decoders. Each case says
whether it must be refused.

:class:`DecodeHarness` runs each case in a worker process whose address space is capped
(``RLIMIT_AS`` = its size after start-up + ``cap_mb``), with a per-case timeout, through
``decode_model`` and through the ``pgs info`` / ``pgs decode`` command lines (stderr captured
at the file-descriptor level, so a Rust panic message would be seen). A case passes when the
decoder refuses it with one :class:`BitstreamError` (the command lines: exit 2 and one line,
no traceback, no panic) or, for a case marked harmless, decodes. Anything else is a finding:
another exception, a hang, the memory cap hit, a worker that died, or a silent decode of a
case that must be refused.

By hand: ``python -m baseline.testing.hostile A.pgs B.pgs [--cases N] [--cap-mb 1024]``.
"""
from __future__ import annotations

import argparse
import json
import os
import random
import select
import struct
import subprocess
import sys
import tempfile
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from baseline.codec.container import _parse, build_container
from baseline.codec.header import CODING_DEFAULTS


@dataclass
class Case:
    """``data`` written to a file and decoded; ``size``: the file then extended (sparsely) to
    that many bytes; ``path``: decode this path as it is instead (``data`` unused); ``fifo``:
    the case file is a named pipe nothing writes to."""
    name: str
    data: bytes
    must_fail: bool = True
    size: int | None = None
    path: str | None = None
    fifo: bool = False


# ------------------------------------------------------------------------------- building
def _resign(header: dict, sections: list) -> bytes:
    """A container with ``header`` and ``sections`` whose section digests are recomputed (the
    file is then as valid as the encoder would make it: only its content is hostile)."""
    from baseline.codec.header import BINDING_FIELDS, digest_sections

    h = {k: v for k, v in header.items() if k not in BINDING_FIELDS}
    h.update(digest_sections(h, sections))
    return build_container(h, sections)


def _edit(header: dict, path: str, value) -> dict:
    """A deep copy of ``header`` with ``path`` ("a.b.c", list indices as digits) set to
    ``value`` (a ``_DELETE`` value removes it)."""
    h = json.loads(json.dumps(header))
    keys = path.split(".")
    cur = h
    for k in keys[:-1]:
        cur = cur[int(k)] if isinstance(cur, list) else cur.setdefault(k, {})
    last = keys[-1]
    if isinstance(cur, list):
        cur[int(last)] = value
    elif value is _DELETE:
        cur.pop(last, None)
    else:
        cur[last] = value
    return h


_DELETE = object()

HEADER_EDITS = [
    ("n_anchors", 4194304), ("n_anchors", 16777216), ("n_anchors", 214748364),
    ("n_anchors", -1), ("n_anchors", 2 ** 63), ("n_anchors", "12"), ("n_anchors", None),
    ("n_anchors", 1.5), ("n_anchors", True), ("n_offsets", 0), ("n_offsets", 100000),
    ("n_offsets", "10"), ("position_bounds", None), ("position_bounds", [[0, 0, 0]]),
    ("position_bounds", [[0, 0, 0], [0, 0, 0]]), ("position_bounds", [[0, 0], [1, 1]]),
    ("position_bounds", [[0, 0, 0], [1e308, 1, 1]]), ("position_bounds", "box"),
    ("attrs", "feat"), ("attrs", []), ("attrs", [1, 2]), ("attrs.0.dims", 10 ** 9),
    ("attrs.0.dims", -3), ("attrs.0.dims", "50"), ("attrs.0.q0", 0), ("attrs.0.q0", -1),
    ("attrs.0.name", 5), ("attrs.0.name", "nosuch"), ("attrs.0.masked", "yes"),
    ("provider_attrs", "feat"), ("provider_attrs", ["nosuch"]),
    ("entropy", None), ("entropy", "hac"), ("entropy.kind", "nosuch"), ("entropy.kind", 3),
    ("entropy.kind", _DELETE), ("entropy.n_masks", 11), ("entropy.attrs", "x"),
    ("entropy.attrs", [["feat", 50, 1.0]]), ("entropy.hidden", 10 ** 6), ("entropy.hidden", 0),
    ("entropy.escape_limit", 2 ** 30 - 1), ("entropy.escape_limit", 0), ("entropy.chunk", 2 ** 40),
    ("entropy.chunk", 0), ("entropy.pipeline", "no"), ("entropy.grid.log2_table_3d", 30),
    ("entropy.grid.log2_table_2d", 40), ("entropy.grid.resolutions_3d", [10 ** 6]),
    ("entropy.grid.resolutions_3d", "big"), ("entropy.grid.resolutions_2d", [1.5]),
    ("entropy.grid.n_features", 1000), ("entropy.grid.planes", ["ab"]),
    ("entropy.grid.nosuch", 1), ("entropy.grid", None), ("entropy.nosuch", 1),
    ("config", "cfg"), ("config", None), ("config.model.n_offsets", 100000),
    ("config.model.feat_dim", 10 ** 6), ("config.model.hidden", 10 ** 6),
    ("config.entropy.grid.log2_table_3d", 30), ("config.entropy.grid.n_features", 1000),
    ("config.entropy.context_hidden", 10 ** 6), ("config.train.iterations", -1),
    ("config.train.log_every", 0), ("config.model.feature_provider", "nosuch"),
    ("config.model.refiner", "nosuch"), ("config.model.nosuch", 1), ("config.nosuch", {}),
    ("config.patches", "x"), ("config.entropy.mask_threshold", 2.0),
    ("module_state", "x"),
    ("module_state.provider", 3), ("module_state.provider.grid.log2_table_3d", 30),
    ("module_state.provider.grid.resolutions_3d", [2 ** 20]), ("weight_dtype", "float8"),
    ("weight_dtype", 16), ("position_coding", "octree"), ("position_coding", 1),
    ("mask_coding", "rle"), ("grid_coding", "some"), ("scene", 3), ("view_center", [0, 0]),
    ("view_center", "here"), ("file_version", 1), ("file_version", _DELETE),
    ("file_id", "zz"), ("file_id", 3), ("section_digests", _DELETE), ("section_digests", []),
    ("format", "other"), ("format", _DELETE),
]
# codings the header declares for a section: another value re-signed contradicts the payload
CODING_EDITS = [("position_coding", "sorted"), ("position_coding", "raw16"),
                ("position_coding", "lattice"),
                ("mask_coding", "patterns"), ("mask_coding", "bernoulli"),
                ("grid_coding", "used"), ("grid_coding", "all"),
                ("weight_dtype", "float16"), ("weight_dtype", "float32")]
# fields the sections do not read: edited without re-signing, the file's id no longer matches
ID_ONLY_EDITS = [("scene", "/somewhere/else"), ("scene", None), ("view_center", [1.0, 2.0, 3.0]),
                 ("config.model.voxel_size", 0.5), ("config.entropy.mask_threshold", 0.02),
                 ("config.train.seed", 7), ("weight_dtype", "float16"),
                 ("position_coding", "sorted"), ("mask_coding", "patterns"),
                 ("grid_coding", "used")]


def plugin_section_edits(header: dict) -> list:
    """Edits of the config sections plugins registered (``cfg.ext``) that the file's header
    holds: every integer key with a declared range (``RANGES``) set far past its cap (at least
    10**6: sizes a decoder would allocate from)."""
    from baseline import registry

    registry.ensure_loaded()
    cfg = header.get("config")
    edits = []
    for name in registry.names("config_section") if isinstance(cfg, dict) else ():
        section = cfg.get(name)
        if not isinstance(section, dict):
            continue
        ranges = getattr(registry.get("config_section", name), "RANGES", {})
        for key, (_, high) in ranges.items():
            if isinstance(section.get(key), int) and not isinstance(section.get(key), bool):
                edits.append((f"config.{name}.{key}", max(int(high) + 1, 10 ** 6)))
    return edits


def crafted_cases(files: dict, n_random: int = 200, seed: int = 0) -> list:
    """Cases from valid files ``{label: bytes}`` (two or more files of different methods give
    the cross-file swaps)."""
    rng = random.Random(seed)
    cases: list = []
    parsed = {k: _parse(v, k) for k, v in files.items()}
    labels = list(files)
    for label, data in files.items():
        header, secs = parsed[label]
        names = list(secs)
        # truncations: every section boundary +- 1 and evenly spaced cuts
        bounds, off = [], len(data) - sum(len(p) for p in secs.values())
        for p in secs.values():
            bounds += [off - 1, off, off + 1]
            off += len(p)
        cuts = sorted({c for c in bounds + [int(len(data) * i / 40) for i in range(40)]
                       if 0 <= c < len(data)})
        cases += [Case(f"{label}: truncated to {c} bytes", data[:c]) for c in cuts]
        # flips and overwrites (every byte is covered by a CRC)
        for _ in range(n_random // 2):
            b = bytearray(data)
            i = rng.randrange(len(b))
            bit = rng.randrange(8)
            b[i] ^= 1 << bit
            cases.append(Case(f"{label}: bit {bit} of byte {i} flipped", bytes(b)))
        for _ in range(n_random // 4):
            b = bytearray(data)
            i = rng.randrange(len(b) - 8)
            b[i:i + 8] = struct.pack("<Q", rng.choice([2 ** 64 - 1, 2 ** 63, 2 ** 32, 0]))
            if bytes(b) != data:                 # (the same bytes written back: no case)
                cases.append(Case(f"{label}: 8 bytes at {i} overwritten", bytes(b)))
        # header edits, container re-made (CRCs valid, digests as encoded)
        sec_list = list(secs.items())
        for path, value in HEADER_EDITS + plugin_section_edits(header):
            try:
                h = _edit(header, path, value)
            except (KeyError, IndexError, TypeError, ValueError):
                continue
            if h == header:
                continue
            shown = "deleted" if value is _DELETE else repr(value)[:40]
            cases.append(Case(f"{label}: header {path} = {shown}", build_container(h, sec_list)))
        n0 = header.get("n_anchors", 0)
        for value in (n0 + 1, n0 - 1, 2 * n0, 0):        # counts the sections do not hold
            h = _edit(header, "n_anchors", value)
            cases.append(Case(f"{label}: header n_anchors = {value} (file: {n0})",
                              build_container(h, sec_list)))
        for path, value in ID_ONLY_EDITS:
            try:
                h = _edit(header, path, value)
            except (KeyError, IndexError, TypeError, ValueError):
                continue
            if h != header:
                cases.append(Case(f"{label}: header {path} = {value!r} (not re-signed)",
                                  build_container(h, sec_list)))
        # a coding the sections were not written with, the file re-signed: the sections
        # contradict the header, which must be found (not decoded as something else)
        for path, value in CODING_EDITS:
            h = _edit(header, path, value)
            if header.get(path, CODING_DEFAULTS[path]) != value:   # (an absent field: default)
                cases.append(Case(f"{label}: header {path} = {value!r} (re-signed)",
                                  _resign(h, sec_list)))
        # sections removed (header untouched), and the same re-signed (the manifest then
        # agrees: the decoder must still find the component missing)
        for nm in names:
            rest = [(n, p) for n, p in sec_list if n != nm]
            cases.append(Case(f"{label}: section {nm} removed", build_container(header, rest)))
            cases.append(Case(f"{label}: section {nm} removed, re-signed", _resign(header, rest)))
        cases += _deep_edits(label, header, sec_list)
        cases.append(Case(f"{label}: unchanged", data, must_fail=False))
        cases.append(Case(f"{label}: re-signed unchanged", _resign(header, sec_list),
                          must_fail=False))
    # cross-file swaps of every shared section (CRCs valid; digests as each file was encoded)
    for a in labels:
        for b in labels:
            if a == b:
                continue
            ha, sa = parsed[a]
            _, sb = parsed[b]
            for nm in sa:
                if nm in sb and sb[nm] != sa[nm]:
                    swapped = [(n, sb[nm] if n == nm else p) for n, p in sa.items()]
                    cases.append(Case(f"{a}: section {nm} taken from {b}",
                                      build_container(ha, swapped)))
    return cases


def special_cases(files: dict, sparse_bytes: int = 3 << 29) -> list:
    """Inputs that are not a file's bytes: kernel files that report size 0 and never end or
    never answer (``/proc/self/pagemap``, ``/dev/zero``, a FIFO nothing writes to), and a file
    declaring a first section of ``sparse_bytes`` (table CRC valid) extended sparsely to match,
    so that only reading the section finds its CRC wrong: a reader that keeps a section before
    checking it holds more than the harness's memory cap."""
    cases = [Case("/proc/self/pagemap (size 0, endless)", b"", path="/proc/self/pagemap"),
             Case("/dev/zero (a device)", b"", path="/dev/zero"),
             Case("a FIFO nothing writes to", b"", fifo=True)]
    for label, data in files.items():
        _, secs = _parse(data, label)
        first = next(iter(secs))
        hlen = struct.unpack_from("<I", data, 6)[0]
        t0 = 14 + hlen + 4                                 # the section table
        t1 = len(data) - sum(len(p) for p in secs.values()) - 4      # its CRC
        nl = struct.unpack_from("<H", data, t0)[0]
        b = bytearray(data)
        struct.pack_into("<Q", b, t0 + 2 + nl, sparse_bytes)
        struct.pack_into("<I", b, t1, zlib.crc32(bytes(b[t0:t1])) & 0xFFFFFFFF)
        total = len(data) - len(secs[first]) + sparse_bytes
        cases.append(Case(f"{label}: section {first} declared {sparse_bytes} bytes, file "
                          f"extended sparsely to {total}", bytes(b), size=total))
    return cases


def _deep_edits(label: str, header: dict, sections: list) -> list:
    """Edits inside section payloads, the file re-signed, so they reach the inner decoders."""
    out = []

    def with_section(name, payload, what):
        out.append(Case(f"{label}: {what} (re-signed)",
                        _resign(header, [(n, payload if n == name else p) for n, p in sections])))

    for name, p in sections:
        if name in [a["name"] for a in header.get("attrs", [])] and len(p) >= 8:
            # attribute stream: chunk size and escape limit
            for chunk, limit in ((2 ** 31, 16383), (0, 16383), (32768, 2 ** 30 - 1), (32768, 0)):
                with_section(name, struct.pack("<II", chunk, limit) + p[8:],
                             f"{name}: stream chunk {chunk}, escape limit {limit}")
            if len(p) >= 18:         # the Gaussian stream's chunk / escape counts
                for n_chunks, n_esc in ((2 ** 32 - 1, 0), (1, 2 ** 32 - 1)):
                    with_section(name, p[:8] + p[8:10] + struct.pack("<II", n_chunks, n_esc)
                                 + p[18:], f"{name}: {n_chunks} chunks, {n_esc} escapes declared")
                # first chunk: huge symbol count / range
                if len(p) >= 30:
                    for n, smin, smax in ((2 ** 32 - 1, -5, 5), (10, -2 ** 31, 2 ** 31 - 1),
                                          (10, 7, 3)):
                        with_section(name, p[:18] + struct.pack("<Iii", n, smin, smax) + p[30:],
                                     f"{name}: chunk 0 declares {n} symbols in [{smin}, {smax}]")
        if name.endswith("weights") or name == "em.mlp":
            _weight_edits(with_section, name, p)
        if name == "positions" and p[:2] == b"L1" and len(p) >= 39:
            # lattice positions: head fields (tag, n, depth, min k, voxel), then the octree words
            for depth in (0, 22, 255):
                with_section(name, p[:6] + bytes([depth]) + p[7:], f"positions: octree depth {depth}")
            with_section(name, p[:7] + struct.pack("<q", 2 ** 62) + p[15:],
                         "positions: lattice origin 2^62")
            for v in (float("nan"), 0.0, -1.0, 1e300):
                with_section(name, p[:31] + struct.pack("<d", v) + p[39:], f"positions: voxel {v}")
            for word, what in ((b"\xff\xff\xff\xff", "all ones"), (b"\0\0\0\0", "all zeros")):
                for n_words in (1, 64, 4096):
                    with_section(name, p[:39] + word * n_words,
                                 f"positions: octree payload of {n_words} words, {what}")
            with_section(name, p[:39], "positions: no octree payload")
        if name == "masks" and p[:1] == b"B":
            for n, n1 in ((2 ** 31, 2 ** 31), (2 ** 40, 0), (10, 20)):
                with_section(name, struct.pack("<cQQ", b"B", n, n1) + p[17:],
                             f"masks: Bernoulli header n={n}, ones={n1}")
    return out


def _weight_edits(with_section, name: str, p: bytes) -> None:
    if p[:2] != b"W1" or len(p) < 6:
        return
    (ilen,) = struct.unpack_from("<I", p, 2)
    try:
        index = json.loads(p[6:6 + ilen])
    except ValueError:
        return
    body = p[6 + ilen:]

    def rebuild(idx, data=body):
        raw = json.dumps(idx, separators=(",", ":")).encode()
        return b"W1" + struct.pack("<I", len(raw)) + raw + data

    if index:
        big = json.loads(json.dumps(index))
        big[0][2] = [2 ** 40]
        with_section(name, rebuild(big), f"{name}: tensor shape [2^40]")
        neg = json.loads(json.dumps(index))
        neg[0][2] = [-4, 2]
        with_section(name, rebuild(neg), f"{name}: negative tensor shape")
        bad = json.loads(json.dumps(index))
        bad[0][0] = 7
        with_section(name, rebuild(bad), f"{name}: tensor name not a string")
        if index[0][1] in ("float32", "float16"):
            width = 4 if index[0][1] == "float32" else 2
            nan = b"\xff\xff\xff\x7f" if width == 4 else b"\xff\x7f"
            with_section(name, p[:6 + ilen] + nan + body[width:], f"{name}: a NaN weight")
            inf = b"\x00\x00\x80\x7f" if width == 4 else b"\x00\x7c"
            with_section(name, p[:6 + ilen] + inf + body[width:], f"{name}: an Inf weight")
    with_section(name, rebuild("x"), f"{name}: weight index not a list")


# ------------------------------------------------------------------------------- running
WORKER = "baseline.testing.hostile"


def _worker() -> None:
    """Read case paths on stdin, answer one JSON line each on stdout (see DecodeHarness)."""
    import io
    import resource

    import torch

    from baseline import registry
    from baseline.cli import main as cli_main
    from baseline.codec.container import BitstreamError
    from baseline.modelfile import decode_model

    torch.set_num_threads(1)
    registry.ensure_loaded()
    cap = int(os.environ.get("PGS_HOSTILE_CAP_MB", "1024")) << 20
    with open("/proc/self/statm") as f:
        vsz = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
    resource.setrlimit(resource.RLIMIT_AS, (vsz + cap, vsz + cap))
    out = os.fdopen(os.dup(1), "w", buffering=1)      # the protocol; the commands' own
    devnull = os.open(os.devnull, os.O_WRONLY)        # stdout goes nowhere
    os.dup2(devnull, 1)
    sys.stdout = open(os.devnull, "w")
    err_fd = os.dup(2)
    print(json.dumps({"ready": True}), file=out)
    for line in sys.stdin:
        path = line.strip()
        res = {}
        with tempfile.TemporaryFile() as captured:
            os.dup2(captured.fileno(), 2)
            try:
                try:
                    decode_model(path)
                    res["api"] = "ok"
                except BitstreamError as e:
                    res["api"] = "refused"
                    res["msg"] = str(e)
                except MemoryError:
                    res["api"] = "memory cap hit"
                except Exception as e:  # noqa: BLE001 - a finding
                    res["api"] = f"{type(e).__name__}: {e}"
                for cmd in (["info", path], ["decode", path, "-o", path + ".out"]):
                    old = sys.stderr
                    sys.stderr = buf = io.StringIO()
                    try:
                        rc = cli_main(cmd)
                    except BaseException as e:  # noqa: BLE001 - a finding
                        rc = f"raised {type(e).__name__}: {e}"
                    finally:
                        sys.stderr = old
                    res[cmd[0]] = {"rc": rc, "stderr": buf.getvalue()}
            finally:
                sys.stderr.flush()
                os.dup2(err_fd, 2)
            captured.seek(0)
            res["fd2"] = captured.read().decode("utf-8", "replace")[-2000:]
        print(json.dumps(res), file=out)


class DecodeHarness:
    """A capped worker process; :meth:`run` returns a finding (str) or None per case."""

    def __init__(self, cap_mb: int = 1024, timeout: float = 120.0):
        self.cap_mb, self.timeout = cap_mb, timeout
        self.dir = tempfile.mkdtemp(prefix="pgs-hostile-")
        self.proc: Optional[subprocess.Popen] = None

    def _start(self) -> None:
        env = dict(os.environ, PGS_HOSTILE_CAP_MB=str(self.cap_mb), OMP_NUM_THREADS="1",
                   NUMBA_NUM_THREADS="1")
        self.proc = subprocess.Popen([sys.executable, "-m", WORKER, "--worker"], env=env,
                                     stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True, bufsize=1)
        line = self._read(300.0)
        if not line or not json.loads(line).get("ready"):
            raise RuntimeError("the decoder worker did not start")

    def _read(self, timeout: float) -> Optional[str]:
        r, _, _ = select.select([self.proc.stdout], [], [], timeout)
        return self.proc.stdout.readline() if r else None

    def close(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None

    def run(self, case: Case) -> Optional[str]:
        import shutil

        if not case.must_fail:
            # A file that must decode is judged in a fresh worker: the cap bounds what one
            # decode may take, and a long-lived worker's address space carries earlier cases'
            # (a valid HAC++ file's decode and render hit the cap only after ~2,000 cases).
            self.close()
        if self.proc is None or self.proc.poll() is not None:
            self._start()
        path = case.path or os.path.join(self.dir, "case.pgs")
        if case.path is None:
            if os.path.lexists(path):
                os.unlink(path)
            if case.fifo:
                os.mkfifo(path)
            else:
                with open(path, "wb") as f:
                    f.write(case.data)
                    if case.size is not None:       # a sparse file: no bytes on disk
                        f.truncate(case.size)
            shutil.rmtree(path + ".out", ignore_errors=True)
        t0 = time.perf_counter()
        self.proc.stdin.write(path + "\n")
        self.proc.stdin.flush()
        line = self._read(self.timeout)
        if line is None:
            self.close()
            return f"hang (no answer in {self.timeout:.0f} s)"
        if not line:
            self.close()
            return "the worker died"
        res = json.loads(line)
        dt = time.perf_counter() - t0
        return _judge(case, res, dt, path)


def _judge(case: Case, res: dict, dt: float, path: str) -> Optional[str]:
    api = res["api"]
    if "panicked" in res.get("fd2", "") or "Traceback" in res.get("fd2", ""):
        return f"output on stderr: {res['fd2'][-300:]!r}"
    if case.must_fail and api == "ok":
        return "decoded silently"
    if not case.must_fail and api != "ok":
        return f"a harmless case was refused: {api} {res.get('msg', '')[:200]}"
    if api not in ("ok", "refused"):
        return api
    for cmd in ("info", "decode"):
        r = res[cmd]
        if case.must_fail and cmd == "decode":
            if r["rc"] != 2:
                return f"pgs decode: exit {r['rc']}"
            if os.path.exists(path + ".out"):
                return "pgs decode left an output folder behind"
        lines = [x for x in r["stderr"].splitlines() if x.strip()]
        if r["rc"] not in (0, 2) or "Traceback" in r["stderr"] or len(lines) > 1 \
                or "internal error" in r["stderr"]:
            return f"pgs {cmd}: exit {r['rc']}, stderr {r['stderr'][-300:]!r}"
    return None


def run_cases(cases: list, cap_mb: int = 1024, timeout: float = 120.0, echo=None) -> dict:
    """Run ``cases``; ``{"cases", "refused", "decoded", "findings": [(name, finding)]}``."""
    h = DecodeHarness(cap_mb, timeout)
    stats = {"cases": 0, "refused": 0, "decoded": 0, "findings": []}
    try:
        for c in cases:
            f = h.run(c)
            stats["cases"] += 1
            if f is not None:
                stats["findings"].append((c.name, f))
                if echo:
                    echo(f"FINDING {c.name}: {f}")
            elif c.must_fail:
                stats["refused"] += 1
            else:
                stats["decoded"] += 1
    finally:
        h.close()
    return stats


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m baseline.testing.hostile")
    ap.add_argument("files", nargs="*")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--random", type=int, default=200, help="random flips/overwrites per file")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--cap-mb", type=int, default=1024)
    args = ap.parse_args(argv)
    if args.worker:
        _worker()
        return 0
    files = {Path(f).parent.name + "/" + Path(f).name: Path(f).read_bytes() for f in args.files}
    cases = crafted_cases(files, args.random, args.seed) + special_cases(files)
    t0 = time.perf_counter()
    st = run_cases(cases, args.cap_mb, echo=print)
    print(f"{st['cases']} cases in {time.perf_counter() - t0:.0f} s: {st['refused']} refused "
          f"cleanly, {st['decoded']} harmless decoded, {len(st['findings'])} findings")
    return 1 if st["findings"] else 0


if __name__ == "__main__":
    sys.exit(main())
