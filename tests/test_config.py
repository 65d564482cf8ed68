"""Configuration (config.py): presets, overrides, files and the checks on every value.

Oracles: the dataclass fields themselves (every preset must pass the checks it is built from) and
hand-written bad inputs, each of which must fail with a message naming the key, the value and what
was expected.
"""

import copy
import dataclasses
import json
import re

import pytest

from tsslam_ref import config, run


@pytest.mark.parametrize("name", sorted(config.PRESETS))
def test_every_preset_passes_its_own_checks(name):
    cfg = config.load(name)
    assert config.validate(cfg, name) is cfg


@pytest.mark.parametrize("override, message", [
    ("mapping.map_every=0", "mapping.map_every = 0 must be >= 1"),
    ("tracking.iters=ten", "tracking.iters = 'ten' must be an integer"),
    ("tracking.iters=2.5", "tracking.iters = 2.5 must be an integer"),
    ("spline.dt=-0.3", "spline.dt = -0.3 must be in (0, 10]"),
    ("data.fps=1e999", "data.fps = inf must be a finite number"),
    ("tracking.best=1", "tracking.best = 1 must be true or false"),
    ("mapping.kf_pixel_fraction=1.5", "mapping.kf_pixel_fraction = 1.5 must be in (0, 1]"),
    ("dynamics.barrier_limit=1", "dynamics.barrier_limit = 1 must be in (0, 1)"),
    ("spline.convention=cumulative", "spline.convention = 'cumulative' must be one of paper, basalt"),
    ("spline.knots=random", "spline.knots = 'random' must be one of uniform, adaptive"),
    ("spline.dt_min=0", "spline.dt_min = 0 must be in (0, 10]"),
    ("method=orbslam", "method = 'orbslam' must be one of tsslam, coslam"),
    ("local_ba.fit_controls=7", "local_ba.fit_controls = 7 must be <= local_ba.window = 6"),
    ("render.far=0", "render.far = 0 must be > render.near = 0.0"),
])
def test_a_bad_override_names_key_value_and_expectation(override, message):
    with pytest.raises(ValueError) as error:
        config.apply_overrides(config.load("tiny"), [override])
    assert message in str(error.value) and override in str(error.value)


def test_good_overrides_keep_their_types():
    cfg = config.apply_overrides(config.load("tiny"), [
        "spline.dt=0.25", "dynamics.a_max=5", "field.bound=[[0,1],[0,1],[0,1]]", "data.resize_width=null",
        "data.path=2024", "local_ba.use_dynamics=false", "mapping.tsslam_map_every=0"])
    assert cfg.spline.dt == 0.25 and cfg.dynamics.a_max == 5 and cfg.data.resize_width is None
    assert cfg.data.path == "2024"  # a string field keeps the text as typed
    assert cfg.local_ba.use_dynamics is False and cfg.mapping.tsslam_map_every == 0


def test_a_config_file_with_a_bad_value_names_the_file(tmp_path):
    path = tmp_path / "mine.json"
    values = config.to_dict(config.load("tiny"))
    values["mapping"]["keyframe_every"] = 0
    path.write_text(json.dumps(values))
    with pytest.raises(ValueError, match=r"mine\.json: mapping\.keyframe_every = 0 must be >= 1"):
        config.load(str(path))


def test_the_loop_checks_a_config_edited_in_code():
    from tsslam_ref import slam

    cfg = config.load("tiny")
    cfg.local_ba.window = 2  # a notebook edit that bypasses apply_overrides
    with pytest.raises(ValueError, match=r"local_ba\.fit_controls = 3 must be <= local_ba\.window = 2"):
        slam.run_slam([None, None], cfg)


def test_the_command_line_reports_a_bad_value_and_exits_2(capsys, tmp_path):
    code = run.main(["--set", "mapping.map_every=0", "--out", str(tmp_path / "out")])
    assert code == 2
    assert "mapping.map_every = 0 must be >= 1" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def _ranged_fields():
    """(key, comparison, bound) for every field declared with config.ranged, top level and sections."""
    cfg = config.Config()
    found = []
    for item in dataclasses.fields(cfg):
        value = getattr(cfg, item.name)
        if dataclasses.is_dataclass(value):
            found += [(f"{item.name}.{sub.name}", *sub.metadata["range"])
                      for sub in dataclasses.fields(value) if "range" in sub.metadata]
        elif "range" in item.metadata:
            found.append((item.name, *item.metadata["range"]))
    return found


