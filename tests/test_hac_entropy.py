"""Entropy models: likelihood, masks, quantization, exact round trips, estimate vs real size."""
import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import scipy.stats
import torch

import baseline.hac  # noqa: F401  (registers the entropy models)
from baseline import registry
from baseline.contracts import CodedAttribute, scaffold_coded_attributes
from baseline.codec.container import BitstreamError
from baseline.hac.entropy import (FactorizedEntropyModel, HACEntropyModel, build_entropy_model,
                                  gaussian_bits, gaussian_likelihood)
from baseline.hac.exact import ExactMLP, det_exp, det_tanh
from baseline.hac.quant import adaptive_q, noise_quantize, ste_round

torch.set_num_threads(1)
ATTRS = scaffold_coded_attributes()
SMALL_GRID = dict(resolutions_3d=(18, 33, 59), log2_table_3d=10, resolutions_2d=(130, 258), log2_table_2d=11)


def make_hac(seed=0, calibrated=True, **kw):
    """A HAC model whose head predicts plausible scales (a 'trained-ish' state)."""
    torch.manual_seed(seed)
    m = HACEntropyModel(ATTRS, 10, grid_options=kw.pop("grid_options", SMALL_GRID), **kw)
    m.set_bounds([-2, -2, -2], [2, 2, 2])
    if calibrated:
        with torch.no_grad():
            m.grid.reset_parameters()
            for gl in m.grid.grids.values():
                gl.params.uniform_(-1, 1)  # binary tables with both signs
            last = m.mlp[-1]
            last.weight.mul_(0.3)
            spread = {"feat": 2.0, "scaling": 0.004, "offsets": 0.4}
            off = 0
            for a in ATTRS:
                last.bias[off:off + a.dims] = 0.0
                last.weight[off + a.dims:off + 2 * a.dims] *= spread[a.name] * 0.5
                last.bias[off + a.dims:off + 2 * a.dims] = spread[a.name]
                last.weight[off:off + a.dims] *= spread[a.name]
                off += 2 * a.dims
    return m


def sample_payload(m, n, seed=0, p_mask=0.5):
    """Positions, masks and values drawn from the model's own coding distribution."""
    g = torch.Generator().manual_seed(seed)
    xyz = torch.rand(n, 3, generator=g) * 3.6 - 1.8
    mask = (torch.rand(n, m.n_masks, generator=g) < p_mask).float()
    P = m.params(xyz, exact=True)
    values = {}
    for a in m.attrs:
        mean, scale, q = P[a.name]
        values[a.name] = (mean + scale * torch.randn(mean.shape, generator=g, dtype=torch.float64)).float()
    return xyz, values, mask


# ------------------------------------------------------------------ math units
def test_likelihood_matches_scipy():
    rng = np.random.default_rng(0)
    x = rng.normal(0, 3, 2000)
    mu = rng.normal(0, 3, 2000)
    sd = np.exp(rng.normal(0, 1.5, 2000))
    q = np.exp(rng.normal(0, 1, 2000))
    ref = np.abs(scipy.stats.norm.cdf((x + q / 2 - mu) / sd) - scipy.stats.norm.cdf((x - q / 2 - mu) / sd))
    ref = np.maximum(ref, 1e-6)
    got = gaussian_likelihood(*(torch.from_numpy(v) for v in (x, mu, sd, q))).numpy()
    np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-15)
    b = gaussian_bits(*(torch.from_numpy(v) for v in (x, mu, sd, q))).numpy()
    assert np.all(b >= 0) and np.all(np.isfinite(b)) and b.max() == pytest.approx(-math.log2(1e-6))
    # scale floor: a negative predicted scale behaves as 1e-9
    assert gaussian_likelihood(torch.tensor(0.0), torch.tensor(0.0), torch.tensor(-1.0), 1.0) == 1.0


