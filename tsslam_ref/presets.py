"""Named settings ("presets"): Co-SLAM's numbers per dataset and our budgets for 2 CPU cores.

Layer 0 (base): plain values, no imports.  Each preset is a list of value layers
``{section: {key: value}}`` applied in order on the defaults of ``config.Config`` (``config.tum()``,
``config.load("tum-cpu")``, ... build them); a key a layer does not name keeps the default or the
value of an earlier layer.  Sources as in config.py: "Co-SLAM" is the official YAML of
github.com/HengyiWang/Co-SLAM at commit 3bb904e, TS-SLAM (paper Sec. IV-A) sets the knot spacing
``spline.dt``, everything else is ours.

* ``tum``, ``scannet``, ``synthetic``, ``replica``: the original numbers.
* ``tum-cpu``, ``synthetic-cpu``: :data:`TWO_CORE_BUDGET` on ``tum`` / ``synthetic``, plus the few
  values in which the two differ.
* ``tiny``: ``synthetic-cpu`` made smaller still, for tests and notebooks.
"""

from typing import Any, Dict, List

Values = Dict[str, Any]
"""One layer of values: ``{"name": str, section: {key: value}}``."""

REPLICA: Values = {
    "name": "replica",
    "data": {"dataset": "replica", "depth_scale": 6553.5, "depth_trunc": 100.0},
    "field": {"log2_hashmap_size": 16, "voxel_sdf": 0.02},
    "render": {"n_samples": 32, "n_range_d": 11, "range_d": 0.1, "far": 5.0, "truncation": 0.1},
    "loss": {"smooth_weight": 1e-6, "smooth_pts": 32, "smooth_vox": 0.1, "smooth_margin": 0.05, "rgb_missing": 0.05},
    "mapping": {"first_iters": 200, "iters": 10},
    "spline": {"dt": 0.3},
    "mesh": {"voxel_final": 0.02},
}
"""Co-SLAM's Replica settings (its ``configs/Replica`` YAML)."""

SYNTHETIC: Values = {
    "name": "synthetic",
    "data": {"dataset": "auto", "depth_trunc": 100.0},
    "field": {"log2_hashmap_size": 16, "voxel_sdf": 0.01},
    "render": {"n_samples": 32, "n_range_d": 11, "range_d": 0.1, "far": 4.0, "truncation": 0.1},
    "loss": {"smooth_weight": 1e-5, "smooth_pts": 32, "smooth_vox": 0.1, "smooth_margin": 0.05, "rgb_missing": 0.05},
    "mapping": {"first_iters": 200, "iters": 10, "lr_embed": 0.001},
    "spline": {"dt": 0.3},
    "mesh": {"voxel_final": 0.02},
}
"""Co-SLAM's NeuralRGBD synthetic settings (its ``configs/Synthetic`` YAML); also our synthetic scenes.
Its scene files set ``far`` per scene (breakfast_room 5 m; complete_kitchen, green_room, whiteroom
8 m; the others 4 m, as here): ``--set render.far=...`` for those."""

SCANNET: Values = {
    "name": "scannet",
    "data": {"dataset": "scannet", "crop_edge": 10, "depth_scale": 1000.0, "depth_trunc": 100.0},
    "field": {"log2_hashmap_size": 16, "voxel_sdf": 0.04},
    "render": {"n_samples": 96, "n_range_d": 21, "range_d": 0.25, "far": 8.0, "truncation": 0.1},
    "loss": {"smooth_weight": 1e-3, "smooth_pts": 64, "smooth_vox": 0.1, "smooth_margin": 0.05, "rgb_missing": 0.0},
    # Co-SLAM optimises a quaternion on ScanNet: one Adam step (about lr per component) turns it
    # about twice as far as our tangent increment, so the rotation rates are doubled to match.
    "tracking": {"lr_rot": 2e-3},
    "mapping": {"first_iters": 500, "iters": 10, "optim_cur": False, "min_pixels_cur": 20, "lr_rot": 2e-3},
    "spline": {"dt": 0.3},
}
"""Co-SLAM's ScanNet settings (its ``configs/ScanNet`` YAML), with two values its scene files
override: the hash table, 2^19 in the base file and 2^12-2^16 per scene (16 as scene0000 and
scene0169; 12 scene0059; 14 scene0106, scene0181, scene0207: ``--set field.log2_hashmap_size=...``),
and ``far``, 5 m in scene0106 and scene0207 (8 m here and in the others)."""

