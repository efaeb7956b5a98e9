"""Baked decoding of decoded models (baseline/scaffold/baked.py): the view-independent part of
every decoder and refiner head computed once must give the Gaussians of AnchorModel.decode."""
import pytest
import torch

from baseline.modelfile import decode_model
from baseline.data.scene import load_scene
from baseline.eval.evaluate import evaluate
from baseline.pipeline import render_view, visible_anchors
from baseline.scaffold.baked import BakedDecoder, BakeHead, _order_heads


@pytest.fixture(scope="module")
def decoded(decoded_files):
    """Decoded baseline and Predict-GS models of one small scene (tests/conftest.py)."""
    return {"scene": load_scene(decoded_files["scene"]),
            "baseline": decoded_files["baseline"] / "model.pgs",
            "predict-gs": decoded_files["predict-gs"] / "model.pgs"}


def _randomize(model, seed):
    """Non-trivial weights everywhere (MGRD's last layers start at zero; a short training
    leaves them small), so that every head and every correction matters."""
    g = torch.Generator().manual_seed(seed)
    mods = [model.decoder] + ([model.refiner] if model.refiner is not None else [])
    with torch.no_grad():
        for mod in mods:
            for p in mod.parameters():
                p.copy_(torch.randn(p.shape, generator=g) * 0.4)


