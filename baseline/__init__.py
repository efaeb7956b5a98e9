"""Scaffold-GS + HAC: the baseline of the anchor-based 3DGS compression toolkit.

This package never imports a plugin; plugins extend it through :mod:`baseline.registry`.
"""

__version__ = "0.1.0"
