"""The contracts between the baseline pipeline and its pluggable components (DESIGN.md).

A *feature provider* supplies the per-anchor features the decoder MLPs read, and declares the
per-anchor attributes it wants entropy coded (:class:`CodedAttribute`). An *entropy model*
builds its output head from that list, so swapping the provider swaps the head with no special
cases. A *refiner* (optional) turns per-anchor extras and the view into additive corrections of
the decoded Gaussians.

Providers and refiners are built as ``cls(model, cfg)``. One whose construction depends on more
than the config (e.g. a hash grid sized from the anchor count at the start of training) defines
``codec_state() -> dict`` (JSON-able); the encoder keeps it in the file header and the decoder
builds the module as ``cls(model, cfg, codec_state=state)``, so a decoded model never re-derives
it from the decoded (grown and pruned) anchors.

A provider whose features depend on the anchor positions only (Predict-GS's SFP) may also define
``build_cache(xyz)`` / ``clear_cache()``: decoded models compute the features once
(:func:`feature_cache` finds such a provider).

A refiner may also declare its heads for baking (``bake_heads(values) -> list[BakeHead]``, see
:mod:`baseline.scaffold.baked`): a decoded model then computes the view-independent part of the
decoder's and the refiner's first layers once (on CUDA, where that was measured faster). A
refiner that does not declare them still works; its decoded models render unbaked.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class CodedAttribute:
    """One per-anchor attribute that the entropy model codes.

    Attributes:
        name: attribute name, also the bitstream section name (``feat``, ``scaling``, ...).
        dims: number of values per anchor.
        q0: base quantization step.
        masked: True when each value is gated by a Gaussian mask (offsets: K x 3 values, one
            mask per Gaussian, so a mask covers ``dims // n_masks`` consecutive values). Masked
            values whose Gaussian is off are neither coded nor counted.
    """

    name: str
    dims: int
    q0: float
    masked: bool = False


def feature_cache(model):
    """The model's feature provider when it implements the optional decoded-model cache
    (``build_cache(xyz)`` / ``clear_cache()``), else None."""
    prov = getattr(model, "provider", None)
    return prov if hasattr(prov, "build_cache") and hasattr(prov, "clear_cache") else None


# The baseline's coded attributes for K = 10 offsets and a 50-dim feature (SPEC.md section 3).
def scaffold_coded_attributes(feat_dim: int = 50, n_offsets: int = 10) -> tuple[CodedAttribute, ...]:
    return (
        CodedAttribute("feat", feat_dim, 1.0),
        CodedAttribute("scaling", 6, 0.001),
        CodedAttribute("offsets", 3 * n_offsets, 0.2, masked=True),
    )
