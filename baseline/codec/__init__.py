"""Bitstream: the ``.pgs`` container, range-coding primitives, weight packing, fuzzing, bench."""
from baseline.codec.container import BitstreamError, read_container, write_container

__all__ = ["BitstreamError", "read_container", "write_container"]
