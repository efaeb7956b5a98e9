"""Binary hash grid against a brute-force per-point implementation of HAC's kernel."""
import math

import numpy as np
import pytest
import torch

from baseline.hac.hashgrid import (FEATURE_BITS, HAC_RESOLUTIONS_2D, HAC_RESOLUTIONS_3D, BinaryHashGrid,
                                   auto_grid_layout, binarize, binary_entropy_bits, level_rows)

torch.set_num_threads(1)
PRIMES = (1, 2654435761, 805459861)


def brute_force(grid: BinaryHashGrid, xyz: np.ndarray) -> np.ndarray:
    """Loop over points, grids, levels and corners in plain Python floats / ints."""
    lo = grid.xyz_min.double().numpy()
    hi = grid.xyz_max.double().numpy()
    tables = {k: binarize(g.params.detach()).double().numpy() for k, g in grid.grids.items()}
    out = []
    for p in xyz:
        u = [(float(p[a]) - lo[a]) / (hi[a] - lo[a]) for a in range(3)]
        row = []
        for name, g in grid.grids.items():
            axes = grid._axes[name]
            c = [u[a] for a in axes]
            D = len(c)
            offset = 0
            for res in g.resolutions:
                rows = int(math.ceil(min(2 ** g.log2_table, res ** D) / 8) * 8)
                outside = any(not (0.0 <= v <= 1.0) for v in c)
                if grid.oob == "all" and any(not (0.0 <= v <= 1.0) for v in u):
                    outside = True
                acc = [0.0] * g.n_features
                wn = 0.0
                if not outside:
                    pos = [v * (res - 2) + 0.5 for v in c]
                    gi = [math.floor(v) for v in pos]
                    fr = [pos[d] - gi[d] for d in range(D)]
                    for corner in range(2 ** D):
                        w = 1.0
                        cc = []
                        for d in range(D):
                            if (corner >> d) & 1:
                                w *= fr[d]
                                cc.append(min(gi[d] + 1, res - 1))
                            else:
                                w *= 1 - fr[d]
                                cc.append(gi[d])
                        if any(x == 0 or x == res - 1 for x in cc):
                            continue
                        if res ** D <= rows:
                            index = sum(cc[d] * res ** d for d in range(D))
                        else:
                            h = 0
                            for d in range(D):
                                h ^= (cc[d] * PRIMES[d]) & 0xFFFFFFFF
                            index = h % rows
                        vals = tables[name][offset + index]
                        for ch in range(g.n_features):
                            acc[ch] += w * vals[ch]
                        wn += w
                if wn == 0:
                    wn = 1e-9
                row += [a / wn for a in acc]
                offset += rows
        out.append(row)
    return np.array(out)


def special_points(lo, hi, rng, n_random=12):
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    pts = [lo, hi, (lo + hi) / 2, np.array([lo[0], hi[1], lo[2]]), np.array([hi[0], lo[1], (lo[2] + hi[2]) / 2])]
    pts += [lo + rng.random(3) * (hi - lo) for _ in range(n_random)]
    # outside in one axis only (planes not using that axis stay valid), and far outside
    pts += [np.array([lo[0] - 0.1, (lo[1] + hi[1]) / 2, (lo[2] + hi[2]) / 2]),
            np.array([(lo[0] + hi[0]) / 2, hi[1] + 1e-3, (lo[2] + hi[2]) / 2]),
            np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, hi[2] * 5]), hi + 10]
    # points whose grid position lands exactly on a lattice node of the first level
    return np.array(pts)


@pytest.fixture(scope="module")
def small_grid():
    torch.manual_seed(0)
    # dense and hashed levels in both grid kinds, including a res^dim equal to the table size
    g = BinaryHashGrid(resolutions_3d=(4, 7, 16, 33), log2_table_3d=9, resolutions_2d=(5, 17, 40),
                       log2_table_2d=8, n_features=3, init_range=1.0)
    g.set_bounds([-1.0, 0.5, 2.0], [3.0, 1.5, 6.0])
    return g


