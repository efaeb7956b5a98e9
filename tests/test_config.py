"""Config merge: defaults, patches in order, --set, errors naming key and source."""
from pathlib import Path

import pytest

from baseline.config import (ConfigError, build_config, config_hash, from_toml, parse_set,
                             to_toml)


def write(tmp_path, name, text):
    p = tmp_path / f"{name}.toml"
    p.write_text(text)
    return str(p)


def test_defaults_are_paper_values():
    cfg = build_config()
    assert cfg.train.iterations == 30000
    assert cfg.model.feat_dim == 50 and cfg.model.n_offsets == 10
    assert cfg.entropy.lmbda == 0.004 and cfg.entropy.grid.log2_table_3d == 13
    assert cfg.entropy.grid.resolutions_2d == [130, 258, 514, 1026]
    assert cfg.lr.offset_init == 0.01 and cfg.lr.mlp_color_final == 5e-5


def test_patches_apply_in_order_then_set(tmp_path):
    a = write(tmp_path, "a", "[train]\niterations = 100\nseed = 3\n")
    b = write(tmp_path, "b", "[train]\niterations = 200\n")
    cfg = build_config([a, b])
    assert cfg.train.iterations == 200 and cfg.train.seed == 3
    cfg = build_config([b, a])
    assert cfg.train.iterations == 100
    cfg = build_config([a, b], ["train.iterations=7", "entropy.grid.auto=true"])
    assert cfg.train.iterations == 7 and cfg.entropy.grid.auto is True
    assert cfg.patches == [a, b]


def test_named_patch_and_include():
    cfg = build_config(["demo"])
    assert cfg.train.rasterizer == "cpu"          # from the included cpu patch
    assert cfg.train.iterations == 1000           # demo overrides cpu
    assert cfg.patches == ["cpu", "grid-auto", "sfp-grid-auto", "demo"]
    assert cfg.entropy.grid.auto and cfg.ext["predict"].grid_auto   # the demo sizes its grids


def test_cpu_preset_scales_milestones():
    cfg = build_config(["cpu"], ["train.iterations=3000"])
    assert cfg.train.at(30000) == 3000
    assert cfg.train.at(10000) == 1000 and cfg.train.at(500) == 50


def archived_hashes(example: str) -> set[str]:
    """The config hashes in the run folder names of an archived comparison's ``runs``: the
    records under ``tests/data/archived/<example>`` (copies of the ones packed in
    ``docs/examples/archive.tar.xz``), else ``docs/examples/<example>``."""
    root = Path(__file__).parent.parent
    runs = root / "tests/data/archived" / example / "runs"
    if not runs.is_dir():
        runs = root / "docs/examples" / example / "runs"
    return {p.name.rsplit("-", 1)[1] for p in runs.iterdir()}


def test_cpu_preset_scales_the_mask_lr_and_the_demo_does_not():
    """The 6k cpu preset trains the masks with lr x 30000 / iterations; its runs get hashes of
    their own (records of the unscaled preset are never reused for it); the 1k demo keeps the
    paper's mask lr, so its hashes are those of the unscaled preset."""
    cpu = build_config(["cpu"], [])
    assert cpu.lr.mask_schedule_scaled
    unscaled = build_config(["cpu"], ["lr.mask_schedule_scaled=false"])
    assert config_hash(cpu) != config_hash(unscaled)
    assert config_hash(cpu) == config_hash(build_config(["cpu", "masks-lr-scaled"], []))
    demo = build_config(["cpu", "demo"], ["train.iterations=6000", "entropy.lmbda=0.004",
                                          "train.positions=float"])
    assert not demo.lr.mask_schedule_scaled
    archived = archived_hashes("demo-6k-s3")
    # HAC's 6k demo record, trained before the fold, at training semantics 2
    assert config_hash(demo, semantics=2) in archived and config_hash(demo) not in archived
    assert build_config(["cpu", "demo", "masks-lr-scaled"], []).lr.mask_schedule_scaled


