"""The typed boundary between the baseline pipeline and its pluggable components.

Every component kind a plugin can register (:mod:`baseline.registry`) has its contract here:

* :class:`FeatureProvider` (registry kind ``feature_provider``): the per-anchor features the
  decoder MLPs read, and the per-anchor attributes it wants entropy coded
  (:class:`CodedAttribute`). An entropy model builds its output head from that list, so swapping
  the provider swaps the head with no special cases.
* :class:`Refiner` (``refiner``, optional): per-anchor extras and the view -> additive
  corrections of the decoded Gaussians' pre-activations.
* :class:`EntropyModel` (``entropy_model``): the rate model and coder of the coded attributes.
* :class:`TrainingHook` (``hooks``): code the trainer runs around each step.
* :class:`MaskTraining` (``mask_training``): how the Gaussian masks are trained.

Providers and refiners are built as ``cls(model, cfg)``; one whose construction depends on more
than the config (a hash grid sized from the anchor count at the start of training) returns
that state from :meth:`FeatureProvider.codec_state`: the encoder keeps it in the file header and
the decoder builds the module as ``cls(model, cfg, codec_state=state)``, so a decoded model never
re-derives it from the decoded (grown and pruned) anchors. The optional capabilities are methods
with no-op defaults, so the pipeline calls them without asking whether they exist.

Class attributes every component may declare: ``SECTION_LABELS`` (bitstream section suffix ->
what it holds, ``""`` = the component itself; ``pgs info`` and the reports name sections so)
and ``TRAINING_SEMANTICS`` (a version bumped when the component trains differently from the
same config: only the runs that use it get new config hashes).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar, Protocol

import torch.nn as nn
from torch import Tensor

from baseline.codec.fields import header_error


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
        noise_phase: False: training's noise phase (quantization noise before the rate starts)
            leaves it exact; the rate's adaptive quantization reaches it as any other. Training
            only, not stored in files.
    """

    name: str
    dims: int
    q0: float
    masked: bool = False
    noise_phase: bool = True


# The baseline's coded attributes for K = 10 offsets and a 50-dim feature (docs/method.md).
def scaffold_coded_attributes(feat_dim: int = 50, n_offsets: int = 10) -> tuple[CodedAttribute, ...]:
    return (
        CodedAttribute("feat", feat_dim, 1.0),
        CodedAttribute("scaling", 6, 0.001),
        CodedAttribute("offsets", 3 * n_offsets, 0.2, masked=True),
    )


@dataclass
class BakeHead:
    """One two-layer head, as a model or a refiner declares it for baking
    (:class:`baseline.scaffold.baked.BakedDecoder`).

    Attributes:
        x: [N, D] its view-independent input for every anchor (feature, residual, ...).
        mlp: ``Sequential(Linear(D + 3 (+1), H), ReLU, Linear(H, K * C))``.
        uses_distance: whether the first layer reads the distance after the view direction.
        targets: attribute -> (first, stop) channels of the head's C channels per Gaussian that
            add into that attribute (e.g. a head giving opacity (0, 1) and color (1, 4)).
    """

    x: Tensor
    mlp: nn.Sequential
    uses_distance: bool
    targets: dict


ParamGroup = dict[str, Any]     # an Adam group: name, params, lr_init, lr_final


class _Component:
    """What every registered component class may declare (see the module docstring)."""

    SECTION_LABELS: ClassVar[dict[str, str]] = {}
    TRAINING_SEMANTICS: ClassVar[int] = 1


class _Module(_Component, nn.Module):
    """What providers and refiners share: their Adam groups and the state a file keeps of them."""

    def param_groups(self, cfg) -> list[ParamGroup]:
        """The Adam groups of the component's parameters."""
        raise NotImplementedError

    def codec_state(self) -> dict | None:
        """JSON-able construction state the decoder needs besides the config; None: none."""
        return None

    @classmethod
    def check_codec_state(cls, state: Any, key: str) -> int:
        """Check a file header's ``codec_state`` of this class before anything is built (raise
        :class:`baseline.codec.container.BitstreamError` naming ``key``); returns the hash-grid
        entries it makes the decoder allocate. Default: a class that keeps no state takes none."""
        raise header_error(key, f"the {cls.__name__} component keeps no state in a file")


