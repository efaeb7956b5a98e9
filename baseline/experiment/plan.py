"""Planning a comparison: the methods of ``--vs``, one :class:`RunSpec` per method, lambda and
seed (its config built and hashed up front, so bad patches fail before any training), and the
uncompressed reference run."""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional

from baseline.config import Config, build_config, config_hash


BASELINE = "baseline"


@dataclass(frozen=True)
class Method:
    name: str                   # "baseline" or the contender's patches joined by "+"
    patches: tuple[str, ...]    # on top of the common patches
    lambdas: Optional[tuple[float, ...]] = None     # its own rate points (``--lambda-for``)


@dataclass
class RunSpec:
    method: Method
    lmbda: float
    cfg: Config
    hash: str
    dir: Path
    seed: Optional[int] = None      # train.seed when the comparison was asked for seeds

    @property
    def label(self) -> str:
        """What progress lines and lists call the run: the method's user-facing name (HAC,
        HAC++, ...; :func:`baseline.eval.report.method_label`), lambda and seed."""
        from baseline.eval.report import method_label

        common = [p for p in self.cfg.patches if p not in self.method.patches]
        return f"{method_label(self.method.name, common)} lambda={self.lmbda:g}" + (
            f" seed={self.seed}" if self.seed is not None else "")


def _method_of(flag: str, value: str) -> Method:
    """``"hacpp+weights-fp16"`` -> Method named by its patches (a ``.toml`` path by its stem)."""
    parts = tuple(p.strip() for p in value.split("+") if p.strip())
    if not parts:
        raise ValueError(f"{flag} '{value}': expected one or more patch names joined by '+'")
    return Method("+".join(Path(p).stem if p.endswith(".toml") else p for p in parts), parts)


def parse_methods(vs: list[str]) -> list[Method]:
    """``["hacpp", "entropy-factorized"]`` -> baseline + one Method each."""
    methods = [Method(BASELINE, ())]
    seen = {BASELINE}
    for v in vs:
        m = _method_of("--vs", v)
        name, parts = m.name, m.patches
        if name in seen:
            raise ValueError(f"--vs '{v}': method '{name}' is listed twice")
        seen.add(name)
        methods.append(Method(name, parts))
    return methods


def resolve_method(flag: str, name: str, methods: list[Method], common_patches=(),
                   extra: tuple[str, ...] = ()) -> str:
    """A method named on the command line -> its ``Method.name``: ``baseline``, a ``--vs``
    value, or its name in the report (``HAC``, ``HAC++``; :func:`method_label`)."""
    from baseline.eval.report import method_label

    by_label = {method_label(m.name, common_patches): m.name for m in methods}
    got = by_label.get(name, name)
    names = [m.name for m in methods] + list(extra)
    if got not in names:
        raise ValueError(f"{flag} {name}: not a method of this comparison "
                         f"(methods: {', '.join(names)})")
    return got


def with_own_lambdas(methods: list[Method], lambda_for: Optional[list[list]],
                     common_patches=()) -> list[Method]:
    """Apply ``--lambda-for METHOD L [L ...]`` (a list of ``[METHOD, L, ...]``): that method's
    rate points replace ``--lambda`` for it. Methods reach different rates at the same lambda,
    so the points where two curves meet (what BD-rate integrates over) may need a lambda only
    one of them is trained at; training the other there too would cost runs that measure
    nothing."""
    own: dict[str, tuple[float, ...]] = {}
    for item in lambda_for or []:
        if len(item) < 2:
            raise ValueError(f"--lambda-for {' '.join(map(str, item))}: expected a method and "
                             f"one or more lambdas")
        name = resolve_method("--lambda-for", str(item[0]), methods, common_patches)
        try:
            lams = tuple(float(x) for x in item[1:])
        except ValueError:
            raise ValueError(f"--lambda-for {' '.join(map(str, item))}: lambdas must be "
                             f"numbers") from None
        if name in own:
            raise ValueError(f"--lambda-for names method '{item[0]}' twice")
        if len(set(lams)) != len(lams):     # the range is the config's (plan_runs checks it)
            raise ValueError(f"--lambda-for {item[0]} lists a value twice: {list(lams)}")
        own[name] = lams
    return [dataclasses.replace(m, lambdas=own[m.name]) if m.name in own else m
            for m in methods]


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.+-]", "_", name)


def plan_runs(out: str | Path, methods: list[Method], lambdas: Optional[list[float]],
              common_patches: list[str] = (), sets: list[str] = (),
              seeds: Optional[list[int]] = None) -> list[RunSpec]:
    """Build every run's config up front (bad patches / keys fail before any training).

    With ``lambdas`` None each method runs once at its config's own ``entropy.lmbda``; a method
    with rate points of its own (``Method.lambdas``) runs at those instead.
    ``seeds``: each rate point is trained once per ``train.seed`` (folders
    ``<method>-l<lambda>-s<seed>-<hash>``), in the order method, seed, lambda, so that one seed's
    whole curve finishes before the next seed starts.
    """
    out = Path(out)
    if seeds is not None:
        seeds = [int(x) for x in seeds]
        if not seeds or len(set(seeds)) != len(seeds) or min(seeds) < 0:
            raise ValueError(f"--seeds must list distinct non-negative integers, got {seeds}")
    specs = []
    for m in methods:
        patches = list(common_patches) + list(m.patches)
        for seed in (seeds if seeds is not None else [None]):
            extra = [] if seed is None else [f"train.seed={seed}"]
            lams = m.lambdas or lambdas
            if lams:
                cfgs = [(float(lm), build_config(patches, list(sets) + extra
                                                 + [f"entropy.lmbda={float(lm)!r}"]))
                        for lm in lams]
            else:
                cfg = build_config(patches, list(sets) + extra)
                cfgs = [(float(cfg.entropy.lmbda), cfg)]
            for lm, cfg in cfgs:
                h = config_hash(cfg)
                tag = "" if seed is None else f"-s{seed}"
                d = out / "runs" / f"{_safe(m.name)}-l{lm:g}{tag}-{h}"
                specs.append(RunSpec(m, lm, cfg, h, d, seed))
    return specs


REFERENCE = "reference"

REFERENCE_PREFIX = "reference-"


def parse_reference(ref: Optional[str]) -> Optional[Method]:
    """``"scaffold"`` -> the uncompressed reference method (patches on top of the common ones)."""
    return None if ref is None else _method_of("--reference", ref)


def plan_reference(out: str | Path, method: Method, common_patches: list[str] = (),
                   sets: list[str] = ()) -> RunSpec:
    """The reference run: the common patches and ``--set`` values plus the reference's patches,
    so it shares the comparison's scene, resolution, split and schedule. It must train without
    quantization or a rate loss (no ``hac_phases`` hook), or it is no uncompressed reference."""
    cfg = build_config(list(common_patches) + list(method.patches), list(sets))
    if "hac_phases" in cfg.train.hooks:
        raise ValueError(f"--reference {method.name}: its training runs the 'hac_phases' hook "
                         f"(quantization and the rate loss), so it is not an uncompressed "
                         f"reference; use e.g. --reference scaffold")
    h = config_hash(cfg)
    return RunSpec(method, float(cfg.entropy.lmbda), cfg, h,
                   Path(out) / "runs" / f"{REFERENCE_PREFIX}{_safe(method.name)}-{h}")