def _outside(comparison, bound):
    """A value just outside the rule (written independently of config._check_range)."""
    if comparison == "in":
        return "none-of-these"
    if comparison in (">", ">="):
        return bound if comparison == ">" else bound - 1
    low, high = bound
    return high + 1 if comparison == "[]" else low  # "(]" and "()" exclude the low end


def test_ranges_live_with_their_fields_and_each_one_is_enforced():
    fields = _ranged_fields()
    cfg = config.Config()
    numeric = [f"{section.name}.{item.name}" for section in dataclasses.fields(cfg)
               if dataclasses.is_dataclass(getattr(cfg, section.name))
               for item in dataclasses.fields(getattr(cfg, section.name))
               if type(getattr(getattr(cfg, section.name), item.name)) in (int, float)]
    unranged = set(numeric) - {key for key, _, _ in fields}
    assert unranged == {"render.far"}, unranged  # render.far: checked against render.near instead
    for key, comparison, bound in fields:
        bad = _outside(comparison, bound)
        with pytest.raises(ValueError, match=re.escape(f"{key} = {bad!r} must be")):
            config.apply_overrides(config.tum_cpu(), [f"{key}={json.dumps(bad)}"])


@pytest.mark.parametrize("values, key", [({"__dict__": 5}, "'__dict__'"), ({"tracking": {"__dict__": 5}}, "'tracking.__dict__'"),
                                         ({"tracking": {"iters": 3, "__class__": 1}}, "'tracking.__class__'")])
def test_a_config_file_names_python_attributes_as_unknown_keys(tmp_path, values, key):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(values))
    with pytest.raises(ValueError, match=re.escape("mine.json: unknown") + ".*" + re.escape(key)):
        config.load(str(path))


def test_a_partial_config_file_starts_from_the_preset_it_names(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps({"name": "tum-cpu", "tracking": {"iters": 10}}))
    expected = config.tum_cpu()
    expected.tracking.iters = 10
    assert config.load(str(path)) == expected
    path.write_text(json.dumps({"tracking": {"iters": 10}}))  # no preset named: the built-in defaults
    assert config.load(str(path)).tracking.n_rays == config.Config().tracking.n_rays
    saved = tmp_path / "saved.json"
    config.save(config.synthetic_cpu(), str(saved))
    assert config.load(str(saved)) == config.synthetic_cpu()
    config.save(config.Config(), str(saved))  # the defaults save as "name": "default" and load back
    assert config.load(str(saved)) == config.Config()
    path.write_text(json.dumps({"name": "tinyy", "tracking": {"iters": 10}}))  # a misspelt preset
    with pytest.raises(ValueError, match=r"mine.json: \"name\": 'tinyy' is no preset.*tiny"):
        config.load(str(path))


def _inclusive_ends(comparison, bound):
    """The values on the allowed side of each closed end of a rule (written independently of
    config._check_range): every choice of "in", the bound of ">=", both ends of "[]", the top of "(]"."""
    if comparison == "in":
        return list(bound)
    if comparison == ">=":
        return [bound]
    if comparison == "[]":
        return list(bound)
    return [bound[1]] if comparison == "(]" else []


def test_every_closed_end_of_a_range_is_accepted():
    """The counterpart of the test above: a value on a closed end (spline.dt = 10 s,
    mapping.kf_pixel_fraction = 1, seed = 2**32 - 1) is allowed and set as given."""
    for key, comparison, bound in _ranged_fields():
        for good in _inclusive_ends(comparison, bound):
            extra = ["local_ba.fit_controls=1"] if key == "local_ba.window" else []
            cfg = config.apply_overrides(config.tum_cpu(), [f"{key}={json.dumps(good)}"] + extra)
            section, _, name = key.rpartition(".")
            assert getattr(getattr(cfg, section) if section else cfg, name) == good, key


def test_the_smallest_map_sizes_the_config_allows_build_a_map():
    """field.n_levels and field.oneblob_bins of 1 passed the config's check, and the run then
    stopped inside the encodings (naming a class, after writing its folder).  Oracle: the field
    itself, built and evaluated at each size's smallest allowed value."""
    import torch

    from tsslam_ref.field import SceneField

    bound = torch.tensor([[-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0]])
    for key, comparison, smallest in _ranged_fields():
        if key.startswith("field.") and comparison == ">=" and isinstance(smallest, int):
            cfg = config.apply_overrides(config.tiny(), [f"{key}={smallest}"])
            rgb, sdf = SceneField(cfg.field, bound)(torch.zeros(4, 3))
            assert rgb.shape == (4, 3) and sdf.shape == (4,), key


