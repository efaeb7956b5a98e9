"""The codec benchmark runs end to end on a small payload and reports exact decoding."""
import torch

from baseline.bench.codec import format_codec_bench, run_codec_bench

torch.set_num_threads(1)


def test_bench_small():
    rows = run_codec_bench(n_anchors=3000, model="hac", threads=1)
    rows += run_codec_bench(n_anchors=3000, model="factorized", threads=1, variants=("fast",))
    assert [r["variant"] for r in rows] == ["reference", "fast", "fast"]
    # both implementations write the same bytes and decode them exactly
    assert all(r["exact"] for r in rows)
    assert rows[0]["bytes"] == rows[1]["bytes"]
    assert all(r["encode_s"] > 0 and r["decode_s"] > 0 and r["model_s"] > 0 for r in rows)
    assert rows[0]["x_enc"] == 1.0 and rows[1]["x_enc"] == rows[0]["encode_s"] / rows[1]["encode_s"]
    assert rows[2]["x_enc"] is None
    text = format_codec_bench(rows)
    assert "hac" in text and "factorized" in text and "18.72" in text and "reference" in text
    hac, fac = rows[1], rows[2]
    assert hac["bytes"]["em.grid"] < 0.2107 * 2 ** 20 and hac["bytes"]["masks"] > 0
    # the factorized model has no context grid: no grid bytes, and (same payload, no hash-grid
    # side information) a smaller file than HAC's on this small, context-poor random payload
    assert not any(k.startswith("em.grid") for k in fac["bytes"]) and fac["bytes"]["masks"] > 0
    assert fac["total_mb"] < hac["total_mb"]


def test_bench_hacpp_beside_hac():
    rows = run_codec_bench(n_anchors=2000, model="hacpp", threads=1)
    assert [r["variant"] for r in rows] == ["reference", "fast"] and all(r["exact"] for r in rows)
    assert rows[0]["bytes"] == rows[1]["bytes"] and "em.ctx" in rows[1]["bytes"]
    assert "hacpp" in format_codec_bench(rows)