class FeatureProvider(_Module):
    """Per-anchor features for the decoder MLPs (baseline: ``explicit``, a learned table).

    A provider may add per-anchor tensors to the model (``model.add_per_anchor``) and must
    implement the four methods that raise here. ``feature_dim`` is the width of the decoder
    MLPs' feature input.
    """

    feature_dim: int
    # whether decoded models may precompute the features once (build_cache / clear_cache):
    # features that depend on the anchor positions only
    caches_features: ClassVar[bool] = False

    def coded_attributes(self) -> tuple[CodedAttribute, ...]:
        """Everything the entropy model codes, the model's own scaling and offsets included."""
        raise NotImplementedError

    def coded_values(self, idx: Tensor) -> dict[str, Tensor]:
        """The provider's own coded values of anchors ``idx`` [M]: {name: [M, dims]}."""
        raise NotImplementedError

    def decoder_features(self, idx: Tensor, values: dict[str, Tensor], xyz: Tensor) -> Tensor:
        """Anchors ``idx`` [M] with coded values {name: [M, d]} at ``xyz`` [M, 3] ->
        [M, feature_dim]."""
        raise NotImplementedError

    def build_cache(self, xyz: Tensor) -> None:
        """Precompute the features of all anchors at ``xyz`` [N, 3] (``caches_features``)."""

    def clear_cache(self) -> None:
        """Drop what :meth:`build_cache` computed."""

    def rate_bits(self) -> Tensor | None:
        """Bits of the provider's own shared state added to the rate loss (a hash grid's);
        None: nothing."""
        return None

    def context_grid(self) -> Any:
        """A positional feature grid of the provider's (a ``BinaryHashGrid`` queried at the
        anchor positions) that a hash-grid entropy model may read as its context instead of
        a grid of its own (``entropy.context = "provider"``); None: it has none."""
        return None


class Refiner(_Module):
    """Additive corrections of the decoded Gaussians (optional; baseline: ``none``).

    ``forward(idx [M], values {name: [M, d]}, view_dir [M, 3], dist [M, 1])`` returns the
    corrections ``{"opacity": [M, K], "cov": [M, K, 7], "color": [M, K, 3]}`` (any subset),
    added to the decoder heads' pre-activations, except those named in ``post_activation``
    (``"opacity"``, ``"color"``), which are added to the activated values (tanh opacity,
    sigmoid colour). ``active`` switches it off and on (a training schedule may start it
    later).
    """

    active: bool = True
    post_activation: tuple[str, ...] = ()

    def bake_heads(self, values: dict[str, Tensor]) -> list[BakeHead] | None:
        """Its heads for baking, given every anchor's decoded values; None: it declares none
        (its decoded models render unbaked)."""
        return None


class TrainingHook(_Component):
    """Code the trainer runs around each step, built as ``cls(trainer)``.

    Hooks steer the trainer through ``trainer.phase`` (quantization phase),
    ``trainer.render_scale`` (progressive resolution) and ``trainer.extra_losses`` (name ->
    callable(ctx) -> scalar). Every method is a no-op by default.
    """

    name: ClassVar[str] = ""

    def before_step(self, it: int) -> None:
        """Before iteration ``it`` renders."""

    def after_backward(self, it: int, ctx: Any) -> None:
        """After the loss's backward pass (``ctx``: the step's render context)."""

    def after_step(self, it: int) -> None:
        """After the optimizer step (growing and pruning run here)."""

    def state_dict(self) -> dict | None:
        """State saved in checkpoints; None: nothing to save."""
        return None

    def load_state_dict(self, state: dict) -> None:
        """Restore what :meth:`state_dict` returned."""

    def restore(self, it: int) -> None:
        """After a checkpoint of iteration ``it`` is loaded: re-derive the module state the hook
        sets in :meth:`before_step` (a loaded run is rendered or encoded without a step)."""

    def log_fields(self) -> dict[str, int | float]:
        """Figures the hook adds to each line of the training log (``train_log.jsonl``), e.g.
        counts since the start of training. Default: none."""
        return {}

    @classmethod
    def stage_starts(cls, cfg) -> list[int]:
        """The iterations (of this run's schedule) after which the hook starts a new stage of
        training; anchors grown in each stage are counted apart by the census. Default: none."""
        return []

    @classmethod
    def all_on_sets(cls, cfg) -> list[str]:
        """``--set`` values that turn every stage of the hook on from the first step (``pgs
        bench train`` times a step with everything on). Default: none."""
        return []


