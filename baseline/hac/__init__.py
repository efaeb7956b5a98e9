"""HAC: binarized hash-grid context, adaptive quantization and entropy models (docs/method.md section 3).

Importing this package registers the entropy models ``hac``, ``hacpp`` (HAC++'s hyperprior,
channel context and mixture) and ``factorized`` in the ``entropy_model`` registry kind.
"""
from baseline import registry
from baseline.hac.entropy import (EntropyModel, FactorizedEntropyModel, HACEntropyModel,
                                  build_entropy_model, gaussian_bits, gaussian_likelihood)
from baseline.hac.hashgrid import BinaryHashGrid, auto_grid_layout, binarize, binary_entropy_bits
from baseline.hac.quant import adaptive_q, noise_quantize, ste_round

registry.register("entropy_model", "hac", HACEntropyModel)
registry.register("entropy_model", "factorized", FactorizedEntropyModel)
from baseline.hac.hacpp import HACPPEntropyModel  # noqa: E402  (imports the base above)

registry.register("entropy_model", "hacpp", HACPPEntropyModel)

__all__ = ["BinaryHashGrid", "auto_grid_layout", "binarize", "binary_entropy_bits",
           "EntropyModel", "HACEntropyModel", "FactorizedEntropyModel", "build_entropy_model",
           "gaussian_bits", "gaussian_likelihood", "adaptive_q", "noise_quantize", "ste_round"]
