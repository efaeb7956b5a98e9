"""Scaffold-GS: anchors, feature providers, decoder MLPs, growing and pruning."""
from baseline.scaffold import providers  # noqa: F401  (registers the `explicit` provider)
