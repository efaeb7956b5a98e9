"""Fixtures shared by several test modules."""
import shutil

import pytest
import torch

from baseline.modelfile import encode_model
from baseline.run import write_scene_record
from baseline.config import build_config
from baseline.data.scene import load_scene
from baseline.data.synthetic import make_scene
from baseline.train.trainer import Trainer

# Fixtures that train a model end to end, and modules whose tests train in their bodies: their
# tests carry the `slow` mark (`pytest -m "not slow"` runs the rest).
TRAINING_FIXTURES = {"decoded_files", "trained", "encoded", "local_run", "cuda_run", "hacpp_files"}
TRAINING_MODULES = {"test_compare.py", "test_benchmark.py", "test_train.py"}


def pytest_collection_modifyitems(config, items):
    for item in items:
        if TRAINING_FIXTURES & set(item.fixturenames) or item.path.name in TRAINING_MODULES:
            item.add_marker(pytest.mark.slow)


def demo_cfg(iters: int, *sets: str, patches=()):
    """The demo preset at ``iters`` iterations, one thread, no log lines (tests' training)."""
    return build_config(["demo", *patches], [f"train.iterations={iters}", "train.threads=1",
                                             "train.log_every=1000", *sets])


@pytest.fixture(scope="session")
def scene_maker(tmp_path_factory):
    """``make(n_views, width, height, seed, **kw) -> folder``: a synthetic scene, written once
    per argument set for the whole session (tests must not write into it)."""
    made = {}

    def make(n_views=10, width=48, height=36, seed=0, **kw):
        key = (n_views, width, height, seed, tuple(sorted(kw.items())))
        if key not in made:
            d = tmp_path_factory.mktemp(f"scene_{n_views}v_{width}x{height}_s{seed}")
            make_scene(d / "scene", n_views=n_views, width=width, height=height, seed=seed, **kw)
            made[key] = d / "scene"
        return made[key]

    return make


@pytest.fixture(scope="session")
def small_scene(tmp_path_factory):
    """A small synthetic COLMAP scene (10 views, 48x36), shared by the whole session: tests
    must not write into it."""
    d = tmp_path_factory.mktemp("small_scene")
    make_scene(d / "scene", n_views=10, width=48, height=36, seed=5)
    return d / "scene"


@pytest.fixture(scope="session")
def decoded_files(tmp_path_factory):
    """A baseline and a Predict-GS run folder (``model.pgs``, checkpoint, ``scene.json``) of the
    same small scene (short trainings, the demo preset), plus the baseline's model written
    without its scene and with a copy of it:
    ``{"scene", "baseline", "predict-gs", "noscene", "elsewhere"}`` (run folders / files)."""
    d = tmp_path_factory.mktemp("fpsbench")
    make_scene(d / "scene", n_views=10, width=48, height=36, seed=5)
    scene = load_scene(d / "scene")
    torch.set_num_threads(1)
    out = {"scene": d / "scene"}
    for name, patches in (("baseline", []), ("predict-gs", ["predict-gs"])):
        cfg = build_config(["demo", *patches], ["train.iterations=120", "train.threads=1",
                                                "train.log_every=1000"])
        t = Trainer(cfg, scene, d / name, progress=False)
        t.train()
        encode_model(t.cfg, t.model, t.entropy, d / name / "model.pgs",
                     extra_header={"scene": str(d / "scene")})
        write_scene_record(d / name, scene, d / "scene")   # a run folder as `pgs train` leaves it
        out[name] = d / name
        if name == "baseline":          # the same model: a file without its scene, one elsewhere
            encode_model(t.cfg, t.model, t.entropy, d / "noscene.pgs")
            shutil.copytree(d / "scene", d / "scene-copy")
            encode_model(t.cfg, t.model, t.entropy, d / "elsewhere.pgs",
                         extra_header={"scene": str(d / "scene-copy")})
            out.update(noscene=d / "noscene.pgs", elsewhere=d / "elsewhere.pgs")
    return out