def test_unknown_key_names_key_and_patch(tmp_path):
    p = write(tmp_path, "bad", "[train]\niteratons = 5\n")
    with pytest.raises(ConfigError) as e:
        build_config([p])
    assert "train.iteratons" in str(e.value) and "bad.toml" in str(e.value)


def test_unknown_section(tmp_path):
    p = write(tmp_path, "bad2", "[trian]\niterations = 5\n")
    with pytest.raises(ConfigError, match="unknown config section 'trian'.*bad2.toml"):
        build_config([p])


def test_type_mismatch_names_key_and_patch(tmp_path):
    p = write(tmp_path, "bad3", '[train]\niterations = "many"\n')
    with pytest.raises(ConfigError, match="'train.iterations' in patch .*bad3.toml.*integer"):
        build_config([p])
    p = write(tmp_path, "bad4", "[entropy.grid]\nresolutions_2d = [1, 2.5]\n")
    with pytest.raises(ConfigError, match=r"resolutions_2d\[1\]"):
        build_config([p])
    with pytest.raises(ConfigError, match="train.seed.*--set"):
        build_config([], ["train.seed=true"])


def test_choice_keys_name_the_choices():
    with pytest.raises(ConfigError, match="train.positions.*coded.*float"):
        build_config([], ["train.positions=floats"])
    assert build_config([], ["train.positions=float"]).train.positions == "float"
    assert build_config([]).train.positions == "coded"


def test_unknown_patch_lists_available():
    with pytest.raises(ConfigError, match="available patches:.*cpu"):
        build_config(["no-such-patch"])


def test_int_accepted_for_float_and_roundtrip(tmp_path):
    cfg = build_config([], ["entropy.lmbda=1", "codec.weight_dtype=float16"])
    assert cfg.entropy.lmbda == 1.0 and isinstance(cfg.entropy.lmbda, float)
    path = tmp_path / "config.toml"
    path.write_text(to_toml(cfg))
    again = from_toml(path)
    assert config_hash(again) == config_hash(cfg)
    assert config_hash(build_config()) != config_hash(cfg)


def test_parse_set_errors():
    with pytest.raises(ConfigError):
        parse_set("novalue")
    with pytest.raises(ConfigError):
        parse_set("iterations=3")
    assert parse_set("a.b.c=x") == {"a": {"b": {"c": "x"}}}


def test_every_shipped_patch_builds_and_changes_something():
    """Each file in patches/ parses, names only known keys, and changes the configuration
    (except `low-rate` and `tandt`, which restate defaults by name: lambda 0.004, and the
    Tanks&Temples voxel 0.01 / growing cells 16)."""
    from baseline.config import default_config, patch_infos, to_dict
    names = sorted(patch_infos())
    assert "masks-x4" in names and "predict-gs" in names
    base = to_dict(default_config(), drop_meta=True)
    for name in names:
        cfg = build_config([name])
        assert (to_dict(cfg, drop_meta=True) == base) == (name in ("low-rate", "tandt")), name
    assert build_config(["masks-x4"]).entropy.mask_lambda == pytest.approx(
        4 * default_config().entropy.mask_lambda)


