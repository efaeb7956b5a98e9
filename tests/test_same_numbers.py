"""The training code's fast paths give the numbers of their reference forms, bit for bit.

A 200-step training (demo preset, one thread: every phase of HAC's schedule and Predict-GS's
stages fall inside it) is run with the product code and with every fast path swapped for its
reference form (``reference_paths``); the two checkpoints must hold identical tensors: the
model, the entropy model, the optimizer's moments and the hooks' state.
"""
import pytest
import torch

from baseline.data.scene import load_scene
from baseline.train.trainer import Trainer
from conftest import demo_cfg
from reference_paths import reference_paths


@pytest.fixture(scope="module")
def scene(scene_maker):
    return load_scene(scene_maker(n_views=12, width=64, height=48, seed=3))


def _tensors(obj, prefix=""):
    """Every tensor of a nested checkpoint dict, by path."""
    if isinstance(obj, torch.Tensor):
        yield prefix, obj
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _tensors(v, f"{prefix}/{k}")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _tensors(v, f"{prefix}/{i}")


def _train(scene, folder, patches):
    torch.manual_seed(0)
    t = Trainer(demo_cfg(200, patches=patches), scene, folder, progress=False)
    t.train()
    return t.state_dict()


@pytest.mark.slow
@pytest.mark.parametrize("patches", [(), ("predict-gs",)], ids=["HAC", "Predict-GS"])
def test_fast_paths_train_the_reference_checkpoint(scene, tmp_path, patches):
    fast = _train(scene, tmp_path / "fast", patches)
    with reference_paths():
        ref = _train(scene, tmp_path / "ref", patches)
    a, b = dict(_tensors(fast)), dict(_tensors(ref))
    assert a.keys() == b.keys()
    assert len(a) > 20
    differ = [k for k in a if not (a[k].dtype == b[k].dtype and a[k].shape == b[k].shape
                                   and torch.equal(a[k], b[k]))]
    assert not differ, differ[:10]


def test_the_allocator_keeps_freed_memory_once_per_process():
    """glibc's allocator is told to keep the blocks a step frees (no numbers change: only
    where memory comes from); where the C library has no mallopt it is a no-op."""
    import ctypes.util

    from baseline.device import keep_freed_memory

    ok = keep_freed_memory()
    if ctypes.util.find_library("c") is None:
        pytest.skip("no C library found")
    assert ok and keep_freed_memory()
