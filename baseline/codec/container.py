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
touches a payload (and a file is read section by section, each checked before the next is
read): a file cut anywhere (also exactly at a section boundary) is reported as
truncated *inside the section it cuts*, and every length is checked against the bytes present
before anything is allocated. Each payload has its own CRC32, so a flipped byte is reported with
the section's name. Every problem raises :class:`BitstreamError` (a ``ValueError``) whose
message names the file part; nothing else escapes the parser.

Writing is atomic (:mod:`baseline.fileio`: a temporary file in the destination folder, fsync,
then ``os.replace``).
"""
from __future__ import annotations

import io
import json
import os
import struct
import zlib
from collections import OrderedDict
from typing import Iterable, Tuple, Union

from baseline.fileio import (CHUNK, DEFAULT_MAX_FILE_MB, UnreadableFile,  # noqa: F401
                             max_file_bytes, open_checked, read_bytes_bounded, write_bytes_atomic)

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


def read_file_bytes(path: Union[str, os.PathLike], what: str = "a .pgs file") -> bytes:
    """The bytes of a regular file no larger than :func:`max_file_bytes`; a missing file, a
    folder, a device / pipe / socket / ``/proc`` file or a file over the cap is a
    :class:`BitstreamError` naming it, raised before anything is read
    (:func:`baseline.fileio.read_bytes_bounded`)."""
    try:
        return read_bytes_bounded(path, what)
    except UnreadableFile as e:
        raise BitstreamError(str(e)) from None


def read_container(src: Union[str, os.PathLike, bytes, bytearray, memoryview]):
    """Parse a container from a path or bytes -> ``(header dict, OrderedDict name -> bytes)``.

    Raises :class:`BitstreamError` naming the problem (and the section) for any damage.
    """
    header, sections, _ = read_container_sized(src)
    return header, sections


def read_container_sized(src) -> tuple:
    """:func:`read_container` plus the container's byte count.

    A file is streamed: the preamble, header and section table are read and checked first (each
    length against the file's size), then each section is read and its CRC checked before the
    next one is read; the first bad section stops the read. A section above
    :data:`STREAM_CHECK_BYTES` has its CRC checked on bounded chunks before its bytes are
    kept, so a damaged or hostile file never makes the reader hold more than that. A file
    whose size the OS does not report is read whole, up to ``PGS_MAX_FILE_MB``."""
    if isinstance(src, (bytes, bytearray, memoryview)):
        data = bytes(src)
        return (*_parse_stream(io.BytesIO(data), len(data), "<bytes>"), len(data))
    where = str(src)
    try:
        f, size, cap = open_checked(src, "a .pgs file")
    except UnreadableFile as e:
        raise BitstreamError(str(e)) from None
    with f:
        if size == 0:                   # not reported (or empty): bounded by the cap alone
            f.close()
            data = read_file_bytes(src)
            return (*_parse_stream(io.BytesIO(data), len(data), where), len(data))
        try:
            return (*_parse_stream(f, size, where), size)
        except OSError as e:
            raise BitstreamError(f"{where}: cannot read it ({e.strerror or e})") from None


STREAM_CHECK_BYTES = 64 << 20


def _parse(data: bytes, where: str):
    """Parse container bytes -> ``(header, sections)``."""
    return _parse_stream(io.BytesIO(data), len(data), where)


def _parse_stream(f, size: int, where: str):
    """Parse the container of ``size`` bytes readable from ``f`` (at its start)."""
    def err(msg):
        return BitstreamError(f"{where}: {msg}")

    def take(n: int, part: str) -> bytes:
        b = f.read(n)
        if len(b) != n:                 # the file shrank while being read
            raise err(f"truncated in {part} (needs {n} bytes, {len(b)} read)")
        return b

    if size == 0:
        raise err("empty file (zero length), not a .pgs file")
    pre = f.read(_PRE.size)
    if pre[:4] != MAGIC:
        if size < 4 and MAGIC.startswith(pre):
            raise err(f"truncated in the preamble ({size} bytes)")
        raise err("wrong magic: not a .pgs file")
    if size < _PRE.size:
        raise err(f"truncated in the preamble ({size} of {_PRE.size} bytes)")
    _, version, hlen, nsec = _PRE.unpack_from(pre, 0)
    if version not in SUPPORTED_VERSIONS:
        raise err(f"unsupported .pgs format version {version} (this reader supports "
                  f"{', '.join(map(str, SUPPORTED_VERSIONS))})")
    off = _PRE.size
    if hlen > MAX_HEADER_BYTES:
        raise err(f"absurd header length {hlen} (damaged preamble)")
    if hlen + _CRC.size > size - off:
        raise err(f"truncated in the header (needs {hlen + _CRC.size} bytes, {size - off} left)")
    hdr = take(hlen, "the header")
    (hcrc,) = _CRC.unpack(take(_CRC.size, "the header"))
    off += hlen + _CRC.size
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
    table = bytearray()                 # entries are read one by one, each length checked
    entries = []
    for i in range(nsec):
        if off + _NAME_LEN.size > size:
            raise err(f"truncated in the section table (entry {i})")
        head = take(_NAME_LEN.size, "the section table")
        (nl,) = _NAME_LEN.unpack(head)
        off += _NAME_LEN.size
        if nl == 0 or off + nl + _ENTRY.size > size:
            raise err(f"truncated or damaged section table (entry {i})")
        body = take(nl + _ENTRY.size, "the section table")
        off += nl + _ENTRY.size
        table += head + body
        plen, pcrc = _ENTRY.unpack_from(body, nl)
        entries.append((body[:nl], plen, pcrc))
    if off + _CRC.size > size:
        raise err("truncated in the section table")
    (tcrc,) = _CRC.unpack(take(_CRC.size, "the section table"))
    if crc32(bytes(table)) != tcrc:
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
        part = f"section '{name}'"
        if plen > STREAM_CHECK_BYTES:   # check the CRC on chunks before keeping anything
            start, c, left = f.tell(), 0, plen
            while left:
                chunk = take(min(CHUNK, left), part)
                c = zlib.crc32(chunk, c)
                left -= len(chunk)
            if (c & 0xFFFFFFFF) != pcrc:
                raise err(f"CRC mismatch in section '{name}'")
            f.seek(start)
        payload = take(plen, part)
        off += plen
        if crc32(payload) != pcrc:
            raise err(f"CRC mismatch in section '{name}'")
        sections[name] = payload
    if off != size:
        raise err(f"{size - off} unexpected bytes after the last section")
    return header, sections


def container_summary(src) -> list:
    """``[(name, payload bytes)]`` including the framing as ``(_framing, bytes)``; for reports."""
    _, sections, size = read_container_sized(src)
    payload = sum(len(p) for p in sections.values())
    return [(n, len(p)) for n, p in sections.items()] + [("_framing", size - payload)]
