"""Deterministic packing of network weights (state dicts) into bitstream sections.

``pack_state_dict(sd, precision="float32" | "float16")`` stores every floating tensor at the
chosen precision (float64 tensors too, unless listed in ``keep``), integer and bool tensors
as they are, in the state dict's order, little-endian::

    b"W1" | uint32 index length | JSON index [[name, dtype, shape], ...] | raw data

The encoder must code with exactly the weights the decoder will load: call
:func:`round_module_` (or :func:`round_state_dict`) with the same precision *before* anything
that depends on the weights is coded (the entropy model's probabilities in particular).
"""
from __future__ import annotations

import contextlib
import contextvars
import json
import struct
from collections import OrderedDict
from typing import Dict, Iterable, Mapping, Optional

import numpy as np
import torch
import torch.nn as nn

from baseline.codec.container import BitstreamError

PRECISIONS = {"float32": torch.float32, "float16": torch.float16}
_DTYPES = {  # stored name -> (torch dtype, numpy little-endian dtype)
    "float32": (torch.float32, "<f4"), "float16": (torch.float16, "<f2"), "float64": (torch.float64, "<f8"),
    "int64": (torch.int64, "<i8"), "int32": (torch.int32, "<i4"), "int16": (torch.int16, "<i2"),
    "int8": (torch.int8, "i1"), "uint8": (torch.uint8, "u1"), "bool": (torch.bool, "u1"),
}
_TAG = b"W1"
_HDR = struct.Struct("<2sI")


def _stored_name(t: torch.Tensor, precision: str, keep: bool) -> str:
    if t.is_floating_point():
        if keep:
            return "float64" if t.dtype == torch.float64 else "float32"
        return precision
    for name, (dt, _) in _DTYPES.items():
        if dt == t.dtype:
            return name
    raise TypeError(f"cannot store tensors of dtype {t.dtype}")


def _check_precision(precision: str) -> str:
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be one of {sorted(PRECISIONS)}, got {precision!r}")
    return precision


def pack_state_dict(state_dict: Mapping[str, torch.Tensor], precision: str = "float32",
                    exclude: Iterable[str] = (), keep: Iterable[str] = ()) -> bytes:
    """Bytes of ``state_dict`` at ``precision`` (deterministic for equal inputs).

    ``exclude``: names (or name prefixes ending in '.') left out. ``keep``: names/prefixes whose
    floating tensors keep float32/float64 (e.g. bounds that must stay exact).
    """
    _check_precision(precision)
    exclude, keep = tuple(exclude), tuple(keep)

    def match(name, pats):
        return any(name == p or (p.endswith(".") and name.startswith(p)) for p in pats)

    index, chunks = [], []
    for name, t in state_dict.items():
        if match(name, exclude):
            continue
        t = t.detach().cpu()
        sname = _stored_name(t, precision, match(name, keep))
        tdt, npdt = _DTYPES[sname]
        arr = t.to(tdt).contiguous().numpy() if sname != "bool" else t.contiguous().numpy().astype(np.uint8)
        chunks.append(np.ascontiguousarray(arr).astype(npdt, copy=False).tobytes())
        index.append([name, sname, list(t.shape)])
    idx = json.dumps(index, separators=(",", ":")).encode("utf-8")
    return _HDR.pack(_TAG, len(idx)) + idx + b"".join(chunks)


# the precision the file's header declares, while a file is decoded (see expect_precision)
_DECLARED: "contextvars.ContextVar[Optional[str]]" = contextvars.ContextVar("pgs_weight_dtype",
                                                                           default=None)


@contextlib.contextmanager
def expect_precision(precision: Optional[str]):
    """Within the block, :func:`unpack_state_dict` checks every blob against the precision a
    file's header declares: a float32 file stores no float16 tensor, and a float16 file's blob
    with floating tensors stores at least one as float16 (only ``keep`` tensors such as grid
    bounds stay float32). The weight blobs describe themselves, so without this check a header
    contradicting its sections would decode unnoticed."""
    token = _DECLARED.set(precision)
    try:
        yield
    finally:
        _DECLARED.reset(token)


def declare_precision(precision: Optional[str]) -> None:
    """Set the declared precision inside an :func:`expect_precision` block (once the header
    has been read)."""
    _DECLARED.set(precision)