def test_small_grid_matches_brute_force(small_grid):
    rng = np.random.default_rng(1)
    pts = special_points(small_grid.xyz_min.numpy(), small_grid.xyz_max.numpy(), rng, 40)
    # exact lattice nodes: u = (k - 0.5) / (res - 2) for the res=16 level
    nodes = [(k - 0.5) / 14 for k in (1, 3, 8)]
    for a in nodes:
        u = np.array([a, nodes[0], nodes[-1]])
        pts = np.vstack([pts, small_grid.xyz_min.numpy() + u * (small_grid.xyz_max - small_grid.xyz_min).numpy()])
    kinds = {(g.dim, r): r ** g.dim <= t for g in small_grid.grids.values() for r, t in zip(g.resolutions, g.rows)}
    assert any(kinds.values()) and not all(kinds.values())  # both dense and hashed levels tested
    got = small_grid(torch.from_numpy(pts)).detach().numpy()
    ref = brute_force(small_grid, pts)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    # outside in x: the 3D grid, xy and xz planes are zero; the yz plane is not (HAC per-grid rule)
    i = len(special_points(np.zeros(3), np.ones(3), np.random.default_rng(0), 40)) - 4
    o = got[i]
    n3 = small_grid.grids["xyz"].output_dim
    n2 = small_grid.grids["xy"].output_dim
    assert np.all(o[:n3 + 2 * n2] == 0) and np.any(o[n3 + 2 * n2:] != 0)
    assert np.all(got[-len(nodes) - 1] == 0)  # far outside: everything zero


def test_oob_all_mode(small_grid):
    g = BinaryHashGrid(**{k: v for k, v in small_grid.config.items() if k != "oob"}, oob="all")
    g.load_state_dict(small_grid.state_dict())
    pts = special_points(g.xyz_min.numpy(), g.xyz_max.numpy(), np.random.default_rng(2), 5)
    got = g(torch.from_numpy(pts)).detach().numpy()
    np.testing.assert_allclose(got, brute_force(g, pts), rtol=0, atol=1e-12)
    assert np.all(got[-4:] == 0)


def test_default_layout_matches_brute_force():
    torch.manual_seed(3)
    g = BinaryHashGrid()
    g.set_bounds([-2, -2, -1], [2, 3, 1])
    pts = special_points(g.xyz_min.numpy(), g.xyz_max.numpy(), np.random.default_rng(4), 6)
    got = g(torch.from_numpy(pts)).detach().numpy()
    np.testing.assert_allclose(got, brute_force(g, pts), rtol=0, atol=1e-12)
    # the float32 path agrees to float32 precision of the positions
    got32 = g(torch.from_numpy(pts).float()).detach().numpy()
    np.testing.assert_allclose(got32, got, atol=5e-4)  # float32 positions at res 1026


def test_default_layout_sizes():
    g = BinaryHashGrid()
    assert g.output_dim == 12 * 4 + 3 * 4 * 4 == 96
    assert g.n_binary == 1_766_272
    rows3 = [level_rows(r, 3, 13) for r in HAC_RESOLUTIONS_3D]
    rows2 = [level_rows(r, 2, 15) for r in HAC_RESOLUTIONS_2D]
    assert rows3[0] == 5832 and rows3[1:] == [8192] * 11
    assert rows2 == [16904, 32768, 32768, 32768]
    assert 4 * (sum(rows3) + 3 * sum(rows2)) == 1_766_272


def test_init_and_binarization():
    torch.manual_seed(0)
    g = BinaryHashGrid()
    p = torch.cat([x.params.reshape(-1) for x in g.grids.values()])
    assert p.abs().max() <= 1e-4 and 0.45 < (p >= 0).float().mean() < 0.55
    x = torch.tensor([-2.0, -1.0, -1e-9, 0.0, 1e-9, 0.5, 1.0, 3.0])
    assert binarize(x).tolist() == [-1, -1, -1, 1, 1, 1, 1, 1]


