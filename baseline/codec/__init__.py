"""Bitstream: the ``.pgs`` container, its format constants and header checks, range coding,
positions, masks, weight packing."""
from baseline.codec.container import BitstreamError, read_container, write_container

__all__ = ["BitstreamError", "read_container", "write_container"]