def test_the_seed_range_is_the_32_bits_the_docs_state():
    """docs/cli.md: seeds in [0, 2**32 - 1], PyTorch's CPU generator keeps 32 bits."""
    assert config.apply_overrides(config.tum_cpu(), [f"seed={2**32 - 1}"]).seed == 4294967295
    with pytest.raises(ValueError, match=re.escape(f"seed = {2**32} must be")):
        config.apply_overrides(config.tum_cpu(), [f"seed={2**32}"])


@pytest.mark.parametrize("override, key", [("tracking.iters=true", "tracking.iters = True must be an integer"),
                                           ("dynamics.a_max=false", "dynamics.a_max = False must be a finite number")])
def test_a_boolean_is_no_number(override, key):
    """Python's bool is an int (True == 1), so only an explicit check stops `--set tracking.iters=true`
    from running 1 iteration."""
    with pytest.raises(ValueError, match=re.escape(key)):
        config.apply_overrides(config.tum_cpu(), [override])


def test_python_spelled_values_mean_what_they_say():
    """`True`, `False` and `None` as Python writes them (not JSON) set True, False and None."""
    cfg = config.apply_overrides(config.tum_cpu(), ["local_ba.use_dynamics=False", "tracking.best=True",
                                                    "data.resize_width=None", "local_ba.enabled=True"])
    assert cfg.local_ba.use_dynamics is False and cfg.tracking.best is True and cfg.local_ba.enabled is True
    assert cfg.data.resize_width is None
    cfg = config.apply_overrides(config.tum_cpu(), ["local_ba.use_dynamics=True", "tracking.best=False"])
    assert cfg.local_ba.use_dynamics is True and cfg.tracking.best is False


def test_an_override_value_may_hold_an_equals_sign():
    """Only the first '=' separates key and value: a folder named `run=1` stays whole."""
    cfg = config.apply_overrides(config.tum_cpu(), ["data.path=/data/run=1/teddy"])
    assert cfg.data.path == "/data/run=1/teddy"


def test_overrides_leave_the_config_they_start_from_unchanged():
    """apply_overrides returns a copy: a base config reused for several variants (a benchmark's rows)
    keeps its values, sections included."""
    base = config.tum_cpu()
    changed = config.apply_overrides(base, ["tracking.iters=3", "spline.dt=0.1", "seed=7"])
    assert changed.tracking.iters == 3 and changed.spline.dt == 0.1 and changed.seed == 7
    assert base == config.tum_cpu()


def test_the_rules_between_two_values_accept_their_equal_case_and_refuse_a_flat_box():
    """fit_controls may fill the whole window (fit_controls <= window); a box side of zero length
    (min == max) is refused (docs/cli.md: min < max)."""
    cfg = config.apply_overrides(config.tum_cpu(), ["local_ba.window=4", "local_ba.fit_controls=4"])
    assert cfg.local_ba.fit_controls == cfg.local_ba.window == 4
    with pytest.raises(ValueError, match=re.escape("field.bound = [[0, 1], [2, 2], [0, 1]] must be")):
        config.apply_overrides(config.tum_cpu(), ["field.bound=[[0,1],[2,2],[0,1]]"])