def test_adaptive_q_and_quantizers():
    adj = torch.tensor([-50.0, -1.0, 0.0, 1.0, 50.0])
    q = adaptive_q(0.2, adj)
    assert torch.allclose(q[1:4], 0.2 * (1 + torch.tanh(adj[1:4])))
    assert q[0] > 0 and q[4] == pytest.approx(0.4)
    x = torch.randn(1000, requires_grad=True)
    y = noise_quantize(x, 0.5)
    assert (y - x).abs().max() <= 0.25
    z = ste_round(x, 0.5)
    assert torch.allclose(z / 0.5, torch.round(z / 0.5))
    z.sum().backward()
    assert torch.all(x.grad == 1)
    # clamp to mean +- 15000 Q
    w = ste_round(torch.tensor([0.0, 0.0, 3e5], dtype=torch.float64), torch.tensor(1.0, dtype=torch.float64))
    assert w[2] == 1e5 + 15000


def test_deterministic_transcendentals():
    x = np.linspace(-40, 40, 20001)
    assert np.max(np.abs(det_exp(x) / np.exp(x) - 1)) < 1e-15
    assert np.max(np.abs(det_tanh(x) - np.tanh(x))) < 1e-15


def test_exact_mlp_is_exact_and_close():
    torch.manual_seed(0)
    mlp = torch.nn.Sequential(torch.nn.Linear(96, 100), torch.nn.ReLU(), torch.nn.Linear(100, 175))
    a = torch.round(torch.rand(3000, 96, dtype=torch.float64) * 2 ** 21 - 2 ** 20)
    ex = ExactMLP(mlp)
    y = ex(a)
    ref = mlp.double()(a * 2.0 ** -20)
    assert (y - ref).abs().max() < 1e-4
    for L in ex.layers:
        assert L.bound < 2 ** 52
    torch.set_num_threads(2)
    try:
        assert torch.get_num_threads() == 2
        assert torch.equal(ex(a), y)
    finally:
        torch.set_num_threads(1)
    # row subsets (other matmul shapes / blocking) give the same bits
    assert torch.equal(torch.cat([ex(a[:1]), ex(a[1:1001]), ex(a[1001:])]), y)


# ------------------------------------------------------------------ interface
def test_registry_and_head_size():
    assert {"hac", "factorized"} <= set(registry.names("entropy_model"))
    cls = registry.get("entropy_model", "hac")
    m = cls(ATTRS, 10)
    assert m.grid.output_dim == 96
    assert [tuple(l.weight.shape) for l in m.mlp if isinstance(l, torch.nn.Linear)] == [(100, 96), (175, 100)]
    m2 = cls((CodedAttribute("residual", 25, 1.0), ATTRS[1], ATTRS[2]), 10)  # Predict-GS head
    assert m2.mlp[-1].out_features == 2 * (25 + 6 + 30) + 3
    f = registry.get("entropy_model", "factorized")(ATTRS, 10)
    assert float(f.hash_bits()) == 0.0
    with pytest.raises(ValueError):
        cls((CodedAttribute("offsets", 31, 0.2, masked=True),), 10)


@pytest.mark.parametrize("kind", ["hac", "factorized"])
def test_forward_bits_and_masks(kind):
    m = make_hac() if kind == "hac" else FactorizedEntropyModel(ATTRS, 10)
    n = 300
    xyz = torch.rand(n, 3) * 2 - 1
    vals = {a.name: torch.randn(n, a.dims) * (1 if a.name != "scaling" else 0.01) for a in ATTRS}
    mask = (torch.rand(n, 10) < 0.5).float()
    for training in (True, False):
        vh, bits = m(xyz, vals, mask, training=training)
        for a in ATTRS:
            assert bits[a.name].shape == (n,)
            assert torch.all(bits[a.name] >= 0) and torch.all(torch.isfinite(bits[a.name]))
            assert vh[a.name].shape == (n, a.dims)
    P = m.params(xyz)
    # eval: bits are exactly the per-element formula summed over the coded values
    vh, bits = m(xyz, vals, mask, training=False)
    mean, scale, q = P["offsets"]
    per = gaussian_bits(vh["offsets"], mean, scale, q)
    on = mask.repeat_interleave(3, dim=1)
    assert torch.allclose(bits["offsets"], (per * on).sum(-1), rtol=1e-5)
    # masked-off offsets do not count, whatever their value
    vals2 = dict(vals, offsets=torch.where(on > 0, vals["offsets"], vals["offsets"] + 100.0))
    _, bits2 = m(xyz, vals2, mask, training=False)
    assert torch.allclose(bits2["offsets"], bits["offsets"])
    _, bits0 = m(xyz, vals, torch.zeros(n, 10), training=False)
    assert torch.all(bits0["offsets"] == 0) and torch.all(bits0["feat"] == bits["feat"])
    # training noise stays within half a step
    vh, _ = m(xyz, vals, mask, training=True)
    assert torch.all((vh["feat"] - vals["feat"]).abs() <= P["feat"][2] / 2 + 1e-6)


