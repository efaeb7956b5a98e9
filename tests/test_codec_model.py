"""Whole-model codec: train briefly into the adaptive phase, encode, decode, compare exactly."""
import subprocess
import sys

import numpy as np
import pytest
import torch

from baseline.codec.container import BitstreamError, read_container
from baseline.codec.rangecoder import anchor_bounds
from baseline.modelfile import (decode_model, encode_model, file_info, format_info,
                                        format_rate_check, rate_check)
from baseline.data.scene import load_scene
from baseline.eval.evaluate import evaluate
from baseline.hac.entropy import LIKELIHOOD_FLOOR, gaussian_likelihood
from baseline.hac.quant import ste_round
from baseline.pipeline import coded_state
from baseline.train.trainer import Trainer
from conftest import demo_cfg

ITERS = 300


@pytest.fixture(scope="module")
def scene(scene_maker):
    return load_scene(scene_maker(n_views=12, width=64, height=48, seed=2))


def _trained(scene, out, patches=()):
    # The full grid layouts (HAC's): the demo preset sizes them from the anchors, and at 300
    # iterations that entropy model is still far from calibrated (17% of the scalings at the
    # likelihood floor on this scene, under 1% at 1k iterations), which is not what the
    # rate-estimate checks below are about.
    cfg = demo_cfg(ITERS, "entropy.grid.auto=false", "predict.grid_auto=false", patches=patches)
    t = Trainer(cfg, scene, out, progress=False)
    t.train()
    assert t.phase == "adaptive"
    return t


@pytest.fixture(scope="module", params=["baseline", "predict-gs"])
def encoded(request, scene, tmp_path_factory):
    d = tmp_path_factory.mktemp(f"codec_{request.param}")
    patches = () if request.param == "baseline" else ("predict-gs",)
    t = _trained(scene, d / "run", patches)
    pre = evaluate(t.model, scene, scene.test_cameras, phase="adaptive", entropy=t.entropy,
                   backend="cpu", coded=coded_state(t.model, t.entropy), render_dir=d / "pre")
    st = encode_model(t.cfg, t.model, t.entropy, d / "m.pgs", extra_header={"scene": "x"})
    # after encoding the weights are at stored precision: render again (what the file holds)
    pre_rounded = evaluate(t.model, scene, scene.test_cameras, phase="adaptive", entropy=t.entropy,
                           backend="cpu", coded=coded_state(t.model, t.entropy))
    return dict(trainer=t, stats=st, path=d / "m.pgs", pre=pre, pre_rounded=pre_rounded, dir=d)


def test_decoded_attributes_bit_identical(encoded):
    dec = decode_model(encoded["path"])
    vq = encoded["stats"]["values"]
    assert set(vq) == set(dec.model.fixed_values)
    for k, v in vq.items():
        assert torch.equal(v, dec.model.fixed_values[k]), k
    assert torch.equal(dec.model.xyz, encoded["stats"]["xyz_q"])


def test_decoded_render_matches_pre_encode(encoded, scene):
    dec = decode_model(encoded["path"])
    post = evaluate(dec.model, scene, scene.test_cameras, phase="decoded", backend="cpu")
    # the pre-encode render prefilters and decodes what the file holds: the same Gaussians
    assert post["psnr"] == encoded["pre_rounded"]["psnr"]
    assert post["gaussians_mean"] == encoded["pre_rounded"]["gaussians_mean"]
    assert abs(post["psnr"] - encoded["pre"]["psnr"]) < 0.01     # float32 weights: no change


def test_decode_with_other_thread_count(encoded, tmp_path):
    out = tmp_path / "vals.pt"
    code = ("import torch, sys; torch.set_num_threads(2);"
            "from baseline import registry; registry.ensure_loaded();"
            "from baseline.modelfile import decode_model;"
            f"d = decode_model(r'{encoded['path']}');"
            f"torch.save(d.model.fixed_values, r'{out}')")
    torch.set_num_threads(1)
    subprocess.run([sys.executable, "-c", code], check=True)
    other = torch.load(out)
    for k, v in encoded["stats"]["values"].items():
        assert torch.equal(v, other[k]), k


