"""The ``pgs bench`` measures: each times its work against a reference in the same process and
prints ratios, so two figures taken at different times on a shared machine are never divided.

Modules: :mod:`~baseline.bench.raster` (the rasterizer backends side by side),
:mod:`~baseline.bench.codec` (entropy coding and decoding of the coded attributes),
:mod:`~baseline.bench.grid` (the hash grids' forward and backward), :mod:`~baseline.bench.train`
(a training step per stage, from a run's checkpoint), :mod:`~baseline.bench.fps` (decoded models'
frames, and a frame per stage).
"""
