"""Training: trainer, losses, phase and densification hooks."""
from baseline.scaffold import densify  # noqa: F401  (registers the scaffold_densify hooks)
from baseline.train import masks  # noqa: F401  (registers the mask_training strategies)
from baseline.train import phases  # noqa: F401  (registers the hac_phases hooks)