def test_estimated_bits_close_to_written(encoded):
    t = encoded["trainer"]
    idx = encoded["stats"]["index"]
    xyz_q = encoded["stats"]["xyz_q"]
    gm = (torch.sigmoid(t.model.per_anchor["mask"].detach()[idx][..., 0]) > 0.01).float()
    values = t.model.coded_values(idx)
    rows = {r["section"]: r for r in rate_check(t.model, t.entropy, encoded["stats"])}
    secs = encoded["stats"]["sections"]
    grids = {"em.grid"} | ({"provider.grid"} if t.cfg.model.feature_provider == "sfp" else set())
    assert set(rows) == {a.name for a in t.entropy.attrs} | grids
    # Symbols whose likelihood hits the training floor (1e-6, HAC's: 19.9 bits) cost the range
    # coder up to its own floor (2^-24 -> 24-25 bits): measured 4.3-4.8 bits more each on this
    # barely trained model. Allowed for explicitly, and required to be rare.
    with torch.no_grad():
        P = t.entropy.params(xyz_q)
        floor_hits = {}
        for a in t.entropy.attrs:
            mean, scale, q = P[a.name]
            lik = gaussian_likelihood(ste_round(values[a.name], q), mean, scale, q)
            m = t.entropy.value_mask(a, gm, len(idx))
            lik = lik[m] if m is not None else lik
            floor_hits[a.name] = int((lik <= LIKELIHOOD_FLOOR * 1.0001).sum())
            assert floor_hits[a.name] <= 0.02 * lik.numel(), (a.name, floor_hits[a.name], lik.numel())
    for name, r in rows.items():
        written, bits = r["written_bytes"] * 8, r["estimated_bytes"] * 8
        assert r["written_bytes"] == secs[name]
        hits = floor_hits.get(name, 0)     # hash grids: Bernoulli coded, no floor
        assert -(0.05 * written + 64 * 8) <= written - bits <= 0.05 * written + 64 * 8 + 5.5 * hits, \
            (name, bits, written, hits)
    assert "written/est" in format_rate_check(list(rows.values()))


def test_info_groups_sum_to_file_size(encoded):
    info = file_info(encoded["path"])
    assert sum(info["groups"].values()) == info["total_bytes"] == encoded["path"].stat().st_size
    assert "feature" in info["groups"] and "hash" in info["groups"]
    gm = decode_model(encoded["path"]).model.gaussian_mask()
    assert info["masks_on"] == {"on": int((gm > 0).sum()), "total": gm.numel()}
    assert f"Gaussian masks on: {info['masks_on']['on']} of" in format_info(info)
    # what each coded section pays for: values written and bits per value
    header, secs = read_container(encoded["path"].read_bytes())
    on, N, K = info["masks_on"]["on"], header["n_anchors"], header["n_offsets"]
    attrs = {a["section"]: a for a in info["attributes"]}
    assert set(attrs) == {a["name"] for a in header["attrs"]}
    for a in header["attrs"]:
        row = attrs[a["name"]]
        want = on * a["dims"] // K if a["masked"] else N * a["dims"]
        assert row["elements"] == want and row["bytes"] == len(secs[a["name"]])
        assert row["bits_per_element"] == pytest.approx(8 * row["bytes"] / want)
    assert attrs["offsets"]["masked"] and attrs["offsets"]["elements"] == 3 * on
    assert "values coded" in format_info(info) and "(mask-on Gaussians only)" in format_info(info)
    names = [r["section"] for r in info["sections"]]
    if encoded["trainer"].cfg.model.feature_provider == "sfp":
        assert "residual" in names and "provider.grid" in names and "feat" not in names
    else:
        assert "feat" in names and "provider.grid" not in names


