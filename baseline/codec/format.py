"""The ``.pgs`` format's constants and hard caps: what every reader and writer of a file agrees
on. A leaf: it imports nothing of the toolkit, so the models below the file format and the
checks of the header share one definition."""
from __future__ import annotations

FORMAT = "pgs-anchor-model"          # the header's "format"
FILE_VERSION = 2           # the header's "file_version": 2 = sections bound by keyed digests
DIGEST_BYTES = 8

# caps on what a header may make the decoder build
MAX_ANCHORS = 1 << 27
MAX_OFFSETS = 64
MAX_DIMS = 4096
MAX_HIDDEN = 4096
MAX_ATTRS = 64
MAX_CHUNK = 1 << 20
MAX_ESCAPE = 1 << 20        # symbols beyond it are stored raw; keeps the coder's alphabet small
MAX_GRID_LEVELS = 32
MAX_GRID_RES = 1 << 16
MAX_GRID_LOG2 = 24
MAX_GRID_FEATURES = 16
MAX_FEATURE_GUESS = 64     # the decoder features per anchor a plan counts (HAC 50)

# how each part of a file is coded (the config's codec section chooses)
POSITION_CODINGS = ("raw16", "sorted", "lattice")
MASK_CODINGS = ("bernoulli", "patterns")
GRID_CODINGS = ("all", "used")
WEIGHT_DTYPES = ("float32", "float16")
# what a header without the field means (the encoder writes a coding only when it is not this)
CODING_DEFAULTS = {"weight_dtype": "float32", "position_coding": "raw16",
                   "mask_coding": "bernoulli", "grid_coding": "all"}