def test_ste_gradient_flows_and_stops_outside_unit_interval():
    torch.manual_seed(0)
    g = BinaryHashGrid(resolutions_3d=(8, 12), log2_table_3d=8, resolutions_2d=(10,), log2_table_2d=8)
    with torch.no_grad():
        prm = g.grids["xyz"].params
        prm[::2] = 1.5  # |p| > 1: no gradient
        prm[1::4] = -2.0
    xyz = torch.rand(500, 3)
    w = torch.randn(500, g.output_dim)
    (g(xyz) * w).sum().backward()
    grad = g.grids["xyz"].params.grad
    big = g.grids["xyz"].params.detach().abs() > 1
    assert torch.all(grad[big] == 0)
    assert (grad[~big] != 0).float().mean() > 0.5  # touched rows get gradient
    for name in ("xy", "xz", "yz"):
        assert g.grids[name].params.grad.abs().sum() > 0


def test_hash_bits_formula_and_gradient():
    torch.manual_seed(0)
    g = BinaryHashGrid(resolutions_3d=(8,), log2_table_3d=8, resolutions_2d=(10,), log2_table_2d=8)
    b = torch.cat([binarize(x.params).reshape(-1) for x in g.grids.values()])
    n = b.numel()
    n1 = int((b > 0).sum())
    p = n1 / n
    expect = -n1 * math.log2(p) - (n - n1) * math.log2(1 - p) + 32
    bits = g.hash_bits()
    assert bits.item() == pytest.approx(expect, rel=1e-5)
    bits.backward()
    assert all(x.params.grad is not None and x.params.grad.abs().sum() > 0 for x in g.grids.values())
    # extreme p is clamped
    assert binary_entropy_bits(torch.ones(1000)).item() == pytest.approx(-1000 * math.log2(1 - 1e-6) + 32, rel=1e-4)


def test_exact_path_is_close_and_reproducible():
    torch.manual_seed(5)
    g = BinaryHashGrid(chunk=1000)
    g.set_bounds([-1, -1, -1], [1, 1, 1])
    xyz = torch.rand(3000, 3) * 2.4 - 1.2
    ref = g(xyz.double()).detach()
    fx = g.features_fixed(xyz)
    assert torch.equal(fx, torch.round(fx)) and fx.abs().max() <= 2 ** FEATURE_BITS
    assert (fx * 2.0 ** -FEATURE_BITS - ref).abs().max() < 2e-4
    torch.set_num_threads(2)
    try:
        assert torch.get_num_threads() == 2
        g2 = BinaryHashGrid(chunk=777)
        g2.load_state_dict(g.state_dict())
        assert torch.equal(g2.features_fixed(xyz), fx)
    finally:
        torch.set_num_threads(1)


def test_binary_values_round_trip():
    torch.manual_seed(0)
    g = BinaryHashGrid()
    blob = g.encode_bits()
    assert len(blob) <= 0.2107 * 2 ** 20  # ~1 bit per entry at p ~ 0.5: 0.21 MB
    h = BinaryHashGrid()
    h.decode_bits(blob)
    for k in g.grids:
        assert torch.equal(binarize(g.grids[k].params), h.grids[k].params)
    xyz = torch.rand(200, 3)
    assert torch.equal(g(xyz), h(xyz))
    assert torch.equal(g.features_fixed(xyz), h.features_fixed(xyz))