def unpack_state_dict(blob, as_float32: bool = True, what: str = "weights",
                      check_finite: bool = True) -> "OrderedDict[str, torch.Tensor]":
    """Inverse of :func:`pack_state_dict`. float16 tensors come back as float32 by default.
    Every floating tensor must be finite (``check_finite``): a decoded network with NaN or Inf
    weights is refused, naming the tensor, instead of rendering nothing. Inside
    :func:`expect_precision` the stored types must agree with the declared precision."""
    blob = bytes(blob)
    if len(blob) < _HDR.size:
        raise BitstreamError(f"{what}: truncated weight header")
    tag, ilen = _HDR.unpack_from(blob)
    if tag != _TAG:
        raise BitstreamError(f"{what}: not a weight blob")
    if ilen > len(blob) - _HDR.size:
        raise BitstreamError(f"{what}: weight index length {ilen} exceeds the blob")
    try:
        index = json.loads(blob[_HDR.size:_HDR.size + ilen].decode("utf-8"))
    except (UnicodeDecodeError, ValueError) as e:
        raise BitstreamError(f"{what}: damaged weight index ({e})") from None
    off = _HDR.size + ilen
    out: "OrderedDict[str, torch.Tensor]" = OrderedDict()
    float_types = set()
    if not isinstance(index, list):
        raise BitstreamError(f"{what}: damaged weight index")
    for entry in index:
        try:
            name, sname, shape = entry
            if not isinstance(name, str) or not isinstance(shape, list) or len(shape) > 8 \
                    or not all(isinstance(x, int) and not isinstance(x, bool) for x in shape):
                raise TypeError
            tdt, npdt = _DTYPES[sname]
        except (TypeError, ValueError, KeyError):
            raise BitstreamError(f"{what}: damaged weight index entry {entry!r:.120}") from None
        if name in out:
            raise BitstreamError(f"{what}: tensor '{name}' is listed twice")
        if any(s < 0 for s in shape):
            raise BitstreamError(f"{what}: negative shape for '{name}'")
        count = int(np.prod(shape, dtype=np.float64)) if shape else 1
        nbytes = count * np.dtype(npdt).itemsize
        if nbytes > len(blob) - off:
            raise BitstreamError(f"{what}: tensor '{name}' needs {nbytes} bytes, {len(blob) - off} left")
        arr = np.frombuffer(blob, dtype=npdt, count=count, offset=off).reshape(shape)
        off += nbytes
        if sname.startswith("float"):
            float_types.add(sname)
        if sname == "bool":
            t = torch.from_numpy(arr.astype(bool))
        else:
            t = torch.from_numpy(arr.astype(arr.dtype.newbyteorder("="), copy=True))
        if as_float32 and sname == "float16":
            t = t.float()
        if check_finite and t.is_floating_point() and not torch.isfinite(t).all():
            raise BitstreamError(f"{what}: tensor '{name}' holds NaN or Inf values")
        out[name] = t
    if off != len(blob):
        raise BitstreamError(f"{what}: {len(blob) - off} unexpected trailing bytes")
    declared = _DECLARED.get()
    if declared == "float32" and "float16" in float_types:
        raise BitstreamError(f"{what}: stores float16 tensors, the header declares float32 "
                             f"weights (weight_dtype)")
    if declared == "float16" and float_types and "float16" not in float_types:
        raise BitstreamError(f"{what}: stores no float16 tensor, the header declares float16 "
                             f"weights (weight_dtype)")
    return out


def round_state_dict(state_dict: Mapping[str, torch.Tensor], precision: str = "float32",
                     keep: Iterable[str] = ()) -> Dict[str, torch.Tensor]:
    """Copy of ``state_dict`` whose floating tensors went through the stored precision."""
    _check_precision(precision)
    keep = tuple(keep)
    out = OrderedDict()
    for name, t in state_dict.items():
        kept = any(name == p or (p.endswith(".") and name.startswith(p)) for p in keep)
        if t.is_floating_point() and not kept:
            out[name] = t.detach().to(PRECISIONS[precision]).to(t.dtype)
        else:
            out[name] = t.detach().clone()
    return out


@torch.no_grad()
def round_module_(module: nn.Module, precision: str = "float32", keep: Iterable[str] = ()) -> nn.Module:
    """Round ``module``'s floating parameters and buffers in place to the stored precision.

    After this the live module equals what :func:`unpack_state_dict` will give the decoder.
    """
    _check_precision(precision)
    dt = PRECISIONS[precision]
    keep = tuple(keep)
    for name, t in list(module.named_parameters()) + list(module.named_buffers()):
        if any(name == p or (p.endswith(".") and name.startswith(p)) for p in keep):
            continue
        if t is not None and t.is_floating_point():
            t.copy_(t.to(dt).to(t.dtype))
    return module