def _assert_same_gaussians(model, cam, tol=1e-4):
    idx = visible_anchors(model, cam)
    with torch.no_grad():
        a = model.decode(cam.center, idx)
        b = model.baked.decode(cam.center, idx)
    assert torch.equal(a.visible, b.visible)
    # only a candidate whose opacity logit is within rounding of 0 may be kept by one form
    # and not the other (the module's documented difference)
    flip = a.selection != b.selection
    if flip.any():
        with torch.no_grad():
            raw_op = model.raw_heads(cam.center, idx).raw_op.reshape(-1)
        assert raw_op[flip].abs().max() < 1e-5, raw_op[flip]
        assert int(flip.sum()) <= max(1, len(a.means) // 1000)
    both = a.selection & b.selection
    ka, kb = both[a.selection], both[b.selection]     # the commonly kept, in each one's order
    assert torch.equal(a.anchor_index[ka], b.anchor_index[kb])
    assert torch.equal(a.means[ka], b.means[kb])    # offsets x scaling: the same arithmetic
    for k in ("quats", "scales", "opacities", "colors"):
        assert torch.allclose(getattr(a, k)[ka], getattr(b, k)[kb], atol=tol, rtol=tol), k
    assert b.opacity_all is None
    return int(both.sum())


@pytest.mark.parametrize("name", ["baseline", "predict-gs"])
def test_baked_decode_matches_decode(decoded, name):
    dec = decode_model(decoded[name])
    m = dec.model
    for seed in (None, 1, 2):
        if seed is not None:
            _randomize(m, seed)
        assert m.bake()
        if name == "predict-gs":
            assert m.refiner is not None and m.refiner.active
            assert m.baked.P.shape[1] == 3 * m.decoder.mlp_cov[0].out_features + 2 * \
                m.refiner.shape_head[0].out_features
        n = sum(_assert_same_gaussians(m, cam) for cam in decoded["scene"].test_cameras)
        assert n > 0


def test_baked_render_and_evaluate(decoded):
    """The decoded phase renders through the bake when there is one; images agree."""
    sc = decoded["scene"]
    m = decode_model(decoded["predict-gs"]).model
    _randomize(m, 3)
    plain = evaluate(m, sc, sc.test_cameras, phase="decoded", backend="cpu")
    assert m.bake()
    baked = evaluate(m, sc, sc.test_cameras, phase="decoded", backend="cpu")
    assert abs(plain["psnr"] - baked["psnr"]) < 1e-3
    cam = sc.test_cameras[0]
    with torch.no_grad():
        r = render_view(m, cam, sc.background.float(), phase="decoded")
        m.baked, keep = None, m.baked
        r0 = render_view(m, cam, sc.background.float(), phase="decoded")
    assert r.gaussians.opacity_all is None and r0.gaussians.opacity_all is not None
    assert (r.render.image - r0.render.image).abs().max() < 1e-4
    m.baked = keep
    with torch.enable_grad():      # with autograd on the bake is not used (it is render-only)
        r1 = render_view(m, cam, sc.background.float(), phase="decoded")
    assert r1.gaussians.opacity_all is not None


def test_bake_without_distance_and_on_a_moved_model(decoded):
    """A decoder that does not read the distance (use_distance False) bakes a zero distance
    row; .to() moves the bake with the model."""
    m = decode_model(decoded["baseline"]).model
    m.decoder.use_distance = False
    with torch.no_grad():       # same heads, the distance column dropped from the first layers
        for head in (m.decoder.mlp_opacity, m.decoder.mlp_cov, m.decoder.mlp_color):
            lin = head[0]
            new = torch.nn.Linear(lin.in_features - 1, lin.out_features)
            new.weight.copy_(lin.weight[:, :-1])
            new.bias.copy_(lin.bias)
            head[0] = new
    _randomize(m, 4)
    assert m.bake()
    assert torch.equal(m.baked.Wv[3], torch.zeros_like(m.baked.Wv[3]))
    for cam in decoded["scene"].test_cameras[:3]:
        _assert_same_gaussians(m, cam)
    m.to(torch.float64)
    assert m.baked.P.dtype == torch.float64 and m.baked.gmask.dtype == torch.bool


def test_bake_refuses_a_training_model_and_skips_an_undeclared_refiner(decoded):
    m = decode_model(decoded["predict-gs"]).model
    fixed, m.fixed_values = m.fixed_values, None
    with pytest.raises(ValueError, match="decoded model"):
        BakedDecoder.from_model(m)
    m.fixed_values = fixed

    class Opaque(torch.nn.Module):      # a refiner that does not declare its heads
        active = True

        def forward(self, idx, values, view_dir, dist):
            return {}

    m.refiner = Opaque()
    assert m.bake() is False and m.baked is None


def test_head_order_makes_every_attribute_contiguous():
    lin = torch.nn.Sequential(torch.nn.Linear(4, 2), torch.nn.ReLU(), torch.nn.Linear(2, 2))
    x = torch.zeros(1, 0)

    def h(*targets):
        return BakeHead(x, lin, True, {t: (0, 1) for t in targets})

    # the baseline's three heads + MGRD's shape (cov) and appearance (opacity, color)
    heads = [h("opacity"), h("cov"), h("color"), h("cov"), h("opacity", "color")]
    order = _order_heads(heads)
    for a in ("opacity", "cov", "color"):
        pos = [i for i, j in enumerate(order) if a in heads[j].targets]
        assert pos[-1] - pos[0] + 1 == len(pos), (a, order)
    # no contiguous order exists: the given one (second layers then span zero rows)
    bad = [h("opacity", "cov"), h("cov", "color"), h("color", "opacity")]
    assert _order_heads(bad) == [0, 1, 2]


def test_bake_with_no_contiguous_order_still_decodes_exactly(decoded):
    """Refiner heads A (opacity, color), B (cov, opacity), C (cov, color) with the decoder's
    three: no order makes every attribute's heads adjacent, so the second layers span rows of
    heads that do not feed them (zero weights); the Gaussians are still the decode's."""
    m = decode_model(decoded["predict-gs"]).model
    ref, K = m.refiner, m.n_offsets
    first = ref.shape_head[0]
    extra = torch.nn.Sequential(torch.nn.Linear(first.in_features, 16), torch.nn.ReLU(),
                                torch.nn.Linear(16, 10 * K))
    ref.add_module("extra_head", extra)
    _randomize(m, 5)
    A, B, C = ref.appearance_head, ref.shape_head, extra

    def forward(idx, values, view_dir, dist):
        x = torch.cat([values["residual"], view_dir, dist], dim=-1)
        a, b, c = A(x).view(-1, K, 4), B(x).view(-1, K, 7), C(x).view(-1, K, 10)
        return {"opacity": a[..., 0] + b[..., 0], "color": a[..., 1:4] + c[..., 7:10],
                "cov": b + c[..., :7]}

    ref.forward = forward
    ref.bake_heads = lambda values: [
        BakeHead(values["residual"], A, True, {"opacity": (0, 1), "color": (1, 4)}),
        BakeHead(values["residual"], B, True, {"cov": (0, 7), "opacity": (0, 1)}),
        BakeHead(values["residual"], C, True, {"cov": (0, 7), "color": (7, 10)})]
    assert m.bake()
    # some second layer spans a head that does not feed it: all-zero rows
    assert any(bool((s.weight == 0).all(dim=1).any()) for s in m.baked.second.values())
    for cam in decoded["scene"].test_cameras[:3]:
        _assert_same_gaussians(m, cam)
    # a target whose channel count is not the attribute's is refused
    ref.bake_heads = lambda values: [BakeHead(values["residual"], C, True, {"cov": (0, 3)})]
    with pytest.raises(ValueError, match="channels"):
        m.bake()


def test_bake_if_faster_bakes_on_cuda_only(decoded):
    """On the CPU the baked form was measured slower, so decoded models are not baked there
    (render and eval paths call bake_if_faster after moving the model)."""
    m = decode_model(decoded["predict-gs"]).model
    assert m.bake()
    assert m.bake_if_faster() is False and not m.xyz.is_cuda
    assert m.baked is None                      # an earlier bake is dropped too
