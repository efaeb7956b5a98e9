"""Training, evaluating and coding on a CUDA GPU (skipped where torch sees none).

The CPU suite cannot reach these paths: the gsplat rasterizer, the PyTorch hash-grid path on
CUDA tensors, device placement of everything the trainer, the densifier and the plugin create,
and the hand-over from a GPU-trained run to the CPU codec. On a GPU machine they run with the
rest of the suite (``./run.sh test``); without gsplat the CPU rasterizer renders the CUDA
tensors (moved for each call), so the device logic is still covered.
"""
from __future__ import annotations

import pytest
import torch

from baseline.modelfile import decode_model, encode_model
from baseline.config import ConfigError, build_config, config_hash
from baseline.contracts import feature_cache
from baseline.data.synthetic import make_scene
from baseline.device import DeviceError, resolve_device, uniform
from baseline.eval.evaluate import evaluate
from baseline.pipeline import coded_state
from baseline.run import load_run, train_run
from conftest import demo_cfg

needs_cuda = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")

ITERS = 300


# ------------------------------------------------------------------ device-independent parts
def test_device_setting_is_checked_and_not_hashed():
    a = build_config(["demo"])
    b = build_config(["demo"], ["train.device=cuda"])
    assert a.train.device == "cpu"          # the cpu preset (and demo) pins the CPU
    assert config_hash(a) == config_hash(b)  # where a run executes is not what it computes
    assert build_config([], ["train.device=cuda:1"]).train.device == "cuda:1"
    with pytest.raises(ConfigError, match="train.device"):
        build_config([], ["train.device=tpu"])


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(DeviceError, match="sees no CUDA GPU"):
            resolve_device("cuda")
    with pytest.raises(DeviceError, match="device"):
        resolve_device("tpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error where there is no GPU")