@pytest.mark.parametrize("kind", ["hac", "factorized"])
def test_rate_rows_equal_full_bits_on_the_sample(kind):
    """Bits on a rate sample (the training path: likelihood only where the loss uses it) equal
    the full computation's on those rows; values are quantized for every anchor alike."""
    m = make_hac() if kind == "hac" else FactorizedEntropyModel(ATTRS, 10)
    n = 400
    g = torch.Generator().manual_seed(5)
    xyz = torch.rand(n, 3, generator=g) * 2 - 1
    vals = {a.name: torch.randn(n, a.dims, generator=g) * (1 if a.name != "scaling" else 0.01) for a in ATTRS}
    mask = (torch.rand(n, 10, generator=g) < 0.5).float()
    choose = torch.rand(n, generator=g) < 0.1
    vh, full = m(xyz, vals, mask, training=False)
    vh_s, part = m(xyz, vals, mask, training=False, rate_rows=choose)
    for a in ATTRS:
        assert part[a.name].shape == (int(choose.sum()),)
        assert torch.allclose(part[a.name], full[a.name][choose], rtol=1e-5, atol=1e-4)
        assert torch.allclose(vh_s[a.name], vh[a.name], rtol=0, atol=1e-6)
    # gradients still reach the whole head (the q columns from every anchor, the rest from the sample)
    if kind == "hac":
        m.zero_grad()
        _, part = m(xyz, vals, mask, training=True, rate_rows=choose.nonzero()[:, 0])
        sum(b.sum() for b in part.values()).backward()
        assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in m.mlp.parameters())


def test_gradients_reach_grid_mlp_and_values():
    m = make_hac()
    n = 200
    xyz = torch.rand(n, 3) * 2 - 1
    vals = {a.name: (torch.randn(n, a.dims) * 0.5).requires_grad_() for a in ATTRS}
    _, bits = m(xyz, vals, torch.ones(n, 10), training=True)
    (sum(b.sum() for b in bits.values()) + m.hash_bits()).backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in m.mlp.parameters())
    assert any(g.params.grad.abs().sum() > 0 for g in m.grid.grids.values())
    assert all(v.grad.abs().sum() > 0 for v in vals.values())


# ------------------------------------------------------------------ exact coding
@pytest.mark.parametrize("kind", ["hac", "factorized"])
def test_round_trip_bit_identical_across_thread_counts(kind):
    if kind == "hac":
        m = make_hac(chunk=700)
    else:
        m = FactorizedEntropyModel(ATTRS, 10, chunk=700)
    n = 2500
    xyz = torch.rand(n, 3) * 3.6 - 1.8
    vals = {"feat": torch.randn(n, 50) * 3, "scaling": torch.rand(n, 6) * 0.05, "offsets": torch.randn(n, 30) * 0.5}
    if kind == "factorized":
        m.fit_(vals)
    mask = (torch.rand(n, 10) < 0.5).float()
    blobs, vq = m.compress(xyz, vals, mask, return_values=True)
    assert all(torch.equal(vq[k], v) for k, v in m.quantize_for_coding(xyz, vals, mask).items())
    for threads in (1, 2):
        torch.set_num_threads(threads)
        try:
            assert torch.get_num_threads() == threads
            m.chunk = 999  # the decoder follows the stream's chunking, not its own setting
            dec = m.decompress(xyz, blobs, mask, n=n)
        finally:
            torch.set_num_threads(1)
            m.chunk = 700
        for a in ATTRS:
            assert dec[a.name].dtype == torch.float32
            assert torch.equal(dec[a.name], vq[a.name]), (threads, a.name)
    off = vq["offsets"].reshape(n, 10, 3)
    assert torch.all(off[mask == 0] == 0) and torch.any(off[mask == 1] != 0)
    # decoded values are quantized to the coding step and close to the input
    P = m.params(xyz, exact=True)
    q = P["feat"][2]
    assert torch.all((vq["feat"].double() - vals["feat"].double()).abs() <= q / 2 + 1e-5)
    # encoding twice gives the same bytes
    assert m.compress(xyz, vals, mask) == blobs


