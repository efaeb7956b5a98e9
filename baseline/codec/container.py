"""The ``.pgs`` container: one self-contained file of named, checksummed sections.

Layout (all integers little-endian)::

    offset  size  field
    0       4     magic  b"PGS\\x00"
    4       2     format version (uint16), currently 1
    6       4     header length H (uint32)
    10      4     section count S (uint32)
    14      H     header: UTF-8 JSON object (config, counts, bounds, dims, ...)
    14+H    4     CRC32 of the header bytes
    ...           section table, S entries: name length (uint16), name (UTF-8),
                  payload length (uint64), payload CRC32 (uint32)
    ...     4     CRC32 of the section table
    ...           payloads, in table order, back to back; the file ends exactly after the last

Because the table comes before the payloads, a reader knows the expected file size before it
touches a payload: a file cut anywhere (also exactly at a section boundary) is reported as
truncated *inside the section it cuts*, and every length is checked against the bytes present
before anything is allocated. Each payload has its own CRC32, so a flipped byte is reported with
the section's name. Every problem raises :class:`BitstreamError` (a ``ValueError``) whose
message names the file part; nothing else escapes the parser.

Writing is atomic (:mod:`baseline.fileio`: a temporary file in the destination folder, fsync,
then ``os.replace``).
"""
from __future__ import annotations

import json
import os
import struct
import zlib
from collections import OrderedDict
from pathlib import Path
from typing import Iterable, Tuple, Union

from baseline.fileio import write_bytes_atomic

MAGIC = b"PGS\x00"
FORMAT_VERSION = 1
SUPPORTED_VERSIONS = (1,)

_PRE = struct.Struct("<4sHII")      # magic, version, header length, section count
_CRC = struct.Struct("<I")
_NAME_LEN = struct.Struct("<H")
_ENTRY = struct.Struct("<QI")      # payload length, payload crc
MAX_HEADER_BYTES = 64 << 20
MAX_SECTIONS = 1 << 16


class BitstreamError(ValueError):
    """A ``.pgs`` file (or one of its sections) is damaged, truncated or not understood."""


def crc32(data) -> int:
    return zlib.crc32(data) & 0xFFFFFFFF


def build_container(header: dict, sections: Iterable[Tuple[str, bytes]]) -> bytes:
    """The container bytes for ``header`` (JSON-serialisable dict) and ``(name, payload)`` pairs."""
    if not isinstance(header, dict):
        raise TypeError("header must be a dict")
    hdr = json.dumps(header, sort_keys=True, separators=(",", ":"), allow_nan=False).encode("utf-8")
    if len(hdr) > MAX_HEADER_BYTES:
        raise ValueError(f"header too large ({len(hdr)} bytes)")
    sections = [(str(n), bytes(p)) for n, p in sections]
    names = [n for n, _ in sections]
    if len(set(names)) != len(names):
        raise ValueError(f"duplicate section names in {names}")
    if len(sections) > MAX_SECTIONS:
        raise ValueError("too many sections")
    table = []
    for name, payload in sections:
        nb = name.encode("utf-8")
        if not nb or len(nb) > 0xFFFF:
            raise ValueError(f"invalid section name {name!r}")
        table.append(_NAME_LEN.pack(len(nb)) + nb + _ENTRY.pack(len(payload), crc32(payload)))
    table_b = b"".join(table)
    out = [_PRE.pack(MAGIC, FORMAT_VERSION, len(hdr), len(sections)), hdr, _CRC.pack(crc32(hdr)),
           table_b, _CRC.pack(crc32(table_b))]
    out += [p for _, p in sections]
    return b"".join(out)


def write_container(path, header: dict, sections: Iterable[Tuple[str, bytes]]) -> int:
    """Write a container atomically (temp file + fsync + rename). Returns the byte count."""
    return write_bytes_atomic(path, build_container(header, sections))


DEFAULT_MAX_FILE_MB = 4096


def max_file_bytes() -> int:
    """The largest ``.pgs`` file a reader accepts: ``PGS_MAX_FILE_MB`` (MiB, a finite number
    above 0), else 4 GiB (truck files are 4-6 MB). Checked against the file's size before a
    byte is read, so a device or an endless stream is never read into memory."""
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


