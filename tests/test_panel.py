"""The report's panels: ground truth, each method's decoded render, error map and bit map."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from baseline.codec.container import read_container
from baseline.modelfile import coded_bits_per_anchor, decode_model
from baseline.data.images import read_image
from baseline.data.scene import load_scene
from baseline.eval.report.panel import bit_map, view_panel


def test_panel_images_and_bit_map_totals(decoded_files, tmp_path):
    scene = load_scene(decoded_files["scene"])
    files = [(n, decoded_files[n] / "model.pgs") for n in ("baseline", "predict-gs")]
    rec = view_panel(files, scene, 1, tmp_path / "p")
    cam = scene.test_cameras[1]
    gt = read_image(rec["images"]["gt"])
    assert gt.shape[:2] == (cam.height, cam.width)
    for label, path in files:
        img = read_image(rec["images"][label]["render"])
        assert img.shape[:2] == (cam.height, cam.width), label
        for kind in ("error", "bits"):        # with a colour bar: wider than the view
            img = read_image(rec["images"][label][kind])
            assert img.shape[1] > cam.width and img.shape[0] >= cam.height, (label, kind)
        # the file's bits: per-anchor (what the map shows) + shared (no pixel owns them)
        split = rec["file_bits"][label]
        assert split["file"] == 8 * path.stat().st_size
        assert split["per_anchor"] + split["shared"] == pytest.approx(split["file"])
        assert 0 < split["shared"] < split["file"]
        dec = decode_model(path)
        bits = coded_bits_per_anchor(dec)
        bmap, shown = bit_map(dec, cam, bits)
        saved = np.load(tmp_path / "p" / f"{label}-bits.npy")
        assert np.array_equal(saved, bmap)
        # the map's total is the coded bits of exactly the anchors it shows
        assert 0 < shown.sum() < len(shown) or shown.all()
        assert bmap.sum() == pytest.approx(float(bits[torch.from_numpy(shown)].sum()), rel=1e-12)
        assert rec["bits_shown"][label] == pytest.approx(bmap.sum())
        # and the per-anchor bits are the file's: their sum is the attribute sections' payload
        _, sections = read_container(path)
        coded = sum(8 * len(sections[a.name]) for a in dec.entropy.attrs)
        assert float(bits.sum()) == pytest.approx(coded, rel=0.05, abs=2048)
    assert rec["error_vmax"] > 0 and rec["bits_vmax"] > 0
    assert (tmp_path / "p" / "panel.png").stat().st_size > 10_000