def test_round_trip_in_subprocess_with_other_threads(tmp_path):
    m = make_hac(chunk=1000)
    xyz, vals, mask = sample_payload(m, 2000, seed=3)
    side = m.serialize("float16")  # rounds the live weights: the encoder codes with them
    blobs, vq = m.compress(xyz, vals, mask, return_values=True)
    torch.save(dict(config=m.config(), side=side, blobs=blobs, xyz=xyz, mask=mask, vq=vq), tmp_path / "s.pt")
    script = textwrap.dedent(f"""
        import torch
        torch.set_num_threads(2)
        from baseline.hac.entropy import build_entropy_model
        d = torch.load({str(tmp_path / 's.pt')!r}, weights_only=False)
        m = build_entropy_model(d["config"], chunk=123)
        m.load_serialized(d["side"])
        out = m.decompress(d["xyz"], d["blobs"], d["mask"])
        assert all(torch.equal(out[k], d["vq"][k]) for k in out), "mismatch"
        print("EXACT")
    """)
    # the checkout first, the caller's own PYTHONPATH kept (where dependencies may live)
    path = os.pathsep.join(p for p in (os.getcwd(), os.environ.get("PYTHONPATH", "")) if p)
    env = dict(os.environ, PYTHONPATH=path, OMP_NUM_THREADS="2")
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0 and "EXACT" in r.stdout, r.stderr[-2000:]


def test_serialize_round_trip_into_fresh_model():
    m = make_hac()
    xyz, vals, mask = sample_payload(m, 1500, seed=4)
    side = m.serialize("float32")
    blobs, vq = m.compress(xyz, vals, mask, return_values=True)
    fresh = build_entropy_model(m.config())
    fresh.load_serialized(side)
    out = fresh.decompress(xyz, blobs, mask)
    assert all(torch.equal(out[k], vq[k]) for k in out)
    f = FactorizedEntropyModel(ATTRS, 10)
    f.fit_(vals, mask)
    fs = f.serialize("float16")
    b2, v2 = f.compress(xyz, vals, mask, return_values=True)
    g = build_entropy_model(f.config())
    g.load_serialized(fs)
    assert all(torch.equal(g.decompress(xyz, b2, mask)[k], v2[k]) for k in v2)


def test_escapes_and_edge_cases():
    m = make_hac(escape_limit=50)
    assert m.escape_limit == 50
    n = 400
    xyz = torch.rand(n, 3) * 2 - 1
    vals = {"feat": torch.randn(n, 50), "scaling": torch.rand(n, 6) * 0.01, "offsets": torch.randn(n, 30) * 0.3}
    vals["feat"][::7, 3] = 4000.0  # far outside the predicted distribution: escape symbols
    vals["feat"][::11, 5] = -2.5e4
    mask = (torch.rand(n, 10) < 0.5).float()
    blobs, vq = m.compress(xyz, vals, mask, return_values=True)
    assert torch.equal(m.decompress(xyz, blobs, mask)["feat"], vq["feat"])
    assert vq["feat"][0, 3] == pytest.approx(4000.0, abs=2.0)
    # the stream carries its escape limit: a decoder configured differently still decodes it
    other = make_hac()
    assert other.escape_limit != 50
    assert torch.equal(other.decompress(xyz, blobs, mask)["feat"], vq["feat"])
    # no anchors at all, and all masks off
    e = {a.name: torch.zeros(0, a.dims) for a in ATTRS}
    eb, ev = m.compress(torch.zeros(0, 3), e, torch.zeros(0, 10), return_values=True)
    assert all(v.shape == (0, a.dims) for a, v in zip(ATTRS, m.decompress(torch.zeros(0, 3), eb, torch.zeros(0, 10)).values()))
    zb, zv = m.compress(xyz, vals, torch.zeros(n, 10), return_values=True)
    assert torch.all(m.decompress(xyz, zb, torch.zeros(n, 10))["offsets"] == 0)
    # wrong decoding inputs are reported, not silently decoded
    with pytest.raises(BitstreamError):
        m.decompress(xyz, blobs, torch.ones(n, 10))  # mask differs: symbol counts differ
    with pytest.raises(BitstreamError):
        m.decompress(xyz, {k: v[:10] for k, v in blobs.items()}, mask)
    with pytest.raises(BitstreamError):
        m.decompress(xyz, {"feat": blobs["feat"]}, mask)
    with pytest.raises(ValueError):
        m.compress(xyz, dict(vals, feat=vals["feat"] * float("nan")), mask)