def read_file_bytes(path: Union[str, os.PathLike], what: str = "a .pgs file") -> bytes:
    """The bytes of a regular file no larger than :func:`max_file_bytes`; a missing file, a
    folder, a device / pipe / socket or a file over the cap is a :class:`BitstreamError` naming
    it, raised before anything is read."""
    where = str(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise BitstreamError(f"{where}: no such file") from None
    except OSError as e:
        raise BitstreamError(f"{where}: cannot read it ({e.strerror or e})") from None
    import stat as _stat

    if _stat.S_ISDIR(st.st_mode):
        raise BitstreamError(f"{where}: is a directory, not {what}")
    if not _stat.S_ISREG(st.st_mode):
        raise BitstreamError(f"{where}: not a regular file (a device, pipe or socket), not {what}")
    cap = max_file_bytes()
    if st.st_size > cap:
        raise BitstreamError(f"{where}: {st.st_size} bytes, above the {cap}-byte cap for {what} "
                             f"(PGS_MAX_FILE_MB raises it)")
    try:
        with open(path, "rb") as f:
            # read(n) allocates n bytes up front: ask for the size stat gave (plus one byte to
            # see a file that grew), then at most the cap in bounded chunks
            data = f.read(st.st_size + 1)
            while len(data) <= cap:
                more = f.read(min(1 << 24, cap + 1 - len(data)))
                if not more:
                    break
                data += more
    except OSError as e:
        raise BitstreamError(f"{where}: cannot read it ({e.strerror or e})") from None
    if len(data) > cap:                  # grew while being read
        raise BitstreamError(f"{where}: more than the {cap}-byte cap for {what}")
    return data


def read_container(src: Union[str, os.PathLike, bytes, bytearray, memoryview]):
    """Parse a container from a path or bytes -> ``(header dict, OrderedDict name -> bytes)``.

    Raises :class:`BitstreamError` naming the problem (and the section) for any damage.
    """
    if isinstance(src, (bytes, bytearray, memoryview)):
        data = bytes(src)
        where = "<bytes>"
    else:
        where = str(src)
        data = read_file_bytes(src)
    return _parse(data, where)


def _parse(data: bytes, where: str):
    size = len(data)

    def err(msg):
        return BitstreamError(f"{where}: {msg}")

    if size == 0:
        raise err("empty file (zero length), not a .pgs file")
    if data[:4] != MAGIC:
        if size < 4 and MAGIC.startswith(data):
            raise err(f"truncated in the preamble ({size} bytes)")
        raise err("wrong magic: not a .pgs file")
    if size < _PRE.size:
        raise err(f"truncated in the preamble ({size} of {_PRE.size} bytes)")
    _, version, hlen, nsec = _PRE.unpack_from(data, 0)
    if version not in SUPPORTED_VERSIONS:
        raise err(f"unsupported .pgs format version {version} (this reader supports "
                  f"{', '.join(map(str, SUPPORTED_VERSIONS))})")
    off = _PRE.size
    if hlen > MAX_HEADER_BYTES:
        raise err(f"absurd header length {hlen} (damaged preamble)")
    if hlen + _CRC.size > size - off:
        raise err(f"truncated in the header (needs {hlen + _CRC.size} bytes, {size - off} left)")
    hdr = data[off:off + hlen]
    off += hlen
    (hcrc,) = _CRC.unpack_from(data, off)
    off += _CRC.size
    if crc32(hdr) != hcrc:
        raise err("CRC mismatch in the header")
    try:
        header = json.loads(hdr.decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise err(f"header is not valid JSON ({e})") from None
    if not isinstance(header, dict):
        raise err("header is not a JSON object")
    min_entry = _NAME_LEN.size + 1 + _ENTRY.size
    if nsec > MAX_SECTIONS:
        raise err(f"absurd section count {nsec} (damaged preamble)")
    if nsec * min_entry + _CRC.size > size - off:
        raise err(f"truncated in the section table ({nsec} sections need at least "
                  f"{nsec * min_entry + _CRC.size} bytes, {size - off} left)")
    table_start = off
    entries = []
    for i in range(nsec):
        if off + _NAME_LEN.size > size:
            raise err(f"truncated in the section table (entry {i})")
        (nl,) = _NAME_LEN.unpack_from(data, off)
        off += _NAME_LEN.size
        if nl == 0 or off + nl + _ENTRY.size > size:
            raise err(f"truncated or damaged section table (entry {i})")
        raw_name = data[off:off + nl]
        off += nl
        plen, pcrc = _ENTRY.unpack_from(data, off)
        off += _ENTRY.size
        entries.append((raw_name, plen, pcrc))
    if off + _CRC.size > size:
        raise err("truncated in the section table")
    (tcrc,) = _CRC.unpack_from(data, off)
    if crc32(data[table_start:off]) != tcrc:
        raise err("CRC mismatch in the section table")
    off += _CRC.size
    names = []
    for raw_name, _, _ in entries:
        try:
            names.append(raw_name.decode("utf-8"))
        except UnicodeDecodeError:
            raise err("section table holds a non-UTF-8 section name") from None
    if len(set(names)) != len(names):
        raise err("section table lists a section twice")
    sections = OrderedDict()
    for name, (_, plen, pcrc) in zip(names, entries):
        remaining = size - off
        if plen > remaining:
            raise err(f"truncated in section '{name}' (needs {plen} bytes, {remaining} left)")
        payload = data[off:off + plen]
        off += plen
        if crc32(payload) != pcrc:
            raise err(f"CRC mismatch in section '{name}'")
        sections[name] = payload
    if off != size:
        raise err(f"{size - off} unexpected bytes after the last section")
    return header, sections


def container_summary(src) -> list:
    """``[(name, payload bytes)]`` including the framing as ``(_framing, bytes)``; for reports."""
    data = src if isinstance(src, (bytes, bytearray)) else read_file_bytes(src)
    header, sections = _parse(bytes(data), "<summary>" if isinstance(src, (bytes, bytearray))
                              else str(src))
    payload = sum(len(p) for p in sections.values())
    return [(n, len(p)) for n, p in sections.items()] + [("_framing", len(data) - payload)]