class MaskTraining(_Component):
    """How the Gaussian masks train (``entropy.mask_training``), built as ``cls(trainer)``, so
    that neither a method nor an entropy model branches on it."""

    name: ClassVar[str] = ""
    # masks multiply opacity and scale after the opacity > 0 selection (else before it)
    mask_after_selection: ClassVar[bool] = False

    @property
    def render_rate_sample(self) -> float:
        """The share of the visible anchors whose rate the render samples."""
        raise NotImplementedError

    def mask_lr_final(self, cfg, extent: float) -> float | None:
        """The mask logits' final learning rate; None: the config's."""
        return None

    def loss(self, result) -> tuple[list, dict]:
        """The adaptive phase's (terms added to the loss in order, logged terms)."""
        raise NotImplementedError


class EntropyModel(Protocol):
    """The rate model and coder of the coded attributes (``baseline.hac.entropy`` holds the
    shared implementation). Values are {name: [N, dims]} for N anchors at ``xyz`` [N, 3];
    ``gauss_mask`` [N, K] gates the masked attributes."""

    kind: ClassVar[str]
    attrs: tuple[CodedAttribute, ...]
    n_masks: int

    @classmethod
    def build(cls, cfg, attrs, n_masks: int, n_anchors: int) -> EntropyModel:
        """The model a training config selects, its head sized from ``attrs``."""
        ...

    @classmethod
    def check_header(cls, entry: dict, key: str) -> int:
        """Check this model's own fields of a file header's entropy entry (named under ``key``);
        returns the hash-grid entries the decoder will allocate."""
        ...

    def forward(self, xyz: Tensor, values: dict[str, Tensor], gauss_mask: Tensor | None = None,
                training: bool = True, **options) -> tuple[dict[str, Tensor], dict[str, Tensor]]:
        """(quantized values {name: [N, d]}, bits {name: [N]})."""
        ...

    def hash_bits(self) -> Tensor:
        """The bits of its own shared state (a hash grid's), a scalar."""
        ...

    def set_bounds(self, xyz_min: Tensor, xyz_max: Tensor) -> None:
        """The anchors' box (context models normalise positions by it)."""
        ...

    def config(self) -> dict:
        """JSON-able constructor options, written into the file header."""
        ...

    def compress(self, xyz: Tensor, values: dict[str, Tensor], gauss_mask: Tensor | None = None,
                 return_values: bool = False) -> Any:
        ...

    def decompress(self, xyz: Tensor, blobs: dict[str, bytes], gauss_mask: Tensor | None = None,
                   n: int | None = None) -> dict[str, Tensor]:
        ...

    def serialize(self, precision: str = "float32", used_xyz: Tensor | None = None
                  ) -> dict[str, bytes]:
        ...

    def load_serialized(self, blobs: dict[str, bytes], used_xyz: Tensor | None = None) -> None:
        ...


def feature_cache(model) -> FeatureProvider | None:
    """The model's feature provider when it precomputes features for decoded models, else None."""
    prov = getattr(model, "provider", None)
    return prov if isinstance(prov, FeatureProvider) and prov.caches_features else None


@dataclass(frozen=True)
class MethodSpec:
    """A method as users name it, registered under kind ``method`` (a plugin's ``register``, or
    a patch file of kind ``method``).

    Attributes:
        name: the patch that selects it (``--vs NAME``), also its run folders' prefix.
        label: what tables, legends and CSV files call it.
        description: one line.
        patches: the patches it ships (found by ``--patch``), its own first.
        notes: what the report's notes say of it, by topic (``feature_sections``: what its
            ``feature`` group holds; ``grown_anchors``: how its grown anchors split by stage).
        demo: one of ``pgs demo``'s default contenders against the baseline.
    """

    name: str
    label: str
    description: str = ""
    patches: tuple[str, ...] = ()
    notes: tuple[tuple[str, str], ...] = ()
    demo: bool = False

    def note(self, topic: str) -> str | None:
        return dict(self.notes).get(topic)