@pytest.mark.parametrize("oob", ["per_grid", "all"])
def test_used_values_are_all_the_points_read(small_grid, oob):
    """codec.grids = "used": every entry outside ``used_values(points)`` can take any value
    without changing the features at those points, on the float and the exact path; coding only
    the used entries round-trips to the same features."""
    g = BinaryHashGrid(**{k: v for k, v in small_grid.config.items() if k != "oob"}, oob=oob)
    g.load_state_dict(small_grid.state_dict())
    rng = np.random.default_rng(7)
    pts = torch.from_numpy(special_points(g.xyz_min.numpy(), g.xyz_max.numpy(), rng, 30)).float()
    used = g.used_values(pts)
    assert used.dtype == bool and used.size == g.n_binary and 0 < used.sum() < used.size
    ref, ref_exact = g(pts), g.features_fixed(pts)
    flipped = g.binary_values()
    flipped[~used] = 1 - flipped[~used]              # every unused entry flipped
    h = BinaryHashGrid(**g.config)
    h.load_state_dict(g.state_dict())
    h.load_binary_values(flipped)
    assert torch.equal(h(pts), ref) and torch.equal(h.features_fixed(pts), ref_exact)
    # ... and flipping one used entry changes some feature
    one = g.binary_values()
    i = int(np.flatnonzero(used)[len(np.flatnonzero(used)) // 2])
    one[i] = 1 - one[i]
    h.load_binary_values(one)
    assert not torch.equal(h.features_fixed(pts), ref_exact)
    # the codec's round trip with the mask: same features, fewer bytes
    blob = g.encode_bits(used)
    d = BinaryHashGrid(**g.config)
    d.load_state_dict(g.state_dict())
    d.decode_bits(blob, g.used_values(pts))
    assert torch.equal(d(pts), ref) and torch.equal(d.features_fixed(pts), ref_exact)
    assert len(blob) < len(g.encode_bits())
    with pytest.raises(ValueError):
        d.decode_bits(blob, used[:-1])


def test_auto_layout_rule():
    full = auto_grid_layout(500_000)
    assert full == dict(resolutions_3d=HAC_RESOLUTIONS_3D, log2_table_3d=13,
                        resolutions_2d=HAC_RESOLUTIONS_2D, log2_table_2d=15)
    small = auto_grid_layout(1000)
    assert small["log2_table_3d"] == 12 and small["resolutions_3d"] == (18, 24, 33, 44, 59)
    assert small["resolutions_2d"] == (130,)
    tiny = auto_grid_layout(10)
    assert tiny["resolutions_3d"] == (18,) and tiny["log2_table_3d"] == 6
    vox = auto_grid_layout(500_000, bounds=[[0, 0, 0], [1, 1, 1]], voxel_size=0.01)
    # cells finer than the voxel (extent 1 / 0.01 = 100 cells) are dropped; one plane level is kept
    assert vox["resolutions_3d"] == (18, 24, 33, 44, 59, 80) and vox["resolutions_2d"] == (130,)
    g = BinaryHashGrid(**small)
    assert g.n_binary < BinaryHashGrid().n_binary


def test_general_hash_path_matches_brute_force():
    # res * rows >= 2^31 takes the int64 hash path (uint32 XOR hash, then modulo rows)
    torch.manual_seed(6)
    g = BinaryHashGrid(resolutions_3d=(2100,), log2_table_3d=20, resolutions_2d=(5000, 6), log2_table_2d=20,
                       n_features=1, init_range=1.0)
    assert [r[2] for r in g.grids["xyz"]._runs] == ["hash64"]
    assert [r[2] for r in g.grids["xy"]._runs] == ["hash64", "dense"]
    g.set_bounds([0, 0, 0], [1, 1, 1])
    pts = special_points(np.zeros(3), np.ones(3), np.random.default_rng(7), 10)
    got = g(torch.from_numpy(pts)).detach().numpy()
    np.testing.assert_allclose(got, brute_force(g, pts), rtol=0, atol=1e-12)


@pytest.mark.parametrize("layout", ["small", "general"])
def test_numba_kernels_match_torch_path(small_grid, layout):
    """The fused numba float path (training) equals the PyTorch path: features and table grads."""
    from baseline.hac import hashgrid as H

    if layout == "small":
        g = small_grid
    else:  # int64 hash levels (res * rows >= 2^31) beside a dense one
        torch.manual_seed(6)
        g = BinaryHashGrid(resolutions_3d=(2100,), log2_table_3d=20, resolutions_2d=(5000, 6),
                           log2_table_2d=20, n_features=2, init_range=1.0)
    lo, hi = g.xyz_min.numpy(), g.xyz_max.numpy()
    pts = special_points(lo, hi, np.random.default_rng(11), 300)
    pts = np.vstack([pts, [[np.nan, 0.5 * (lo[1] + hi[1]), lo[2]]]])  # NaN: outside
    x = torch.from_numpy(pts).float()
    w = torch.randn(len(pts), g.output_dim, generator=torch.Generator().manual_seed(0))
    res = {}
    old = H.get_grid_backend()
    try:
        for be in ("torch", "numba"):
            H.set_grid_backend(be)
            g.zero_grad(set_to_none=True)
            out = g(x)
            (out * w).sum().backward()
            res[be] = (out.detach().clone(), [p.grad.clone() for p in g.parameters()])
    finally:
        H.set_grid_backend(old)
    np.testing.assert_allclose(res["numba"][0].numpy(), res["torch"][0].numpy(), rtol=0, atol=1e-6)
    n3 = g.grids["xyz"].output_dim  # NaN x: the 3D grid is zero (the yz plane is not)
    assert torch.all(res["numba"][0][-1, :n3] == 0)
    for a, b in zip(res["numba"][1], res["torch"][1]):
        scale = max(float(b.abs().max()), 1.0)
        np.testing.assert_allclose(a.numpy(), b.numpy(), rtol=0, atol=1e-5 * scale)


def test_numba_backend_refuses_position_gradient(small_grid):
    from baseline.hac import hashgrid as H

    x = torch.rand(10, 3, requires_grad=True)
    old = H.get_grid_backend()
    try:
        H.set_grid_backend("auto")  # falls back to PyTorch, which differentiates positions
        small_grid(x).sum().backward()
        assert x.grad is not None
        H.set_grid_backend("numba")
        with pytest.raises(ValueError, match="position"):
            small_grid(x)
    finally:
        H.set_grid_backend(old)
    with pytest.raises(ValueError, match="grid backend"):
        H.set_grid_backend("cuda")


def test_grid_bench_runs_small():
    from baseline.bench.grid import format_grid_bench, run_grid_bench

    rows = run_grid_bench(n_anchors=2000, threads=1, repeats=1)
    assert [r["backend"] for r in rows] == ["torch", "numba"]
    assert all(r["forward_s"] > 0 and r["forward_backward_s"] > 0 for r in rows)
    assert rows[0]["ratio_forward"] == 1.0
    text = format_grid_bench(rows)
    assert "numba" in text and "x f+b" in text


@pytest.mark.parametrize("layout", ["small", "general", "hac"])
def test_exact_kernel_bit_identical_to_torch_path(small_grid, layout):
    """The exact (coding) path's numba kernel gives the PyTorch float64 path's bits, including
    points outside the box (+0 features), NaN, and weights that round half to even."""
    from baseline.hac import hashgrid as H

    if layout == "small":
        g = small_grid
    elif layout == "general":
        torch.manual_seed(6)
        g = BinaryHashGrid(resolutions_3d=(2100,), log2_table_3d=20, resolutions_2d=(5000, 6),
                           log2_table_2d=20, n_features=2, init_range=1.0)
    else:
        torch.manual_seed(7)
        g = BinaryHashGrid(init_range=1.0)
        g.set_bounds([-2.0, -1.0, 0.0], [2.0, 1.0, 3.0])
    lo, hi = g.xyz_min.numpy().astype(float), g.xyz_max.numpy().astype(float)
    rng = np.random.default_rng(3)
    pts = special_points(lo, hi, rng, 500)
    # positions on a 2^-17 lattice of the box: many per-axis weights f * 2^15 are exact ties
    u = np.floor(rng.random((500, 3)) * 2 ** 17) / 2 ** 17
    pts = np.vstack([pts, lo + u * (hi - lo), [[np.nan, lo[1], lo[2]]]])
    x = torch.from_numpy(pts)
    old = H.get_grid_backend()
    try:
        H.set_grid_backend("torch")
        ref = g.features_fixed(x)
        H.set_grid_backend("auto")
        got = g.features_fixed(x)
    finally:
        H.set_grid_backend(old)
    assert torch.equal(got.view(torch.int64), ref.view(torch.int64))   # bits, signs of zero too
    assert (got != 0).any()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fused_table_bits_equal_the_unfused_form_bit_for_bit(seed):
    """hash_bits counts the ones instead of summing the binarized, concatenated tables: its
    value and its gradient on every table entry are the unfused form's, bit for bit (a change
    would change every training's numbers)."""
    from baseline.hac.hashgrid import table_bits

    g = torch.Generator().manual_seed(seed)
    sizes = [(4096, 4), (1000, 2), (37, 4)]
    scale = [1e-4, 0.7, 3.0][seed]                     # HAC's init range, mid-training, saturated
    base = [torch.randn(s, generator=g) * scale for s in sizes]
    if seed == 2:
        base[0][0, :] = torch.tensor([0.0, -0.0, 1.0, -1.0])
        base[0][1, 0] = float("nan")
    w = torch.randn((), generator=g)
    a = [t.clone().requires_grad_(True) for t in base]
    ref = binary_entropy_bits(torch.cat([binarize(t).reshape(-1) for t in a]))
    (ref * w).backward()
    b = [t.clone().requires_grad_(True) for t in base]
    got = table_bits(b)
    (got * w).backward()
    assert torch.equal(got.detach(), ref.detach())
    for x, y in zip(a, b):
        assert torch.equal(x.grad, y.grad)


@pytest.mark.parametrize("layout", ["small", "general", "hac"])
@pytest.mark.parametrize("nparts", [1, 3])
def test_float_kernels_equal_the_point_by_point_loop_bit_for_bit(small_grid, layout, nparts):
    """The level-by-level float kernels give the bits of the point-by-point reference loop
    (``tests/reference_grid_kernels.py``): features, and table gradients for one and several
    point ranges; points outside, on the box faces and NaN included."""
    import reference_grid_kernels as R

    from baseline.hac import _grid_kernels as K
    from baseline.hac.hashgrid import _float_meta, _kernel_meta
    from baseline.render.cpu import configure_numba

    configure_numba()
    if layout == "small":
        g = small_grid
    elif layout == "general":
        torch.manual_seed(6)
        g = BinaryHashGrid(resolutions_3d=(2100,), log2_table_3d=20, resolutions_2d=(5000, 6),
                           log2_table_2d=20, n_features=2, init_range=1.0)
    else:
        torch.manual_seed(3)
        g = BinaryHashGrid(init_range=1.0)
    lo, hi = g.xyz_min.numpy(), g.xyz_max.numpy()
    rng = np.random.default_rng(5)
    pts = special_points(lo, hi, rng, 2000)
    pts = np.vstack([pts, [[np.nan, 0.5 * (lo[1] + hi[1]), lo[2]]]])
    u = g.normalize(torch.from_numpy(pts).float())
    for name, gl in g.grids.items():
        uc = u[:, list(g._axes[name])].contiguous().numpy()
        table = np.where(gl.params.detach().numpy() >= 0, 1.0, -1.0).astype(np.float32)
        want = np.empty((len(uc), gl.output_dim), np.float32)
        got = np.full_like(want, 7.0)
        R.grid_fwd(uc, table, *_kernel_meta(gl), want)
        K.grid_fwd(uc, table, *_float_meta(gl), got, False)
        assert np.array_equal(got.view(np.int32), want.view(np.int32)), name
        got[:] = 7.0                       # the parameters read as their signs
        K.grid_fwd(uc, gl.params.detach().numpy(), *_float_meta(gl), got, True)
        assert np.array_equal(got.view(np.int32), want.view(np.int32)), name
        gout = rng.standard_normal(want.shape).astype(np.float32)
        gw, gg = np.zeros_like(table), np.zeros_like(table)
        R.grid_bwd(uc, gout, *_kernel_meta(gl), gw, nparts)
        K.grid_bwd(uc, gout, *_float_meta(gl), gg, nparts)
        assert np.array_equal(gg.view(np.int32), gw.view(np.int32)), name
        assert np.abs(gw).sum() > 0


def test_level_kinds():
    from baseline.hac._grid_kernels import DENSE, HASH_MOD, HASH_POW2, level_kinds

    assert level_kinds([64, 8192, 24], [0, 1, 1]).tolist() == [DENSE, HASH_POW2, HASH_MOD]