def test_hash_of_finished_runs_survives_new_options():
    """Options added later (LATER_KEYS) stay out of the hash at their default: the demo-preset
    HAC and Predict-GS runs archived in demo-schedule/1k (tests/data/archived) keep their folder hashes
    under their training semantics (version 1); the option turned on gives a new one. The
    current training semantics gives every config a new hash, so those records are never
    reused as if trained by the current code."""
    from baseline.config import LATER_KEYS, TRAINING_SEMANTICS

    # the demo preset of those runs had the full grid layouts (it sizes them from the anchors now)
    old = ["entropy.lmbda=0.004", "entropy.grid.auto=false", "predict.grid_auto=false",
           "train.positions=float"]
    base = build_config(["cpu", "demo"], old)
    assert ("lr", "mask_schedule_scaled") in LATER_KEYS
    archived = archived_hashes("demo-schedule/1k")
    assert TRAINING_SEMANTICS >= 2 and config_hash(base) not in archived

    def h1(c):                          # the rest of the test: version-1 hashes
        return config_hash(c, semantics=1)

    assert h1(base) in archived
    on = build_config(["cpu", "demo", "masks-lr-scaled"], old)
    assert on.lr.mask_schedule_scaled and h1(on) not in archived
    clamp = build_config(["cpu", "demo"], old + ["densify.clamp_scaling_to_end=true"])
    assert ("densify", "clamp_scaling_to_end") in LATER_KEYS and h1(clamp) not in archived
    ste = build_config(["cpu", "demo", "quant-ste"], old)
    assert ("entropy", "decoder_quant") in LATER_KEYS and ste.entropy.decoder_quant == "ste"
    assert h1(ste) not in archived
    srt = build_config(["cpu", "demo", "positions-sorted"], old)
    assert ("codec", "positions") in LATER_KEYS and srt.codec.positions == "sorted"
    assert h1(srt) not in archived
    cc = build_config(["cpu", "demo", "compact-codec"], old)
    assert ("codec", "masks") in LATER_KEYS and cc.codec.masks == "patterns"
    assert cc.codec.positions == "sorted" and h1(cc) not in archived
    assert ("codec", "grids") in LATER_KEYS and cc.codec.grids == "used"


def test_position_coding_is_validated():
    assert build_config([]).codec.positions == "raw16"      # HAC's layout by default
    with pytest.raises(ConfigError, match="codec.positions"):
        build_config([], ["codec.positions=octree"])
    assert build_config([]).codec.masks == "bernoulli"
    with pytest.raises(ConfigError, match="codec.masks"):
        build_config([], ["codec.masks=rle"])
    assert build_config([]).codec.grids == "all"
    with pytest.raises(ConfigError, match="codec.grids"):
        build_config([], ["codec.grids=some"])


def test_decoder_quant_is_validated():
    with pytest.raises(ConfigError, match="decoder_quant"):
        build_config([], ["entropy.decoder_quant=round"])