def test_estimated_bits_match_real_size():
    m = make_hac()
    n = 20000
    xyz, vals, mask = sample_payload(m, n, seed=7)
    est = m.estimate_bits(xyz, vals, mask)
    blobs = m.compress(xyz, vals, mask)
    for a in ATTRS:
        real = 8 * len(blobs[a.name])
        assert real == pytest.approx(est[a.name], rel=0.01), (a.name, real, est[a.name])
    f = FactorizedEntropyModel(ATTRS, 10)
    f.fit_(vals, mask)
    est = f.estimate_bits(xyz, vals, mask)
    blobs = f.compress(xyz, vals, mask)
    for a in ATTRS:
        assert 8 * len(blobs[a.name]) == pytest.approx(est[a.name], rel=0.01), a.name


def _round_half_even(fr):
    return round(fr)  # Python rounds Fractions half to even, like torch.round


def test_exact_mlp_equals_integer_arithmetic():
    """The fixed-point MLP is bit-identical to an independent big-integer evaluation."""
    from fractions import Fraction

    torch.manual_seed(1)
    mlp = torch.nn.Sequential(torch.nn.Linear(12, 9), torch.nn.ReLU(), torch.nn.Linear(9, 5))
    ex = ExactMLP(mlp)
    a = torch.round(torch.rand(40, 12, dtype=torch.float64) * 2 ** 21 - 2 ** 20)
    got = ex(a)
    L1, L2 = ex.layers
    for r in range(a.shape[0]):
        x = [int(v) for v in a[r]]
        h = []
        for j in range(9):
            y = sum(x[i] * int(L1.w[j, i]) for i in range(12)) + int(L1.b[j])
            y = max(y, 0)
            h.append(_round_half_even(Fraction(y) * Fraction(2) ** (L1.out_frac_next - L1.w_frac - L1.in_frac)))
        for o in range(5):
            y = sum(h[i] * int(L2.w[o, i]) for i in range(9)) + int(L2.b[o])
            ref = float(Fraction(y) * Fraction(2) ** (-(L2.w_frac + L2.in_frac)))
            assert got[r, o].item() == ref


def test_exact_params_independent_of_summation_order():
    """Permuting the hidden units changes every float summation order, not the exact params."""
    m = make_hac()
    xyz = torch.rand(3000, 3) * 3.6 - 1.8
    P = m.params(xyz, exact=True)
    perm = torch.randperm(m.hidden)
    with torch.no_grad():
        m.mlp[0].weight.copy_(m.mlp[0].weight[perm])
        m.mlp[0].bias.copy_(m.mlp[0].bias[perm])
        m.mlp[2].weight.copy_(m.mlp[2].weight[:, perm])
    P2 = m.params(xyz, exact=True)
    for k in P:
        for t, t2 in zip(P[k], P2[k]):
            assert torch.equal(t, t2), k