def test_compact_codec_decodes_the_same_model_smaller(encoded, scene, tmp_path):
    """codec.positions = "sorted" (the same 16-bit positions coded as a set; every section
    follows their Morton order), codec.masks = "patterns" and codec.grids = "used" (only the
    hash-grid entries the anchors read): the decoded model is the default file's up to the
    anchor order, those sections smaller."""
    import dataclasses

    t = encoded["trainer"]
    cfg = dataclasses.replace(t.cfg, codec=dataclasses.replace(t.cfg.codec, positions="sorted",
                                                               masks="patterns", grids="used"))
    st = encode_model(cfg, t.model, t.entropy, tmp_path / "s.pgs", extra_header={"scene": "x"})
    raw, srt = decode_model(encoded["path"]), decode_model(tmp_path / "s.pgs")
    assert srt.header["position_coding"] == "sorted" and "position_coding" not in raw.header
    assert srt.header["mask_coding"] == "patterns" and "mask_coding" not in raw.header
    info = file_info(tmp_path / "s.pgs")
    assert info["header"]["position_coding"] == "sorted"
    assert info["header"]["mask_coding"] == "patterns"
    assert info["header"]["grid_coding"] == "used" and srt.header["grid_coding"] == "used"
    assert info["masks_on"] == file_info(encoded["path"])["masks_on"]
    assert sum(info["groups"].values()) == info["total_bytes"]
    # the encoder's own values, in its (sorted) order, are what the decoder returns
    assert torch.equal(srt.model.xyz, st["xyz_q"])
    for k, v in st["values"].items():
        assert torch.equal(v, srt.model.fixed_values[k]), k
    # the same anchors as the raw16 file: match them by position (unique here)
    key = lambda x: [tuple(r) for r in x.tolist()]
    pos_raw = {p: i for i, p in enumerate(key(raw.model.xyz))}
    assert len(pos_raw) == raw.model.n_anchors == srt.model.n_anchors
    perm = torch.tensor([pos_raw[p] for p in key(srt.model.xyz)])
    for k, v in raw.model.fixed_values.items():
        assert torch.equal(v[perm], srt.model.fixed_values[k]), k
    assert torch.equal(raw.model.gaussian_mask()[perm], srt.model.gaussian_mask())
    # the SFP (a grid coded with only its used entries) predicts the same features
    if hasattr(srt.model.provider, "predict"):
        with torch.no_grad():
            f_raw = raw.model.provider.predict(raw.model.xyz)
            f_srt = srt.model.provider.predict(srt.model.xyz)
        assert torch.equal(f_raw[perm], f_srt)
    a = evaluate(raw.model, scene, scene.test_cameras, phase="decoded", backend="cpu")
    b = evaluate(srt.model, scene, scene.test_cameras, phase="decoded", backend="cpu")
    assert abs(a["psnr"] - b["psnr"]) < 0.01
    secs_raw = read_container(encoded["path"].read_bytes())[1]
    secs_srt = read_container((tmp_path / "s.pgs").read_bytes())[1]
    assert len(secs_raw["positions"]) == 6 * raw.model.n_anchors
    grids = [n for n in secs_srt if n.endswith("grid")]
    assert "em.grid" in grids
    for name in ["positions", "masks"] + grids:
        # (this barely trained model keeps every mask on: a constant costs both codings ~nothing)
        assert len(secs_srt[name]) < len(secs_raw[name]) or len(secs_srt[name]) <= 64, name
        # damage inside the section is named (the container's CRC catches it first)
        blob = bytearray((tmp_path / "s.pgs").read_bytes())
        blob[bytes(blob).find(secs_srt[name]) + len(secs_srt[name]) // 2] ^= 0x5A
        (tmp_path / "bad.pgs").write_bytes(bytes(blob))
        with pytest.raises(BitstreamError, match=name):
            decode_model(tmp_path / "bad.pgs")


def test_encode_cli_codes_positions_without_touching_the_run(tmp_path, scene):
    """`pgs encode RUN --positions sorted --masks patterns` writes a smaller file of the same run
    and, being a different coding than the run's config, records nothing in its results.json."""
    from baseline.cli import main

    run = tmp_path / "run"
    from baseline.run import train_run

    # a few iterations: the codec, not the model, is under test (an untrained context codes too)
    cfg = demo_cfg(30)

    train_run(str(scene.source_path), run, cfg, progress=False, evaluate_after=False)
    before = (run / "results.json").read_text()
    assert main(["encode", str(run), "-o", str(tmp_path / "s.pgs"), "--positions", "sorted",
                 "--masks", "patterns", "--grids", "used"]) == 0
    assert (run / "results.json").read_text() == before
    assert main(["encode", str(run), "-o", str(tmp_path / "r.pgs")]) == 0
    assert (tmp_path / "s.pgs").stat().st_size < (tmp_path / "r.pgs").stat().st_size


def _sections(path):
    header, secs = read_container(path.read_bytes())
    return header, secs


def test_truncated_and_flipped_files_name_the_section(encoded, tmp_path):
    raw = encoded["path"].read_bytes()
    _, secs = _sections(encoded["path"])
    # truncation at several points
    for cut in (0, 3, 10, len(raw) // 3, len(raw) - 1):
        p = tmp_path / f"t{cut}.pgs"
        p.write_bytes(raw[:cut])
        with pytest.raises(BitstreamError):
            decode_model(p)
    # one flipped byte inside each section: the CRC names it
    offset = len(raw) - sum(len(b) for b in secs.values())
    for name, blob in secs.items():
        if len(blob) == 0:
            continue
        bad = bytearray(raw)
        bad[offset + len(blob) // 2] ^= 0x5A
        p = tmp_path / f"flip_{name}.pgs"
        p.write_bytes(bytes(bad))
        with pytest.raises(BitstreamError, match=name.replace(".", r"\.")):
            decode_model(p)
        offset += len(blob)


def test_quant_cost_all_rounded_is_the_decoded_file(encoded, scene):
    """`pgs quant-cost`: its 'all rounded' row renders what the file decodes to (same PSNR as
    the decoded .pgs), every coded attribute gets a rounded and a noise row, the noise rows
    repeat with the seed, and the model is left as it was."""
    from baseline.eval.quantcost import format_rows, quantization_cost

    t = encoded["trainer"]
    xyz = t.model.xyz.detach().clone()
    scaling = t.model.per_anchor["scaling"].detach().clone()
    rows = quantization_cost(t, scene, scene.test_cameras, seed=1, backend="cpu")
    names = [a.name for a in t.model.coded_attributes()]
    assert [r["variant"] for r in rows] == (["raw"] + [f"{k} rounded" for k in names]
                                           + ["all rounded"] + [f"{k} noise" for k in names])
    dec = decode_model(encoded["path"])
    post = evaluate(dec.model, scene, scene.test_cameras, phase="decoded", backend="cpu")
    by = {r["variant"]: r for r in rows}
    assert abs(by["all rounded"]["psnr"] - post["psnr"]) < 1e-6
    assert torch.equal(t.model.xyz.detach(), xyz) and t.model.fixed_values is None
    assert torch.equal(t.model.per_anchor["scaling"].detach(), scaling)
    again = quantization_cost(t, scene, scene.test_cameras, seed=1, backend="cpu")
    assert [r["psnr"] for r in again] == [r["psnr"] for r in rows]
    assert "all rounded" in format_rows(rows)


def test_quant_cost_ablation_replaces_one_attribute_of_the_decoded_model(encoded, scene):
    """`pgs quant-cost --ablate`: its base row is the decoded model ('all rounded'), each
    attribute gets a context-mean, a zero and a shuffled row, zeroing an attribute costs PSNR,
    the statistics cover exactly the coded values, and the model is left as it was."""
    from baseline.eval.quantcost import format_ablation, quantization_cost, value_ablation

    t = encoded["trainer"]
    xyz = t.model.xyz.detach().clone()
    res = value_ablation(t, scene, scene.test_cameras, seed=1, backend="cpu")
    names = [a.name for a in t.model.coded_attributes()]
    assert [r["variant"] for r in res["rows"]] == (
        ["as coded"] + [f"{k} {v}" for v in ("at context mean", "zero", "shuffled") for k in names])
    base = {r["variant"]: r for r in quantization_cost(t, scene, scene.test_cameras, seed=1,
                                                       backend="cpu")}
    by = {r["variant"]: r for r in res["rows"]}
    assert abs(by["as coded"]["psnr"] - base["all rounded"]["psnr"]) < 1e-9
    assert by["offsets zero"]["psnr"] < by["as coded"]["psnr"] - 0.1
    valid = t.model.anchor_valid()
    hard = (t.model.gaussian_mask().detach() > 0)
    per = 3 * t.model.n_offsets // hard.shape[1]
    n_coded = {"scaling": int(valid.sum()) * 6,
               "offsets": int((hard & valid[:, None]).sum()) * per}
    st = {s["attribute"]: s for s in res["stats"]}
    assert set(st) == set(names)
    for k, n in n_coded.items():
        assert st[k]["coded_values"] == n
    for s in st.values():
        assert s["r2_context_mean"] <= 1.0 and 0.0 <= s["share_at_mean"] <= 1.0
        assert s["rms_steps_from_mean"] >= 0.0 and s["mean_step"] > 0.0 and s["raw_std"] > 0.0
        assert 0.0 <= s["share_within_half_step_of_zero"] <= 1.0
    assert torch.equal(t.model.xyz.detach(), xyz) and t.model.fixed_values is None
    assert "at context mean" in format_ablation(res)


def test_quant_cost_refuses_a_run_that_codes_nothing(scene, tmp_path):
    from baseline.eval.quantcost import quantization_cost

    cfg = demo_cfg(5, patches=["scaffold"])
    t = Trainer(cfg, scene, tmp_path / "r", progress=False)
    t.train()
    with pytest.raises(ValueError, match="adaptive phase"):
        quantization_cost(t, scene)


def test_an_uncoded_anchor_far_outside_moves_nothing(encoded, scene, tmp_path):
    """End to end: an anchor with every mask off is not coded, so moving it far outside the
    other anchors' box must change neither the coded positions nor the decoded render (the
    positions' bounds come from the coded anchors only; taken over all anchors, one stray
    invalid anchor coarsened every position's 16-bit step)."""
    import copy

    t = encoded["trainer"]
    model = copy.deepcopy(t.model)
    i = int(torch.nonzero(model.anchor_valid())[0, 0])
    with torch.no_grad():
        model.per_anchor["mask"][i] = -20.0                      # every Gaussian off: uncoded
    assert not bool(model.anchor_valid()[i])
    far = copy.deepcopy(model)
    with torch.no_grad():
        xyz = far.per_anchor["xyz"]
        xyz[i] = xyz.max(dim=0).values + 50.0 * (xyz.max(dim=0).values - xyz.min(dim=0).values)
    paths = {}
    for name, m in (("near", model), ("far", far)):
        paths[name] = tmp_path / f"{name}.pgs"
        encode_model(t.cfg, m, t.entropy, paths[name], extra_header={"scene": "x"})
    a, b = decode_model(paths["near"]), decode_model(paths["far"])
    assert torch.equal(a.model.xyz, b.model.xyz)
    for k, v in a.model.fixed_values.items():
        assert torch.equal(v, b.model.fixed_values[k]), k
    pre = evaluate(far, scene, scene.test_cameras, phase="adaptive", entropy=t.entropy,
                   backend="cpu", coded=coded_state(far, t.entropy))
    post = evaluate(b.model, scene, scene.test_cameras, phase="decoded", backend="cpu")
    assert abs(post["psnr"] - pre["psnr"]) < 0.01


def test_a_huge_scaling_renders_alike_before_and_after_coding(encoded, scene, tmp_path):
    """An anchor with log-scaling 30: the codec clamps its scaling to mean +- 15000 Q (the mean
    over every coded anchor). The pre-encode evaluation must render what the file holds: the
    clamp's mean over all coded anchors (not the visible ones of a view) and the prefilter on
    the coded scalings and positions (not the raw ones)."""
    import copy

    t = encoded["trainer"]
    model = copy.deepcopy(t.model)
    i = int(torch.nonzero(model.anchor_valid())[0, 0])
    with torch.no_grad():
        model.per_anchor["scaling"][i] = 30.0
    path = tmp_path / "huge.pgs"
    encode_model(t.cfg, model, t.entropy, path, extra_header={"scene": "x"})
    pre = evaluate(model, scene, scene.test_cameras, phase="adaptive", entropy=t.entropy,
                   backend="cpu", coded=coded_state(model, t.entropy))
    post = evaluate(decode_model(path).model, scene, scene.test_cameras, phase="decoded",
                    backend="cpu")
    assert pre["psnr"] == post["psnr"] and pre["gaussians_mean"] == post["gaussians_mean"]


def test_lattice_positions_decode_the_trained_positions(encoded, tmp_path):
    """codec.positions = "lattice": the decoded positions are the trained ones bit for bit (raw16
    and sorted store 16-bit quantized ones), every attribute follows the octree's order, the
    pre-encode evaluation sees the same positions, and pgs info reports bits per anchor."""
    import dataclasses

    t = encoded["trainer"]
    cfg = dataclasses.replace(t.cfg, codec=dataclasses.replace(t.cfg.codec, positions="lattice"))
    st = encode_model(cfg, t.model, t.entropy, tmp_path / "l.pgs", extra_header={"scene": "x"})
    dec = decode_model(tmp_path / "l.pgs")
    assert dec.header["position_coding"] == "lattice"
    assert dec.model.voxel_size == t.voxel_size == t.model.voxel_size
    assert torch.equal(dec.model.xyz, t.model.xyz.detach()[st["index"]])
    assert torch.equal(st["xyz_q"], dec.model.xyz)
    for k, v in st["values"].items():
        assert torch.equal(v, dec.model.fixed_values[k]), k
    cs = coded_state(t.model, t.entropy, "lattice")
    assert torch.equal(cs.xyz, t.model.xyz.detach()[cs.index])
    info = file_info(tmp_path / "l.pgs")
    assert info["header"]["position_coding"] == "lattice"
    assert info["positions"]["bits_per_anchor"] == 8 * st["sections"]["positions"] / st["anchors"]
    assert "bits per anchor" in format_info(info)
    # the same anchors and values as the raw16 file, matched by position
    raw = decode_model(encoded["path"])
    assert raw.model.n_anchors == dec.model.n_anchors
    idx_raw = {int(i): j for j, i in enumerate(encoded["stats"]["index"].tolist())}
    perm = torch.tensor([idx_raw[int(i)] for i in st["index"].tolist()])
    assert torch.equal(raw.model.gaussian_mask()[perm], dec.model.gaussian_mask())


def test_training_drew_the_decoded_positions(encoded, tmp_path):
    """train.positions = "coded" (the default): training drew every coded anchor at the
    position the decoder gives it, bit for bit (HAC's get_anchor), over the box taken when the
    context started, which the encoder stored and a checkpoint keeps."""
    t, st = encoded["trainer"], encoded["stats"]
    box = t.model.position_box
    assert box is not None
    dec = decode_model(encoded["path"])
    assert torch.equal(t.model.positions(st["index"]), dec.model.xyz)
    assert not torch.equal(t.model.xyz.detach()[st["index"]], dec.model.xyz)   # floats differ
    assert torch.equal(coded_state(t.model, t.entropy).xyz, dec.model.xyz)
    t.save_checkpoint(tmp_path / "ck.pt")
    fresh = Trainer(t.cfg, t.scene, tmp_path / "run", progress=False)
    assert fresh.model.position_box is None
    fresh.load_checkpoint(tmp_path / "ck.pt")
    assert all(np.array_equal(a, b) for a, b in zip(fresh.model.position_box, box))


def test_float_positions_train_at_the_stored_floats(scene, tmp_path):
    """train.positions = "float": no box, training draws the stored floats (the encoder then
    takes the coded anchors' box, as before the option existed)."""
    t = Trainer(demo_cfg(30, "train.positions=float", "entropy.context_from=10"), scene,
                tmp_path / "run", progress=False)
    t.train()
    assert t.phase == "adaptive" and t.model.position_box is None
    assert torch.equal(t.model.positions(), t.model.xyz)
    # "coded" draws the 16-bit positions from the first step, over the initial anchors' box
    c = Trainer(demo_cfg(30, "entropy.context_from=10"), scene, tmp_path / "c", progress=False)
    for h in c.hooks:
        h.before_step(1)
    lo, hi = anchor_bounds(c.model.xyz.detach().numpy())
    assert np.array_equal(c.model.position_box[0], lo) and np.array_equal(c.model.position_box[1], hi)
    assert not torch.equal(c.model.positions(), c.model.xyz)


def test_boxed_positions_follow_the_anchors_and_the_box(scene, tmp_path):
    """The 16-bit positions are computed once per set of anchors and box; a new box, an
    in-place write to the anchors or a new anchor tensor (growth, pruning) recomputes them, and
    the rows of a subset are those of the whole, bit for bit."""
    from baseline.codec.rangecoder import box_positions

    t = Trainer(demo_cfg(30), scene, tmp_path / "run", progress=False)
    m = t.model
    lo, hi = anchor_bounds(m.xyz.detach().numpy())
    m.position_box = (lo, hi)
    first = m.positions()
    assert m.positions() is first                                  # reused
    assert torch.equal(first, box_positions(m.xyz.detach(), lo, hi))
    idx = torch.tensor([3, 0, 7])
    assert torch.equal(m.positions(idx), box_positions(m.xyz.detach()[idx], lo, hi))
    wider = (lo - 1.0, hi + 1.0)
    m.position_box = wider                                         # a new box
    assert torch.equal(m.positions(), box_positions(m.xyz.detach(), *wider))
    wider[1][0] += 2.0                                             # the same box, edited
    assert torch.equal(m.positions(), box_positions(m.xyz.detach(), *wider))
    with torch.no_grad():
        m.xyz[0] += 0.25                                           # an in-place write
    assert torch.equal(m.positions(), box_positions(m.xyz.detach(), *wider))
    m.per_anchor["xyz"] = torch.nn.Parameter(m.xyz.detach()[:5].clone(), requires_grad=False)
    assert m.positions().shape == (5, 3)                           # a new anchor tensor
    assert torch.equal(m.positions(), box_positions(m.xyz.detach(), *wider))
    m.position_box = None
    assert m.positions() is m.xyz


def test_quant_cost_keeps_one_file_per_split(encoded, scene, scene_maker, tmp_path):
    """`pgs quant-cost RUN --split train` writes its own file: the test views' figures stay."""
    import json
    import shutil

    from baseline.cli import main
    from baseline.run import write_scene_record

    run = tmp_path / "run"
    shutil.copytree(encoded["dir"] / "run", run)
    folder = scene_maker(n_views=12, width=64, height=48, seed=2)   # the `scene` fixture's
    write_scene_record(run, scene, folder)                          # as `pgs train` does
    assert main(["quant-cost", str(run)]) == 0
    test_json = (run / "quant_cost.json").read_text()
    assert main(["quant-cost", str(run), "--split", "train"]) == 0
    assert (run / "quant_cost.json").read_text() == test_json
    assert json.loads(test_json)["split"] == "test"
    assert json.loads((run / "quant_cost.train.json").read_text())["split"] == "train"