@pytest.mark.parametrize("expr,key", [
    ("train.log_every=0", "train.log_every"), ("train.schedule_base=0", "train.schedule_base"),
    ("entropy.mask_threshold=2", "entropy.mask_threshold"), ("entropy.lmbda=nan", "entropy.lmbda"),
    ("entropy.lmbda=-1", "entropy.lmbda"), ("entropy.lmbda=inf", "entropy.lmbda"),
    ("model.n_offsets=100000", "model.n_offsets"), ("model.n_offsets=0", "model.n_offsets"),
    ("entropy.context_hidden=1000000", "entropy.context_hidden"),
    ("entropy.grid.log2_table_3d=30", "entropy.grid.log2_table_3d"),
    ("entropy.grid.resolutions_3d=[1]", "entropy.grid.resolutions_3d"),
    ("entropy.grid.n_features=0", "entropy.grid.n_features"),
    ("predict.residual_dim=100000", "predict.residual_dim"), ("predict.d_s=0", "predict.d_s"),
    ("lr.feature=-0.1", "lr.feature"), ("train.lambda_dssim=2", "train.lambda_dssim"),
    ("data.near=0", "data.near"), ("train.iterations=0", "train.iterations"),
    ("entropy.rate_sample=0", "entropy.rate_sample"),
])
def test_out_of_range_values_are_refused_by_name(expr, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        build_config(["predict-gs"], [expr])


def test_iterations_flag_and_set_agree(tmp_path, capsys):
    from baseline.cli import main

    assert main(["config", "--iterations", "0"]) == 2
    assert "train.iterations" in capsys.readouterr().err
    assert main(["config", "--set", "train.iterations=0"]) == 2
    assert "train.iterations" in capsys.readouterr().err
    assert main(["config", "--iterations", "123"]) == 0
    assert "iterations = 123" in capsys.readouterr().out


def test_truck_hacpp_archive_is_what_its_command_plans_today(tmp_path):
    """docs/RESULTS.md rebuilds the seeded truck comparison of HAC, Predict-GS, HAC++ and
    Predict-GS+HAC++ from the records in docs/examples/truck-r4-cpu-hacpp-s2 with `--report-only`:
    that holds only while the command plans exactly those run folders (same config hashes). A
    change to what a config trains changes its hash, and the archived records must then no
    longer be reported as this code's runs; this test names the change. (They are records of
    training semantics 2, which trained at the float anchor positions: today's command plans
    none of them, the same command at the float positions hashed at version 2 plans them all.)"""
    from baseline.experiment import parse_methods, plan_runs, with_own_lambdas

    common = ["cpu"]
    methods = with_own_lambdas(
        parse_methods(["predict-gs", "hacpp", "predict-gs+hacpp"]),
        [["HAC", "0.008", "0.004", "0.002", "0.001"],
         ["Predict-GS", "0.004", "0.002", "0.001", "0.0005"],
         ["HAC++", "0.008", "0.004", "0.002", "0.001"]], common)
    runs = Path(__file__).parent.parent / "docs/examples/truck-r4-cpu-hacpp-s2/runs"
    archived = {p.name for p in runs.iterdir()}
    today = plan_runs(tmp_path, methods, [0.004, 0.002, 0.001], common,
                      ["data.resolution=4"], [0, 1])
    assert not archived & {s.dir.name for s in today}
    specs = plan_runs(tmp_path, methods, [0.004, 0.002, 0.001], common,
                      ["data.resolution=4", "train.positions=float"], [0, 1])
    planned = {f"{s.dir.name.rsplit('-', 1)[0]}-{config_hash(s.cfg, semantics=2)}" for s in specs}
    # every archived run is planned; the one planned run not archived was never trained
    assert archived <= planned, sorted(archived - planned)
    assert [n.rsplit("-", 1)[0] for n in planned - archived] == ["predict-gs-l0.0005-s1"]


def test_every_shipped_patch_declares_its_kind_and_description():
    """Each shipped patch (the baseline's folder and every plugin's) names one of the kinds and
    says in one line what it does; a method's label is what the reports call it."""
    from baseline.config import PATCH_KINDS, method_specs, patch_infos

    infos = patch_infos()
    assert {i.path.parent.name for i in infos.values()} == {"patches"}
    assert {i.path.parent.parent.name for i in infos.values()} == {"baseline", "predict_plugin"}
    for name, info in infos.items():
        assert info.kind in PATCH_KINDS, (name, info.kind)
        assert info.description and "\n" not in info.description, name
    assert infos["predict-gs"].kind == "method" and infos["cpu"].kind == "preset"
    specs = method_specs()
    assert specs["predict-gs"].label == "Predict-GS" and specs["hacpp"].label == "HAC++"
    assert set(specs["predict-gs"].patches) <= set(infos)
    # the plugin's patches live in its own folder
    assert all(infos[p].path.parent.parent.name == "predict_plugin"
               for p in specs["predict-gs"].patches)


def test_config_list_groups_the_patches_by_kind(capsys):
    from baseline.cli import main
    from baseline.config import PATCH_KINDS, patch_infos

    assert main(["config", "--list"]) == 0
    out = capsys.readouterr().out
    heads = [line.split(" (")[0] for line in out.splitlines() if not line.startswith(" ")]
    assert heads == [k for k in PATCH_KINDS if any(i.kind == k for i in patch_infos().values())]
    for name, info in patch_infos().items():
        line = next(x for x in out.splitlines() if x.split() and x.split()[0] == name)
        assert line.rstrip().endswith(info.description)
    # the patch that follows a kind's header is of that kind
    kind = None
    for line in out.splitlines():
        if not line.startswith(" "):
            kind = line.split(" (")[0]
        else:
            assert patch_infos()[line.split()[0]].kind == kind


def _archived_runs_are_planned(tmp_path, example, methods, lambdas, present=(),
                               resolution=4) -> set:
    """Assert that docs/examples/<example>/runs holds runs (of each method id in ``present``
    among them) and only runs that today's truck command plans (`-r RESOLUTION --patch cpu`, seeds 0
    and 1, same config hashes); returns the planned run folders' names."""
    from baseline.experiment import plan_runs

    runs = Path(__file__).parent.parent / "docs/examples" / example / "runs"
    archived = {p.name for p in runs.iterdir()}
    planned = {s.dir.name for s in plan_runs(tmp_path, methods, lambdas, ["cpu"],
                                             [f"data.resolution={resolution}"], [0, 1])}
    assert archived, example
    for method in present:
        assert any(n.startswith(method + "-") for n in archived), (method, sorted(archived))
    assert archived <= planned, sorted(archived - planned)
    return planned


def test_truck_semantics3_records_are_what_their_command_plans_today(tmp_path):
    """docs/examples/truck-pos holds truck's runs at training semantics 3 (the 16-bit positions),
    archived as the adopted protocol's curves finish: every one must be a run today's command
    plans (same config hash), else a change to what a config trains has orphaned them and they
    must no longer be reported as this code's runs. The command: `pgs compare
    ../shared/data/tandt_truck -r 4 --patch cpu --vs predict-gs --seeds 0 1 --lambda-for HAC
    0.008 0.004 0.002 --lambda-for Predict-GS 0.004 0.002 0.001`."""
    from baseline.experiment import parse_methods, with_own_lambdas

    methods = with_own_lambdas(parse_methods(["predict-gs"]),
                               [["HAC", "0.008", "0.004", "0.002"],
                                ["Predict-GS", "0.004", "0.002", "0.001"]], ["cpu"])
    planned = _archived_runs_are_planned(tmp_path, "truck-pos", methods, [0.004])
    assert len(planned) == 12, planned


def test_truck_r2_records_are_what_their_command_plans_today(tmp_path):
    """docs/examples/truck-r2 holds the `-r 2` pair of HAC and Predict-GS (490 x 272 views, the
    rest of the protocol as truck-pos's): each must be a run that `pgs compare
    ../shared/data/tandt_truck -r 2 --patch cpu --vs predict-gs --seeds 0 1 --lambda 0.008 0.004
    0.002 0.001` plans today (same config hash), and both methods are there."""
    from baseline.experiment import parse_methods

    _archived_runs_are_planned(tmp_path, "truck-r2", parse_methods(["predict-gs"]),
                               [0.008, 0.004, 0.002, 0.001], present=("baseline", "predict-gs"),
                               resolution=2)


@pytest.mark.parametrize("example, methods", [
    ("truck-ste", ["predict-gs+quant-ste", "quant-ste"]),
    ("truck-sfpctx", ["predict-gs+sfp-context"]),
    ("truck-hash", ["predict-gs+quant-ste+hash-rate-hac"]),
    ("truck-mgrdinit", ["predict-gs+quant-ste+mgrd-init-default"]),
    ("truck-fusion", ["predict-gs+quant-ste+fusion-default"]),
    ("truck-fusion-xeon", ["predict-gs+quant-ste+fusion-default"]),
])
def test_truck_lever_records_are_what_their_command_plans_today(tmp_path, example, methods):
    """docs/examples/truck-ste, truck-sfpctx, truck-hash, truck-mgrdinit, truck-fusion and
    truck-fusion-xeon hold levers' runs at training semantics 3, trained by code that trains
    truck-pos's configs as truck-pos's code does: each must be a run that `pgs compare ../shared/data/tandt_truck -r 4
    --patch cpu --vs M [--vs M2] --seeds 0 1 --lambda 0.008 0.004 0.002 0.001` plans today
    (same config hash; HAC+quant-ste's curve starts at 0.008)."""
    from baseline.experiment import parse_methods

    _archived_runs_are_planned(tmp_path, example, parse_methods(methods),
                               [0.008, 0.004, 0.002, 0.001], present=(methods[0],))