def test_cli_names_a_missing_gpu(tmp_path, capsys):
    from baseline.cli import main

    make_scene(tmp_path / "s", n_views=4, width=16, height=12, seed=0)
    assert main(["train", str(tmp_path / "s"), "--out", str(tmp_path / "r"), "--patch", "demo",
                 "--device", "cuda", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "pgs train: error: device 'cuda'" in err and "train.device=cpu" in err


def test_uniform_on_the_cpu_draws_the_old_stream():
    g1, g2 = torch.Generator().manual_seed(3), torch.Generator().manual_seed(3)
    assert torch.equal(uniform((4, 5), g1, "cpu"), torch.rand((4, 5), generator=g2))


# ------------------------------------------------------------------------------ on a GPU
@pytest.fixture(scope="module")
def scene_dir(scene_maker):
    return scene_maker(n_views=12, width=64, height=48, seed=2)


def _cfg(patches=(), *sets):
    return demo_cfg(ITERS, "train.device=cuda", "train.rasterizer=auto", *sets, patches=patches)


@pytest.fixture(scope="module", params=["baseline", "predict-gs"])
def cuda_run(request, scene_dir, tmp_path_factory):
    if not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    d = tmp_path_factory.mktemp(f"cuda_{request.param}")
    patches = () if request.param == "baseline" else ("predict-gs",)
    res = train_run(str(scene_dir), d / "run", _cfg(patches), progress=False)
    return dict(dir=d, res=res, patches=patches)


@needs_cuda
def test_training_runs_on_the_gpu(cuda_run):
    res = cuda_run["res"]
    assert res["device"].startswith("cuda")
    assert res["iterations"] == ITERS and res["anchors"] > 0
    assert res["test"]["psnr"] > 15.0, res["test"]
    from baseline.render.gsplat_backend import gsplat_available
    assert res["backend"] == ("gsplat" if gsplat_available() else "cpu")


@needs_cuda
def test_gpu_checkpoint_loads_on_either_device(cuda_run):
    run = cuda_run["dir"] / "run"
    tc, scene = load_run(run, device="cpu")
    tg, _ = load_run(run, device="cuda")
    assert tc.phase == tg.phase == "adaptive"
    for k, v in tg.model.per_anchor.items():
        assert v.is_cuda and torch.equal(v.cpu(), tc.model.per_anchor[k]), k
    for (k, v), (_, w) in zip(tg.entropy.state_dict().items(), tc.entropy.state_dict().items()):
        assert torch.equal(v.cpu(), w), k
    # resumed training steps on the GPU (optimizer state and hooks moved with the model)
    tg.step(ITERS)


@needs_cuda
def test_gpu_run_encodes_on_the_cpu_and_decodes_exactly(cuda_run):
    """Train on the GPU, code on the CPU: decoded values are the encoder's bit for bit, and the
    decoded model renders like the pre-encode quantized one, on the GPU and on the CPU."""
    run = cuda_run["dir"] / "run"
    t, scene = load_run(run, device="cpu")
    path = cuda_run["dir"] / "m.pgs"
    st = encode_model(t.cfg, t.model, t.entropy, path, extra_header={"scene": "x"})
    dec = decode_model(path)
    for k, v in st["values"].items():
        assert torch.equal(v, dec.model.fixed_values[k]), k
    cams = scene.test_cameras
    pre = evaluate(t.model, scene, cams, phase="adaptive", entropy=t.entropy, backend="cpu",
                   coded=coded_state(t.model, t.entropy))
    post_cpu = evaluate(dec.model, scene, cams, phase="decoded", backend="cpu")
    assert abs(post_cpu["psnr"] - pre["psnr"]) < 0.01
    dec.model.to("cuda")                 # fixed values (and the SFP's cache) move with it
    assert all(v.is_cuda for v in dec.model.fixed_values.values())
    post_gpu = evaluate(dec.model, scene, cams, phase="decoded", backend="auto")
    assert abs(post_gpu["psnr"] - post_cpu["psnr"]) < 0.05, (post_gpu, post_cpu)
    prov = feature_cache(dec.model)
    if prov is not None:                    # features that depend on positions only (the SFP)
        prov.build_cache(dec.model.xyz)
        assert prov._cache.is_cuda
        cached = evaluate(dec.model, scene, cams, phase="decoded", backend="auto")
        assert abs(cached["psnr"] - post_gpu["psnr"]) < 1e-3


@needs_cuda
def test_baked_decoding_on_the_gpu(cuda_run):
    """A decoded model baked after moving to the GPU, and one baked on the CPU then moved,
    decode the Gaussians of the plain form there, and render the same images."""
    run = cuda_run["dir"] / "run"
    t, scene = load_run(run, device="cpu")
    path = cuda_run["dir"] / "baked.pgs"
    encode_model(t.cfg, t.model, t.entropy, path, extra_header={"scene": "x"})
    from baseline.pipeline import visible_anchors

    for where in ("baked on the gpu", "baked on the cpu, moved"):
        m = decode_model(path).model
        if where.startswith("baked on the cpu"):
            assert m.bake()
            m.to("cuda")
        else:
            m.to("cuda")
            assert m.bake()
        assert m.baked.P.is_cuda and m.baked.gmask.is_cuda
        assert m.bake_if_faster() and m.baked is not None          # on CUDA: baked
        fixed, m.fixed_values = m.fixed_values, None
        assert m.bake_if_faster() is False and m.baked is None      # a training model: never
        m.fixed_values = fixed
        assert m.bake()
        for cam in scene.test_cameras:
            idx = visible_anchors(m, cam)
            with torch.no_grad():
                a = m.decode(cam.center, idx)
                b = m.baked.decode(cam.center, idx)
            assert torch.equal(a.anchor_index, b.anchor_index), where
            assert torch.allclose(a.colors, b.colors, atol=1e-4) and torch.equal(a.means, b.means)
        baked = evaluate(m, scene, scene.test_cameras, phase="decoded", backend="auto")
        m.baked = None
        plain = evaluate(m, scene, scene.test_cameras, phase="decoded", backend="auto")
        assert abs(baked["psnr"] - plain["psnr"]) < 1e-3, (where, baked, plain)