DOCUMENTED_PRESET_VALUES = {
    # Co-SLAM's YAML (configs/<Dataset>/<dataset>.yaml and its per-scene files, commit 3bb904e), the
    # paper's knot spacing (Sec. IV-A) and config.py's field docs ("Co-SLAM: ..., TUM ...")
    "tum": {"data.crop_edge": 10, "data.resize_width": 496, "data.depth_scale": 5000.0, "data.depth_trunc": 5.0, "render.far": 5.0,
            "render.n_samples": 64, "render.n_range_d": 21, "render.range_d": 0.25, "render.truncation": 0.05,
            "loss.rgb_weight": 1.0, "loss.sdf_weight": 5000.0, "loss.smooth_weight": 1e-8, "loss.smooth_pts": 64,
            "loss.smooth_vox": 0.04, "loss.smooth_margin": 0.0, "loss.rgb_missing": 1.0, "tracking.lr_rot": 1e-2,
            "tracking.lr_trans": 1e-2, "tracking.best": False, "mapping.first_iters": 1000, "mapping.iters": 20,
            "field.voxel_sdf": 0.02, "mesh.voxel_final": 0.03, "spline.dt": 0.25, "tracking.iters": 10,
            "loss.fs_weight": 10.0},
    "scannet": {"data.crop_edge": 10, "data.depth_scale": 1000.0, "render.far": 8.0, "render.n_samples": 96,
                "render.n_range_d": 21, "render.range_d": 0.25, "render.truncation": 0.1, "loss.smooth_weight": 1e-3,
                "loss.smooth_pts": 64, "loss.rgb_missing": 0.0, "mapping.first_iters": 500, "mapping.optim_cur": False,
                "mapping.min_pixels_cur": 20, "field.voxel_sdf": 0.04, "field.log2_hashmap_size": 16,
                "mesh.voxel_final": 0.03, "spline.dt": 0.3,
                "tracking.iters": 10, "mapping.iters": 10, "loss.fs_weight": 10.0,
                "tracking.lr_rot": 2e-3, "mapping.lr_rot": 2e-3},  # docs/deviations.md: Co-SLAM's quaternion
    "synthetic": {"field.voxel_sdf": 0.01, "render.far": 4.0, "mapping.lr_embed": 0.001, "loss.smooth_weight": 1e-5,
                  "mapping.first_iters": 200, "mesh.voxel_final": 0.02, "spline.dt": 0.3, "mapping.iters": 10,
                  "render.truncation": 0.1, "loss.smooth_pts": 32},
    "replica": {"data.depth_scale": 6553.5, "field.voxel_sdf": 0.02, "render.far": 5.0, "loss.smooth_weight": 1e-6,
                "mesh.voxel_final": 0.02, "spline.dt": 0.3, "render.truncation": 0.1, "mapping.iters": 10,
                "mapping.first_iters": 200, "tracking.best": True},
    # docs/deviations.md ("CPU presets", "TUM crop") and docs/system.md (tracking lr, mesh voxel, rays)
    "tum-cpu": {"data.resize_width": 160, "data.crop_edge": 0, "field.voxel_sdf": 0.04, "tracking.lr_rot": 3e-3,
                "tracking.lr_trans": 3e-3, "tracking.n_rays": 512, "tracking.iters": 20, "mapping.n_rays": 1024,
                "mesh.voxel_final": 0.04, "render.truncation": 0.05, "loss.sdf_weight": 5000.0, "spline.dt": 0.25,
                "tracking.best": True, "mapping.iters": 20, "loss.smooth_pts": 32, "mapping.first_iters": 200},
    "synthetic-cpu": {"data.resize_width": 160, "field.voxel_sdf": 0.04, "tracking.lr_rot": 3e-3,
                      "tracking.lr_trans": 3e-3, "tracking.n_rays": 512, "tracking.iters": 20, "mapping.n_rays": 1024,
                      "mapping.iters": 20, "mapping.lr_embed": 0.01, "mapping.first_iters": 200},
    "tiny": {"tracking.lr_rot": 1e-3, "tracking.lr_trans": 1e-3},
}


# the paper's Sec. IV-A (lambda_1 = lambda_2 = 0.1, bounds 5 and 5) and docs/deviations.md (K = 32 times),
# the same in every preset
PAPER_DYNAMICS = {"dynamics.lambda_acc": 0.1, "dynamics.lambda_ang": 0.1, "dynamics.a_max": 5.0,
                  "dynamics.omegadot_max": 5.0, "dynamics.n_samples": 32, "dynamics.barrier_limit": 0.95}


@pytest.mark.parametrize("name", sorted(DOCUMENTED_PRESET_VALUES))
def test_presets_hold_the_numbers_their_sources_state(name):
    """Oracle: the numbers as written in Co-SLAM's YAML files, the paper and docs/*.md (tables
    above), not presets.py: a preset that drifts from its documented source fails here."""
    cfg = config.load(name)
    for key, expected in {**PAPER_DYNAMICS, **DOCUMENTED_PRESET_VALUES[name]}.items():
        section, field_name = key.split(".")
        assert getattr(getattr(cfg, section), field_name) == expected, (name, key)


def test_assigning_a_misspelt_setting_is_refused_with_the_name_it_meant():
    """A typo would add an attribute nothing reads: tracking would run with the preset's 20 iterations."""
    cfg = config.tiny()
    with pytest.raises(AttributeError, match=r"TrackingConfig has no setting 'itres' \(did you mean 'iters'\?\)"):
        cfg.tracking.itres = 5
    with pytest.raises(AttributeError, match=r"Config has no setting 'zzz'; its settings: name, method"):
        cfg.zzz = 1
    cfg.tracking.iters = 5  # a real setting still assigns
    assert cfg.tracking.iters == 5 and copy.deepcopy(cfg).tracking.iters == 5
    assert dataclasses.replace(cfg.tracking, iters=7).iters == 7


