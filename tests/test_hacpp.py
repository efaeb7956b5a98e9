"""HAC++'s entropy model (`hacpp`): the mixture likelihood, teacher forcing vs chunk-by-chunk
coding, exact round trips for HAC and Predict-GS, thread counts, damaged files."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import torch

from baseline.codec.mixture import MixtureStreamDecoder, MixtureStreamEncoder, mixture_pmf
from baseline.contracts import CodedAttribute
from baseline.hac.entropy import build_entropy_model
from baseline.hac.hacpp import (HACPPEntropyModel, chunk_sizes, mixture_bits_reference,
                                mixture_likelihood)

ATTRS = (CodedAttribute("feat", 50, 1.0), CodedAttribute("scaling", 6, 0.001),
         CodedAttribute("offsets", 30, 0.2, masked=True))
SMALL_GRID = dict(resolutions_3d=(8, 16), log2_table_3d=10, resolutions_2d=(16, 32),
                  log2_table_2d=10)


def _model(seed=0, **kw):
    torch.manual_seed(seed)
    m = HACPPEntropyModel(ATTRS, 10, grid_options=SMALL_GRID, chunk=700, **kw)
    m.set_bounds(torch.full((3,), -2.0), torch.full((3,), 2.0))
    with torch.no_grad():                 # a plausible, not a degenerate, model
        for p in m.parameters():
            if p.dim() == 2 and p.shape[0] != 1:
                p.mul_(0.5)
    return m


def _payload(n=2400, seed=1):
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(n, 3, generator=g) * 3.6 - 1.8
    vals = {"feat": torch.randn(n, 50, generator=g) * 3,
            "scaling": torch.rand(n, 6, generator=g) * 0.05,
            "offsets": torch.randn(n, 30, generator=g) * 0.5}
    mask = (torch.rand(n, 10, generator=g) < 0.5).float()
    return xyz, vals, mask


def test_chunk_sizes():
    assert chunk_sizes(50, 5) == [10] * 5 and chunk_sizes(25, 5) == [5] * 5
    assert chunk_sizes(10, 5) == [2] * 5 and chunk_sizes(6, 5) == [2, 1, 1, 1, 1]
    assert chunk_sizes(3, 5) == [1, 1, 1]
    m = _model()
    assert m.n_out == 225 and len(m.ctx) == 5
    assert [net[0].in_features for net in m.ctx] == [150, 160, 170, 180, 190]
    assert all(net[2].out_features == 30 for net in m.ctx)


def test_mixture_sums_to_one_and_matches_the_components():
    g = torch.Generator().manual_seed(0)
    n = 64
    m1, m2 = torch.randn(n, generator=g, dtype=torch.float64) * 3, torch.randn(n, generator=g, dtype=torch.float64)
    s1, s2 = torch.rand(n, generator=g, dtype=torch.float64) * 2 + 0.3, torch.rand(n, generator=g, dtype=torch.float64) + 0.2
    l1, l2 = torch.randn(n, generator=g, dtype=torch.float64), torch.randn(n, generator=g, dtype=torch.float64)
    q = torch.full((n,), 0.7, dtype=torch.float64)
    ks = torch.arange(-200, 201, dtype=torch.float64)[:, None]
    x = ks * q                                      # every bin, [401, n]
    p = torch.softmax(torch.stack([l1, l2], -1), -1)
    raw = (p[..., 0] * (torch.special.ndtr((x + 0.35 - m1) / s1) - torch.special.ndtr((x - 0.35 - m1) / s1))
           + p[..., 1] * (torch.special.ndtr((x + 0.35 - m2) / s2) - torch.special.ndtr((x - 0.35 - m2) / s2)))
    assert torch.allclose(raw.sum(0), torch.ones(n, dtype=torch.float64), atol=1e-12)
    lik = mixture_likelihood(x, q, m1, s1, l1, m2, s2, l2)
    assert torch.allclose(lik, raw.clamp_min(1e-6), rtol=1e-9, atol=0)
    assert torch.allclose(-torch.log2(lik), mixture_bits_reference(x, q, m1, s1, l1, m2, s2, l2),
                          rtol=1e-10, atol=1e-10)
    # the coder's probabilities of every symbol of an alphabet sum to 1 exactly
    smin, smax = -30, 45
    sym = np.repeat(np.arange(smin, smax + 1), 3)
    k = sym.size
    pm = mixture_pmf(sym, smin, smax, np.full(k, 1.5), np.full(k, 2.0), np.full(k, -4.0),
                     np.full(k, 0.7), np.full(k, 0.3))
    assert pm.reshape(-1, 3)[:, 0].sum() == pytest.approx(1.0, abs=1e-12)
    assert (pm > 0).all()


def test_mixture_stream_round_trip_with_escapes():
    rng = np.random.default_rng(3)
    enc = MixtureStreamEncoder(escape_limit=40)
    chunks = []
    for n in (0, 1, 500, 3000):
        m1, m2 = rng.normal(0, 3, n), rng.normal(0, 5, n)
        s1, s2 = np.exp(rng.normal(0, 1.5, n)), np.exp(rng.normal(0, 1.5, n))
        w = rng.random(n)
        s = np.rint(np.where(rng.random(n) < w, rng.normal(m1, s1), rng.normal(m2, s2))).astype(np.int64)
        if n > 10:
            s[::50] += 10 ** 6                     # beyond the escape limit
        enc.add(s, m1, s1, m2, s2, w)
        chunks.append((s, m1, s1, m2, s2, w))
    blob = enc.finish()
    dec = MixtureStreamDecoder(blob, escape_limit=40)
    for s, *p in chunks:
        assert np.array_equal(dec.decode(*p), s)
    dec.check_done()


def _own_payload(m, n=2400, seed=1):
    """Values drawn near the hyperprior's own means and scales (as a trained model sees them):
    probabilities away from the floor, where the float path is accurate."""
    xyz, vals, mask = _payload(n, seed)
    g = torch.Generator().manual_seed(seed + 7)
    with torch.no_grad():
        P = m.params(xyz)
        for a in ATTRS:
            mean, scale, q = P[a.name]
            vals[a.name] = (mean + torch.randn(mean.shape, generator=g) * scale.clamp(max=5.0)
                            + q * 0.3).float()
    return xyz, vals, mask


def test_teacher_forced_training_bits_equal_the_coding_bits():
    m = _model()
    xyz, vals, mask = _own_payload(m)
    vals = m.quantize_for_coding(xyz, vals, mask)   # the same values (symbols) on both paths
    md = _model().double()                     # the training path in float64: what is left
    md.load_state_dict(m.state_dict())         # is the coding path's fixed point
    _, bits = md(xyz.double(), {k: v.double() for k, v in vals.items()}, mask.double(),
                 training=False)               # all chunks at once, rounded values
    exact = m.exact_bits(xyz, vals, mask)                  # chunk by chunk, the coding path
    for a in ATTRS[:1]:        # the mixture and its channel context (the others: HAC's Gaussian)
        t, e = bits[a.name].detach().double(), exact[a.name]
        # per anchor within the fixed point's perturbation (~2^-20 on the hyperprior, ~2^-16 on
        # the channel networks' inputs); the totals within 1e-4
        assert torch.allclose(t, e, rtol=1e-3, atol=0.05), (a.name, (t - e).abs().max())
        assert float(t.sum()) == pytest.approx(float(e.sum()), rel=1e-4), a.name
    _, b32 = m(xyz, vals, mask, training=False)            # and the float32 path, loosely
    assert torch.allclose(b32["feat"].double(), exact["feat"], rtol=1e-2, atol=0.5)
    # and what is written is that (plus the coder's framing and 16-bit frequencies)
    blobs = m.compress(xyz, vals, mask)
    written = 8 * len(blobs["feat"])
    assert written == pytest.approx(float(exact["feat"].sum()), rel=0.08)   # floors: 2^-16 vs 1e-6


def test_round_trip_is_exact_and_config_rebuilds():
    m = _model()
    xyz, vals, mask = _payload()
    side = m.serialize("float16")
    blobs, vq = m.compress(xyz, vals, mask, return_values=True)
    m2 = build_entropy_model(m.config())
    m2.load_serialized(side)
    out = m2.decompress(xyz, blobs, mask, n=xyz.shape[0])
    for k, v in vq.items():
        assert torch.equal(out[k], v), k
    assert m.config()["kind"] == "hacpp" and m.config()["main"] == "feat"


def _train(scene, out, patches):
    from baseline.train.trainer import Trainer
    from baseline.data.scene import load_scene
    from conftest import demo_cfg
    t = Trainer(demo_cfg(150, patches=patches), load_scene(scene), out, progress=False)
    t.train()
    assert t.phase == "adaptive"
    return t


@pytest.fixture(scope="module")
def hacpp_files(small_scene, tmp_path_factory):
    from baseline.modelfile import encode_model
    d = tmp_path_factory.mktemp("hacpp")
    out = {}
    # the hacpp composition: entropy model, mask training and lattice positions
    for name, patches in (("hac", ["hacpp"]), ("pgs", ["predict-gs", "hacpp"])):
        t = _train(small_scene, d / name, patches)
        st = encode_model(t.cfg, t.model, t.entropy, d / f"{name}.pgs",
                          extra_header={"scene": str(small_scene)})
        out[name] = (t, st, d / f"{name}.pgs")
    return out


@pytest.mark.parametrize("name", ["hac", "pgs"])
def test_hac_and_predict_gs_round_trip_with_hacpp(hacpp_files, name):
    from baseline.modelfile import decode_model, file_info
    t, st, path = hacpp_files[name]
    assert t.entropy.kind == "hacpp"
    assert t.entropy.main == ("feat" if name == "hac" else "residual")
    dec = decode_model(path)
    assert dec.entropy.kind == "hacpp"
    assert t.cfg.entropy.mask_training == "hacpp" and dec.header["position_coding"] == "lattice"
    assert torch.equal(dec.model.xyz, t.model.xyz.detach()[st["index"]])   # positions exact
    for k, v in st["values"].items():
        assert torch.equal(v, dec.model.fixed_values[k]), k
    labels = {r["section"]: r["label"] for r in file_info(path)["sections"]}
    assert labels["em.ctx"] == "hacpp.channel_context" and labels["em.mlp"] == "hacpp.hyperprior"
    if name == "pgs":                              # 25 residual values in 5 chunks of 5
        assert t.entropy.sizes == [5] * 5


@pytest.mark.parametrize("name", ["hac", "pgs"])
def test_float16_weights_decode_and_a_header_contradicting_them_is_refused(hacpp_files, name,
                                                                           tmp_path):
    """Every weight blob of a float16 file (networks, hyperprior, channel context, grids) stores
    float16 tensors; the same file re-signed as float32 is refused by the decoder."""
    import copy
    import dataclasses

    from baseline.codec.container import BitstreamError, read_container
    from baseline.testing.hostile import _resign
    from baseline.modelfile import decode_model, encode_model
    t, _, _ = hacpp_files[name]
    model, entropy = copy.deepcopy(t.model), copy.deepcopy(t.entropy)
    cfg = dataclasses.replace(t.cfg, codec=dataclasses.replace(t.cfg.codec, weight_dtype="float16"))
    st = encode_model(cfg, model, entropy, tmp_path / "h.pgs")
    dec = decode_model(tmp_path / "h.pgs")
    for k, v in st["values"].items():
        assert torch.equal(v, dec.model.fixed_values[k]), k
    header, sections = read_container(tmp_path / "h.pgs")
    header["weight_dtype"] = "float32"
    (tmp_path / "bad.pgs").write_bytes(_resign(header, list(sections.items())))
    with pytest.raises(BitstreamError, match="weight_dtype"):
        decode_model(tmp_path / "bad.pgs")


def test_hacpp_file_decodes_identically_with_two_threads(hacpp_files, tmp_path):
    t, st, path = hacpp_files["pgs"]
    out = tmp_path / "vals.pt"
    code = ("import torch; torch.set_num_threads(2); assert torch.get_num_threads() == 2;"
            "from baseline import registry; registry.ensure_loaded();"
            "from baseline.modelfile import decode_model;"
            f"torch.save(decode_model(r'{path}').model.fixed_values, r'{out}')")
    subprocess.run([sys.executable, "-c", code], check=True,
                   env=dict(os.environ, OMP_NUM_THREADS="2"))
    other = torch.load(out)
    for k, v in st["values"].items():
        assert torch.equal(v, other[k]), k


def test_damaged_hacpp_files_give_clean_errors(hacpp_files):
    from baseline.testing.hostile import crafted_cases, run_cases
    files = {n: hacpp_files[n][2].read_bytes() for n in ("hac", "pgs")}
    cases = [c for c in crafted_cases(files, n_random=30, seed=2)
             if any(k in c.name for k in ("truncated", "flipped", "overwritten", "taken from",
                                            "unchanged", "removed"))]
    st = run_cases(cases)
    assert not st["findings"], st["findings"][:10]
    assert st["refused"] > 100