def test_exact_grid_features_equal_integer_reference():
    """features_fixed is bit-identical to an independent per-point evaluation with integer weights."""
    torch.manual_seed(2)
    g = HACEntropyModel(ATTRS, 10, grid_options=SMALL_GRID).grid
    with torch.no_grad():
        for gl in g.grids.values():
            gl.params.uniform_(-1, 1)
    g.set_bounds([-1.5, -1, -2], [1, 2.5, 2])
    xyz = torch.rand(25, 3) * 3 - 1.5
    got = g.features_fixed(xyz)
    lo = g.xyz_min.double().tolist()
    hi = g.xyz_max.double().tolist()
    tables = {k: (gl.params.detach() >= 0).numpy() * 2 - 1 for k, gl in g.grids.items()}
    PR = (1, 2654435761, 805459861)
    for r in range(xyz.shape[0]):
        u = [(float(xyz[r, a]) - lo[a]) / (hi[a] - lo[a]) for a in range(3)]
        col = 0
        for name, gl in g.grids.items():
            c = [u[a] for a in g._axes[name]]
            D = len(c)
            off = 0
            for res, rows in zip(gl.resolutions, gl.rows):
                vals = [0] * gl.n_features
                wn = 0
                if all(0.0 <= v <= 1.0 for v in c):
                    pos = [v * (res - 2) + 0.5 for v in c]
                    gi = [math.floor(p) for p in pos]
                    w1 = [round((pos[d] - gi[d]) * 32768.0) for d in range(D)]
                    for corner in range(2 ** D):
                        w, cc = 1, []
                        for d in range(D):
                            hi_ = (corner >> d) & 1
                            w *= w1[d] if hi_ else 32768 - w1[d]
                            cc.append(min(gi[d] + 1, res - 1) if hi_ else gi[d])
                        if any(x in (0, res - 1) for x in cc):
                            continue
                        if res ** D <= rows:
                            idx = sum(cc[d] * res ** d for d in range(D))
                        else:
                            h = 0
                            for d in range(D):
                                h ^= (cc[d] * PR[d]) & 0xFFFFFFFF
                            idx = h % rows
                        for ch in range(gl.n_features):
                            vals[ch] += w * int(tables[name][off + idx, ch])
                        wn += w
                for ch in range(gl.n_features):
                    ref = float(round(vals[ch] / (wn if wn else 1) * 2.0 ** 20))
                    assert got[r, col].item() == ref, (r, name, res, ch)
                    col += 1
                off += rows
    assert col == got.shape[1]


# ------------------------------------------------------- decoder_quant = "ste"
def test_ste_round_q_values_and_gradients():
    """Forward: the rounded values of evaluation (clamp included). Backward: identity to x and,
    to the step, the rounding error in steps (summed over what q broadcasts across), checked
    against the value written as x + q * e with e held constant."""
    from baseline.hac.quant import ste_round_q

    g = torch.Generator().manual_seed(3)
    x = (torch.randn(64, 5, generator=g, dtype=torch.float64) * 2).requires_grad_()
    q = (torch.rand(64, 1, generator=g, dtype=torch.float64) + 0.25).requires_grad_()
    y = ste_round_q(x, q)
    assert torch.equal(y.detach(), ste_round(x.detach(), q.detach()))
    w = torch.randn(64, 5, generator=g, dtype=torch.float64)
    (y * w).sum().backward()
    assert torch.equal(x.grad, w)
    e = ((y.detach() - x.detach()) / q.detach())
    assert torch.all(e.abs() <= 0.5 + 1e-12)
    x2, q2 = x.detach().clone().requires_grad_(), q.detach().clone().requires_grad_()
    ((x2 + q2 * e) * w).sum().backward()
    assert torch.allclose(q.grad, q2.grad, rtol=1e-12, atol=1e-12)
    # a scalar step gets the sum over every value
    qs = torch.tensor(0.7, dtype=torch.float64, requires_grad=True)
    x3 = x.detach().clone().requires_grad_()
    (ste_round_q(x3, qs) * w).sum().backward()
    e3 = (torch.round(x3.detach() / 0.7) * 0.7 - x3.detach()) / 0.7
    assert torch.allclose(qs.grad, (w * e3).sum(), rtol=1e-12)