def test_a_key_given_twice_in_a_config_file_is_refused_naming_it(tmp_path):
    """JSON allows a repeated key and Python keeps the last value: {"iters": 5, ..., "iters": 50} ran with 50."""
    path = tmp_path / "twice.json"
    path.write_text('{"name": "tum-cpu", "tracking": {"iters": 5, "n_rays": 256, "iters": 50}}')
    with pytest.raises(ValueError, match=r"twice.json: key 'iters' is given twice in one object \(values 5 and 50\)"):
        config.load(str(path))
    path.write_text('{"name": "tum-cpu", "tracking": {"iters": 5}, "mapping": {"iters": 7}}')  # one per object: fine
    assert config.load(str(path)).tracking.iters == 5 and config.load(str(path)).mapping.iters == 7


def test_override_values_in_python_number_syntax_and_whole_numbers_for_integers():
    """'.5', '5.', '+0.5' and '+3' were refused as "must be a finite number" / "an integer", and
    '1e3' for an integer setting as "1000.0 must be an integer"."""
    cfg = config.apply_overrides(config.tum_cpu(), ["tracking.lr_rot=.5", "tracking.lr_trans=5.", "mapping.lr_embed=+0.5",
                                                    "mapping.iters=+3", "tracking.n_rays=1e2", "seed=2E1"])
    assert (cfg.tracking.lr_rot, cfg.tracking.lr_trans, cfg.mapping.lr_embed) == (0.5, 5.0, 0.5)
    assert (cfg.mapping.iters, cfg.tracking.n_rays, cfg.seed) == (3, 100, 20)
    assert all(type(value) is int for value in (cfg.mapping.iters, cfg.tracking.n_rays, cfg.seed))
    assert config.apply_overrides(config.tum_cpu(), ["data.path=2024"]).data.path == "2024"  # strings stay text
    for bad in ("tracking.lr_rot=nan", "tracking.lr_rot=inf", "tracking.iters=1e400", "tracking.iters=3.5"):
        with pytest.raises(ValueError, match=re.escape(bad.split("=")[0])):
            config.apply_overrides(config.tum_cpu(), [bad])


def test_a_yaml_file_is_named_as_yaml_and_an_old_config_with_voxel_eval_still_loads(tmp_path):
    coslam_yaml = tmp_path / "tum.yaml"
    coslam_yaml.write_text("inherit_from: configs/Tum/tum.yaml\nmapping:\n  bound: [[-3.5, 3], [-3, 3], [-3, 3]]\n")
    with pytest.raises(ValueError, match="YAML .Co-SLAM's config format. is not read"):
        config.load(str(coslam_yaml))
    (tmp_path / "empty.json").write_text("")
    with pytest.raises(ValueError, match="not valid JSON") as refused:
        config.load(str(tmp_path / "empty.json"))
    assert "YAML" not in str(refused.value)
    old = config.to_dict(config.tum_cpu())
    old["mesh"]["voxel_eval"] = 0.05  # what earlier versions saved
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert config.to_dict(config.load(str(tmp_path / "old.json"))) == config.to_dict(config.tum_cpu())
    with pytest.raises(ValueError, match="unknown key 'tracking.iter' .did you mean 'tracking.iters'"):
        config.from_dict({"tracking": {"iter": 3}})


def test_a_full_size_presets_crop_on_small_frames_is_noted():
    """`--config tum` on 160-px frames cropped 12 % of their width (10 px per side, made for 640) and
    could not resize to 496 px, without a word."""
    from types import SimpleNamespace

    from tsslam_ref.datasets.intrinsics import Intrinsics
    from tsslam_ref.run_outputs import data_notes

    def notes(width, height, crop, resize):
        camera = Intrinsics(fx=width, fy=width, cx=width / 2, cy=height / 2, width=width, height=height)
        return data_notes(SimpleNamespace(frames_without_gt=0, colour_without_depth=0, camera_note=None,
                                          native_intrinsics=camera, crop_edge=crop, resize_width=resize))

    tum = config.load("tum")
    small = notes(160, 120, tum.data.crop_edge, tum.data.resize_width)
    assert len(small) == 1 and small[0].startswith("these frames are 160x120 px: data.crop_edge = 10 px per side")
    assert "removes 12 % of their width, and data.resize_width = 496 does not enlarge them" in small[0]
    assert notes(640, 480, tum.data.crop_edge, tum.data.resize_width) == []  # what the preset is made for
    assert notes(160, 120, 0, 160) == []  # tum-cpu, tiny
    assert "does not enlarge" not in notes(160, 120, 10, None)[0]  # scannet's crop, no resize