TUM: Values = {
    "name": "tum",
    # Co-SLAM resizes 640x480 to 512x384, then crops 8 px: 496x368.  Cropping first, in native
    # pixels (docs/deviations.md), the same image is 10 px cropped, then resized to 496 wide.
    "data": {"dataset": "tum", "crop_edge": 10, "resize_width": 496, "depth_scale": 5000.0, "depth_trunc": 5.0},
    "field": {"log2_hashmap_size": 16, "voxel_sdf": 0.02},
    "render": {"n_samples": 64, "n_range_d": 21, "range_d": 0.25, "far": 5.0, "truncation": 0.05},
    "loss": {"rgb_weight": 1.0, "depth_weight": 0.1, "sdf_weight": 5000.0, "fs_weight": 10.0,
             "smooth_weight": 1e-8, "smooth_pts": 64, "smooth_vox": 0.04, "smooth_margin": 0.0, "rgb_missing": 1.0},
    "tracking": {"iters": 10, "lr_rot": 1e-2, "lr_trans": 1e-2, "best": False},
    "mapping": {"first_iters": 1000, "iters": 20},
    "spline": {"dt": 0.25},
}
"""Co-SLAM's TUM RGB-D settings (its ``configs/Tum`` YAML); TS-SLAM uses dt = 0.25 s on TUM.  Its
fr2_xyz scene file sets ``far`` 6 m (5 m here and in the others): ``--set render.far=6`` there."""

TWO_CORE_BUDGET: Values = {
    "data": {"resize_width": 160},
    "field": {"log2_hashmap_size": 16, "voxel_sdf": 0.04},
    "render": {"n_samples": 32, "n_range_d": 11},
    # Adam moves each parameter by at most about lr per iteration, so 20 x 1e-3 (Co-SLAM's Replica
    # rate) caps a frame's rotation correction near 1.1 deg per axis: too little for hand-held
    # turns of 4-5 deg per frame (TUM-VI room2); with half of Co-SLAM's rays, 3e-3 also keeps the
    # steps steady (docs/system.md, "Tracking's step-size cap").
    "tracking": {"n_rays": 512, "iters": 20, "lr_rot": 3e-3, "lr_trans": 3e-3, "ignore_edge": 5},
    "mapping": {"first_iters": 200, "first_n_rays": 1024, "n_rays": 1024, "iters": 20},
    "local_ba": {"n_rays": 512},
    "mesh": {"voxel_final": 0.04},
}
"""What ``tum-cpu`` and ``synthetic-cpu`` share for 2 CPU cores (ours): 160 px wide images, a
smaller hash table, fewer rays and samples, 200 first-frame iterations, and twice Co-SLAM's
tracking iterations (20) at a larger rate; ``synthetic-cpu`` also doubles global BA's (20)."""

TUM_CPU: Values = {
    "name": "tum-cpu",
    "data": {"crop_edge": 0},  # in native pixels; the bundled slice is already 160 px wide
    "tracking": {"best": True},
    "loss": {"smooth_pts": 32},
}
"""Where ``tum-cpu`` differs from :data:`TWO_CORE_BUDGET` on :data:`TUM` (same losses, weights and
truncation as ``tum``): tracking keeps its best iteration (Co-SLAM's ``Tum_dagger`` rule, its
"Co-SLAM†"), no crop, and a 32³ smoothness lattice."""

SYNTHETIC_CPU: Values = {
    "name": "synthetic-cpu",
    "mapping": {"lr_embed": 0.01},
}
"""Where ``synthetic-cpu`` differs from :data:`TWO_CORE_BUDGET` on :data:`SYNTHETIC`: the hash
grid's learning rate is 0.01, as in ``tum-cpu`` and Co-SLAM's other datasets (its Synthetic YAML
sets 0.001)."""

TINY: Values = {
    "name": "tiny",
    "field": {"log2_hashmap_size": 14, "voxel_sdf": 0.08},
    "render": {"n_samples": 24, "n_range_d": 8},
    # the tests' and notebooks' figures use learning rates 1e-3
    "tracking": {"n_rays": 128, "iters": 5, "lr_rot": 1e-3, "lr_trans": 1e-3},
    "mapping": {"first_iters": 30, "first_n_rays": 256, "n_rays": 256, "iters": 10},
    "local_ba": {"n_rays": 128, "refine_iters": 5},
    "loss": {"smooth_pts": 16},
    "mesh": {"voxel_final": 0.08},
}
"""Smallest sensible settings for unit tests and notebooks (seconds on 2 cores; ours), on ``synthetic-cpu``."""

PRESET_LAYERS: Dict[str, List[Values]] = {
    "tum": [TUM],
    "scannet": [SCANNET],
    "synthetic": [SYNTHETIC],
    "replica": [REPLICA],
    "tum-cpu": [TUM, TWO_CORE_BUDGET, TUM_CPU],
    "synthetic-cpu": [SYNTHETIC, TWO_CORE_BUDGET, SYNTHETIC_CPU],
    "tiny": [SYNTHETIC, TWO_CORE_BUDGET, SYNTHETIC_CPU, TINY],
}
"""Every preset by name: its value layers, applied in order on the defaults."""