@pytest.mark.parametrize("kind", ["hac", "factorized"])
def test_decoder_quant_ste_rounds_what_the_decoder_sees_and_keeps_the_noisy_rate(kind):
    """Training with decoder_quant="ste": values equal the evaluation's rounded ones, bits are
    the noise proxy's (the same draws as "noise"), gradients reach the values straight through
    and the adaptive steps (HAC) through the rounding error."""
    m = make_hac() if kind == "hac" else FactorizedEntropyModel(ATTRS, 10)
    n = 300
    g = torch.Generator().manual_seed(11)
    xyz = torch.rand(n, 3, generator=g) * 2 - 1
    vals = {a.name: torch.randn(n, a.dims, generator=g) * (1 if a.name != "scaling" else 0.01)
            for a in ATTRS}
    mask = (torch.rand(n, 10, generator=g) < 0.5).float()
    torch.manual_seed(0)
    v_noise, b_noise = m(xyz, vals, mask, training=True)
    torch.manual_seed(0)
    v_ste, b_ste = m(xyz, vals, mask, training=True, decoder_quant="ste")
    v_eval, _ = m(xyz, vals, mask, training=False)
    for a in ATTRS:
        assert torch.equal(b_ste[a.name], b_noise[a.name])
        assert torch.allclose(v_ste[a.name], v_eval[a.name], rtol=0, atol=1e-6)
        assert not torch.allclose(v_ste[a.name], v_noise[a.name])
    with pytest.raises(ValueError, match="decoder_quant"):
        m(xyz, vals, mask, training=True, decoder_quant="round")
    if kind == "hac":
        m.zero_grad()
        vg = {k: v.clone().requires_grad_() for k, v in vals.items()}
        out, _ = m(xyz, vg, mask, training=True, decoder_quant="ste")
        w = {k: torch.randn(v.shape, generator=g) for k, v in out.items()}
        sum((out[k] * w[k]).sum() for k in out).backward()   # a loss on the decoded values only
        for k in vg:
            assert torch.equal(vg[k].grad, w[k])
        last = m.mlp[-1]
        adj_rows = last.weight.grad[-len(ATTRS):]            # the Q-adjustment outputs
        assert adj_rows.abs().sum() > 0


def test_tiny_steps_do_not_clip_the_values():
    """When the adaptive steps collapse (lambda = 0: nothing pushes them up), HAC's clamp to
    mean +- 15000 Q would cut the values themselves; with the base step the clamp is
    mean +- 15000 max(Q, q0): the values decode to within a (tiny) step, exactly, through the
    escapes, and the evaluation path gives the same values. Steps >= q0 keep HAC's clamp."""
    from baseline.hac.quant import clamp_halfwidth, ste_round_q

    x = torch.tensor([0.0, 0.0, 0.3, -0.2], dtype=torch.float64)
    tiny = torch.tensor(1e-9, dtype=torch.float64)
    assert abs(ste_round(x, tiny)[2] - x.mean()) < 2e-5      # HAC's clamp: 0.3 -> mean + 1.5e-5
    assert ste_round(x, tiny, q0=0.001)[2] == pytest.approx(0.3, abs=1e-9)
    assert ste_round_q(x, tiny, q0=0.001)[3] == pytest.approx(-0.2, abs=1e-9)
    q = torch.tensor([0.5, 2.0], dtype=torch.float64)
    assert torch.equal(clamp_halfwidth(q, 1.0), torch.tensor([15000.0, 30000.0], dtype=torch.float64))
    assert torch.equal(clamp_halfwidth(q), 15000 * q)

    m = make_hac()
    with torch.no_grad():                                     # every Q adjustment -> -inf
        m.mlp[-1].bias[-len(ATTRS):] = -50.0
        m.mlp[-1].weight[-len(ATTRS):] = 0.0
    n = 200
    g = torch.Generator().manual_seed(4)
    xyz = torch.rand(n, 3, generator=g) * 2 - 1
    vals = {"feat": torch.randn(n, 50, generator=g), "scaling": torch.rand(n, 6, generator=g) * 0.05,
            "offsets": torch.randn(n, 30, generator=g) * 0.3}
    mask = (torch.rand(n, 10, generator=g) < 0.5).float()
    blobs, vq = m.compress(xyz, vals, mask, return_values=True)
    dec = m.decompress(xyz, blobs, mask)
    on = mask.repeat_interleave(3, dim=1) > 0
    for a in ATTRS:
        assert torch.equal(dec[a.name], vq[a.name])
        want = torch.where(on, vals[a.name], 0) if a.name == "offsets" else vals[a.name]
        assert torch.allclose(vq[a.name], want, atol=1e-5), a.name
    ev, _ = m(xyz, vals, mask, training=False)
    assert torch.allclose(ev["scaling"], vals["scaling"], atol=1e-5)
