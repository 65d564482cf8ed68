"""One configuration system for the whole package: nested dataclasses, presets, overrides.

Layer 0 (base): dataclasses only, no torch.

* One dataclass per concept (``DataConfig``, ``FieldConfig``, ``RenderConfig``, ``LossConfig``,
  ``TrackingConfig``, ``MappingConfig``, ``SplineConfig``, ``DynamicsConfig``, ``LocalBAConfig``,
  ``MeshConfig``) gathered in :class:`Config`.
* Every field says its unit and its source: "Co-SLAM" means the official YAML/code at commit
  3bb904e (github.com/HengyiWang/Co-SLAM); "paper" means TS-SLAM (ICRA 2025, arXiv:2410.08780);
  "ours" means a choice of this project (see docs/deviations.md).
* Presets are plain functions registered in :data:`PRESETS`: ``tum``, ``scannet``, ``synthetic``,
  ``replica`` (the original numbers), ``tum-cpu`` and ``synthetic-cpu`` (same structure, fewer rays
  and samples, for 2 CPU cores), and ``tiny`` (tests and notebooks).
* Overrides are strings ``section.key=value`` (``--set tracking.iters=20`` on the command line),
  parsed as JSON where possible, else kept as strings.
* :func:`load` accepts a preset name or a JSON file written by :func:`save` (every run saves its
  resolved config as ``config.json``).
* :func:`validate` checks every value's type against its field and the range the field declares
  (:func:`ranged`, next to the field's default)
  (a file, an override or a notebook's edit with ``mapping.map_every=0`` or ``tracking.iters="ten"``
  fails at once, naming the key, the value and what was expected).
"""

import copy
import dataclasses
import json
import math
import os
import re
from dataclasses import dataclass
from dataclasses import field as _field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple


def ranged(default: Any, comparison: str, bound: Any) -> Any:
    """A dataclass field with its default and the values it allows, kept in the field's metadata.

    ``comparison`` is one of ``">"``, ``">="`` (``bound`` a number), ``"(]"``, ``"()"``, ``"[]"``
    (``bound`` a pair) or ``"in"`` (``bound`` the allowed values); :func:`validate` reads it.
    """
    return _field(default=default, metadata={"range": (comparison, bound)})


@dataclass
class DataConfig:
    """Which frames to read and how to pre-process them."""

    dataset: str = "auto"
    """Layout of ``path``: auto | tum | scannet | neural_rgbd | replica | folder (ours)."""
    path: str = ""
    """Dataset folder; empty means the bundled default sequence (ours)."""
    resize_width: Optional[int] = ranged(None, ">=", 8)
    """Resize colour and depth to this width in pixels (aspect kept, intrinsics scaled exactly);
    None keeps the native size (ours)."""
    crop_edge: int = ranged(0, ">=", 0)
    """Pixels cropped from every side before resizing (Co-SLAM ``crop_edge``: ScanNet 10, TUM 8)."""
    depth_scale: Optional[float] = ranged(None, ">", 0)
    """PNG value per metre; None uses the dataset's standard (TUM 5000, ScanNet 1000, ...)."""
    depth_trunc: float = ranged(100.0, ">", 0)
    """Depth beyond this (m) is invalid for colour/depth losses (Co-SLAM ``cam.depth_trunc``: TUM 5)."""
    fps: float = ranged(30.0, ">", 0)
    """Frame rate assumed where a dataset has no timestamps (paper Sec. IV-A: 30 FPS)."""
    frame_start: int = ranged(0, ">=", 0)
    """First frame index used (ours)."""
    frame_stop: Optional[int] = None
    """One past the last frame index used; None = all (ours)."""
    frame_step: int = ranged(1, ">=", 1)
    """Use every n-th frame (ours)."""


@dataclass
class FieldConfig:
    """Co-SLAM joint encoding: OneBlob + multi-resolution hash grid + two tiny MLPs (Sec. III-A)."""

    bound: Optional[List[List[float]]] = None
    """Scene box [[xmin,xmax],[ymin,ymax],[zmin,zmax]] in metres; None = estimated from the first
    frames' depth (ours; Co-SLAM needs it in every scene YAML)."""
    bound_margin: float = ranged(1.0, ">=", 0)
    """Margin (m) added on every side when the bound is estimated from frame 0's depth (ours: later
    frames see beyond frame 0, so the margin is generous)."""
    n_levels: int = ranged(16, ">=", 1)
    """Hash-grid levels (Co-SLAM, fixed in code)."""
    n_features_per_level: int = ranged(2, ">=", 1)
    """Features per level (Co-SLAM, fixed in code)."""
    base_resolution: int = ranged(16, ">=", 2)
    """Coarsest grid resolution (Co-SLAM, fixed in code)."""
    log2_hashmap_size: int = ranged(16, ">=", 4)
    """log2 of the per-level table size T (Co-SLAM ``grid.hash_size``)."""
    voxel_sdf: float = ranged(0.02, ">", 0)
    """Finest cell size in metres; finest resolution = max box side / voxel_sdf (Co-SLAM)."""
    oneblob_bins: int = ranged(16, ">=", 1)
    """OneBlob bins per axis (Co-SLAM ``pos.n_bins``)."""
    geo_feat_dim: int = ranged(15, ">=", 1)
    """Geometric feature passed from the SDF head to the colour head (Co-SLAM)."""
    hidden_dim: int = ranged(32, ">=", 1)
    """Hidden width of the geometry MLP (Co-SLAM)."""
    hidden_dim_color: int = ranged(32, ">=", 1)
    """Hidden width of the colour MLP (Co-SLAM)."""
    fast_gather: bool = True
    """Use the fused corner lookup with its hand-written backward (``field._TrilinearLookup``, see
    the speed table of docs/map.md); False uses the plain reference path."""
    compiled_kernel: bool = True
    """On the CPU, let the fast path use the compiled hash-grid kernel (``hash_kernel.py``, built
    with the local C++ compiler on first use; falls back to the PyTorch fast path with a warning
    when it cannot be built).  Results agree to rounding, not bit for bit (ours)."""


@dataclass
class RenderConfig:
    """Ray sampling and SDF volume rendering (Sec. III-A, Eq. 3; Co-SLAM ``render_rays``)."""

    n_samples: int = ranged(32, ">=", 1)
    """Uniform samples in [near, far] per ray (Co-SLAM ``n_samples_d``)."""
    n_range_d: int = ranged(11, ">=", 0)
    """Depth-guided samples in [D - range_d, D + range_d] (Co-SLAM)."""
    range_d: float = ranged(0.1, ">=", 0)
    """Half-width (m) of the depth-guided interval (Co-SLAM)."""
    near: float = ranged(0.0, ">=", 0)
    """Near plane (m) (Co-SLAM)."""
    far: float = 5.0
    """Far plane (m) (Co-SLAM ``cam.far``)."""
    truncation: float = ranged(0.1, ">", 0)
    """tr: SDF truncation (m) (Co-SLAM ``training.trunc``: 0.10, TUM 0.05)."""
    perturb: bool = True
    """Stratified jitter of the sorted samples (Co-SLAM ``perturb: 1``)."""
    chunk: int = ranged(4096, ">=", 1)
    """Rays per chunk for full-image rendering (ours)."""


@dataclass
class LossConfig:
    """Weights of the five reconstruction losses (Sec. III-A, Eq. 4; Co-SLAM section 3.4)."""

    rgb_weight: float = ranged(5.0, ">=", 0)
    depth_weight: float = ranged(0.1, ">=", 0)
    sdf_weight: float = ranged(1000.0, ">=", 0)
    fs_weight: float = ranged(10.0, ">=", 0)
    smooth_weight: float = ranged(1e-5, ">=", 0)
    """Feature total-variation weight, global BA only (Co-SLAM)."""
    smooth_pts: int = ranged(32, ">=", 2)
    """Lattice points per axis for the smoothness term (Co-SLAM)."""
    smooth_vox: float = ranged(0.1, ">", 0)
    """Lattice spacing (m) (Co-SLAM)."""
    smooth_margin: float = 0.05
    """Margin (m) from the box when placing the lattice (Co-SLAM)."""
    rgb_missing: float = ranged(0.05, ">=", 0)
    """Colour-loss factor for rays without valid depth (Co-SLAM; effective weight is its square)."""


@dataclass
class TrackingConfig:
    """Per-frame pose optimisation with the map frozen (Sec. III-D, Tracking Thread)."""

    iters: int = ranged(10, ">=", 1)
    """Adam iterations per frame (Co-SLAM ``tracking.iter``)."""
    n_rays: int = ranged(1024, ">=", 1)
    """Pixels sampled per frame, reused for all iterations (Co-SLAM ``tracking.sample``)."""
    lr_rot: float = ranged(1e-3, ">", 0)
    """Learning rate of the rotation increment (Co-SLAM: 1e-3, TUM 1e-2)."""
    lr_trans: float = ranged(1e-3, ">", 0)
    """Learning rate of the translation (Co-SLAM: 1e-3, TUM 1e-2)."""
    ignore_edge: int = ranged(20, ">=", 0)
    """Border (px of the processed image) excluded from sampling (Co-SLAM ``ignore_edge_W/H``)."""
    best: bool = True
    """Keep the lowest-loss pose (Co-SLAM ``tracking.best``)."""
    const_speed: bool = True
    """Constant-velocity initialisation (Co-SLAM ``const_speed``)."""
    max_loss_ratio: float = ranged(50.0, ">", 1)
    """The run stops with a clear message when a frame's best tracking loss exceeds this multiple
    of the median over the first tracked frames (ours: the 'w/o LBA' failure of paper Table V)."""


@dataclass
class MappingConfig:
    """First-frame mapping, keyframes and global BA (Co-SLAM section 5; Sec. III-D Global BA)."""

    first_iters: int = ranged(200, ">=", 0)
    """Map iterations on frame 0 with its pose fixed (Co-SLAM: 200, ScanNet 500, TUM 1000)."""
    first_n_rays: int = ranged(2048, ">=", 1)
    """Rays per first-frame iteration (Co-SLAM ``mapping.sample``)."""
    iters: int = ranged(10, ">=", 0)
    """Global BA iterations (Co-SLAM ``mapping.iters``: 10, TUM 20)."""
    n_rays: int = ranged(2048, ">=", 1)
    """Keyframe rays per BA iteration (Co-SLAM ``mapping.sample``)."""
    min_pixels_cur: int = ranged(100, ">=", 0)
    """Minimum current-frame rays per BA iteration (Co-SLAM)."""
    keyframe_every: int = ranged(5, ">=", 1)
    """Every n-th frame becomes a keyframe (Co-SLAM; paper Sec. III-D)."""
    map_every: int = ranged(5, ">=", 1)
    """Global BA every n-th frame for the discrete-pose baseline (Co-SLAM)."""
    tsslam_map_every: int = ranged(5, ">=", 0)
    """TS-SLAM (ours): every n-th frame on which no spline interval completes, Co-SLAM's global BA
    on what the spline does not reach yet (the map, the newer keyframes and the current frame; the
    spline and the keyframes it reaches are held), so that the map takes in new views as often as
    Co-SLAM's does.  0 gives the paper's schedule, mapping only once per interval dt, which loses
    the camera on walking-speed motion (docs/system.md, "Walking-speed motion")."""
    kf_pixel_fraction: float = ranged(0.05, "(]", (0, 1))
    """Share of each keyframe's pixels stored (Co-SLAM ``n_pixels``)."""
    lr_embed: float = ranged(0.01, ">", 0)
    """Hash-grid learning rate (Co-SLAM; Synthetic 0.001)."""
    lr_decoder: float = ranged(0.01, ">", 0)
    """MLP learning rate (Co-SLAM)."""
    lr_rot: float = ranged(1e-3, ">", 0)
    """BA rotation learning rate (Co-SLAM)."""
    lr_trans: float = ranged(1e-3, ">", 0)
    """BA translation learning rate (Co-SLAM)."""
    optim_cur: bool = True
    """Optimise the current frame's pose in BA (Co-SLAM: False for ScanNet)."""
    pose_accum_step: int = ranged(5, ">=", 1)
    """Pose optimiser steps every n BA iterations with accumulated gradients (Co-SLAM)."""


@dataclass
class SplineConfig:
    """Uniform cubic B-spline trajectory (Sec. III-B)."""

    dt: float = ranged(0.3, "(]", (0, 10))
    """Knot spacing Delta t in seconds (paper: 0.30 ScanNet/synthetic, 0.25 TUM); at most 10 s: the
    knot times are float64 seconds of dataset time (about 1.3e9 s for TUM), and a spacing of
    hours would leave a hand-held camera's motion unmodelled while the basis coordinate
    (t - t0) / dt loses precision (at 1e6 s positions fall onto a 1/64 m grid)."""
    convention: str = ranged("paper", "in", ('paper', 'basalt'))
    """Index convention: 'paper' (segment [t_i, t_i+1) uses points i-2..i+1) or 'basalt' (i..i+3)."""


@dataclass
class DynamicsConfig:
    """Dynamics regulariser L_DR (Sec. III-C, Eq. 10)."""

    lambda_acc: float = ranged(0.1, ">=", 0)
    """lambda_1, weight of the linear-acceleration barrier (paper)."""
    lambda_ang: float = ranged(0.1, ">=", 0)
    """lambda_2, weight of the angular-acceleration barrier (paper)."""
    a_max: float = ranged(5.0, ">", 0)
    """||a||_max in m/s^2 (paper)."""
    omegadot_max: float = ranged(5.0, ">", 0)
    """||omega_dot||_max in rad/s^2 (paper)."""
    n_samples: int = ranged(32, ">=", 1)
    """K: times sampled uniformly in the window (ours; the paper does not state K)."""
    barrier_limit: float = ranged(0.95, "()", (0, 1))
    """Ratio ||a||/a_max beyond which the log barrier is continued by its second-order
    Taylor expansion (ours, see dynamics.py)."""


@dataclass
class LocalBAConfig:
    """Sliding-window local BA over spline control points (Sec. III-D, Fig. 4)."""

    enabled: bool = True
    """False gives the 'w/o LBA' ablation (paper Table V)."""
    window: int = ranged(6, ">=", 1)
    """M: control points in the sliding window (ours; the paper does not state M)."""
    fit_iters: int = ranged(50, ">=", 0)
    """Curve-approximation (Levenberg-Marquardt) iterations for a new control point (ours)."""
    fit_controls: int = ranged(3, ">=", 1)
    """Newest control points fitted in the curve approximation, over the poses of as many
    intervals (ours; the paper fits only the new one, which is unstable, see local_ba.py)."""
    refine_iters: int = ranged(10, ">=", 0)
    """Control-point refinement iterations with the map frozen (ours)."""
    joint_iters: int = ranged(0, ">=", 0)
    """Iterations of local BA's last stage: the window's control points jointly with the map on the
    window's keyframes (paper Sec. III-D, which gives no number).  Off by default (ours; it raised
    ATE, docs/system.md "TS-SLAM's ATE on clean synthetic data"); ``local_ba.joint_iters=10`` runs it."""
    n_rays: int = ranged(1024, ">=", 1)
    """Rays per refinement/joint iteration (ours)."""
    lr_rot: float = ranged(2e-4, ">", 0)
    """Control-rotation learning rate (ours).  Adam moves a parameter by about its learning rate
    per step whatever the gradient, and the newest control points are seen by few frames, so the
    rate is kept below Co-SLAM's pose rate (measurements: docs/system.md, deviations table)."""
    lr_trans: float = ranged(2e-4, ">", 0)
    """Control-translation learning rate (ours), see ``lr_rot``."""
    use_spline: bool = True
    """False gives the 'w/o B-S.' ablation: local BA on discrete per-frame poses (paper Table V)."""
    use_dynamics: bool = True
    """False gives the 'w/o DR' ablation (paper Table V)."""
    max_deviation: float = ranged(0.3, ">", 0)
    """The run stops with a clear message when the spline is farther than this (m) from the
    tracked poses of the newest interval (ours: how the 'w/o LBA' failure shows)."""


@dataclass
class MeshConfig:
    """Marching-cubes meshes (Co-SLAM section 6.1)."""

    voxel_eval: float = ranged(0.05, ">", 0)
    """Voxel size (m) of intermediate meshes (Co-SLAM)."""
    voxel_final: float = ranged(0.03, ">", 0)
    """Voxel size (m) of the final mesh (Co-SLAM: 0.02 Replica/Synthetic, 0.03 ScanNet/TUM)."""
    sdf_cutoff: float = ranged(3.0, ">", 0)
    """Skip cells whose corners all have |normalised SDF| >= this (Co-SLAM NumpyMarchingCubes)."""


@dataclass
class Config:
    """Everything a run needs.  Saved as ``config.json`` beside every run's outputs."""

    name: str = "default"
    """Preset name this config started from."""
    method: str = ranged("tsslam", "in", ('tsslam', 'coslam'))
    """tsslam (B-spline trajectory) or coslam (one pose per frame, the baseline)."""
    seed: int = ranged(0, "[]", (0, 2**63 - 1))
    """Seed for every random draw (torch, numpy)."""
    device: str = "auto"
    """cpu | cuda | auto."""
    dtype: str = ranged("float32", "in", ('float32', 'float64'))
    """Map and rendering precision."""
    parallel: bool = False
    """Track and map in two threads (parallel.py; not deterministic).  False: the sequential,
    deterministic loop."""
    data: DataConfig = _field(default_factory=DataConfig)
    field: FieldConfig = _field(default_factory=FieldConfig)
    render: RenderConfig = _field(default_factory=RenderConfig)
    loss: LossConfig = _field(default_factory=LossConfig)
    tracking: TrackingConfig = _field(default_factory=TrackingConfig)
    mapping: MappingConfig = _field(default_factory=MappingConfig)
    spline: SplineConfig = _field(default_factory=SplineConfig)
    dynamics: DynamicsConfig = _field(default_factory=DynamicsConfig)
    local_ba: LocalBAConfig = _field(default_factory=LocalBAConfig)
    mesh: MeshConfig = _field(default_factory=MeshConfig)


# --------------------------------------------------------------------------------------------
# Presets (plain functions).  The first four hold the original numbers.


def replica() -> Config:
    """Co-SLAM's Replica settings (its ``configs/Replica`` YAML)."""
    cfg = Config(name="replica")
    cfg.data = DataConfig(dataset="replica", depth_scale=6553.5, depth_trunc=100.0)
    cfg.field = FieldConfig(log2_hashmap_size=16, voxel_sdf=0.02)
    cfg.render = RenderConfig(n_samples=32, n_range_d=11, range_d=0.1, far=5.0, truncation=0.1)
    cfg.loss = LossConfig(smooth_weight=1e-6, smooth_pts=32, smooth_vox=0.1, smooth_margin=0.05, rgb_missing=0.05)
    cfg.mapping = MappingConfig(first_iters=200, iters=10)
    cfg.spline = SplineConfig(dt=0.3)
    cfg.mesh = MeshConfig(voxel_final=0.02)
    return cfg


def synthetic() -> Config:
    """Co-SLAM's NeuralRGBD synthetic settings (its ``configs/Synthetic`` YAML); also our synthetic scenes."""
    cfg = Config(name="synthetic")
    cfg.data = DataConfig(dataset="auto", depth_trunc=100.0)
    cfg.field = FieldConfig(log2_hashmap_size=16, voxel_sdf=0.01)
    cfg.render = RenderConfig(n_samples=32, n_range_d=11, range_d=0.1, far=4.0, truncation=0.1)
    cfg.loss = LossConfig(smooth_weight=1e-5, smooth_pts=32, smooth_vox=0.1, smooth_margin=0.05, rgb_missing=0.05)
    cfg.mapping = MappingConfig(first_iters=200, iters=10, lr_embed=0.001)
    cfg.spline = SplineConfig(dt=0.3)
    cfg.mesh = MeshConfig(voxel_final=0.02)
    return cfg


def scannet() -> Config:
    """Co-SLAM's ScanNet settings (its ``configs/ScanNet`` YAML)."""
    cfg = Config(name="scannet")
    cfg.data = DataConfig(dataset="scannet", crop_edge=10, depth_scale=1000.0, depth_trunc=100.0)
    cfg.field = FieldConfig(log2_hashmap_size=16, voxel_sdf=0.04)
    cfg.render = RenderConfig(n_samples=96, n_range_d=21, range_d=0.25, far=8.0, truncation=0.1)
    cfg.loss = LossConfig(smooth_weight=1e-3, smooth_pts=64, smooth_vox=0.1, smooth_margin=0.05, rgb_missing=0.0)
    cfg.mapping = MappingConfig(first_iters=500, iters=10, optim_cur=False, min_pixels_cur=20)
    cfg.spline = SplineConfig(dt=0.3)
    return cfg


def tum() -> Config:
    """Co-SLAM's TUM RGB-D settings (its ``configs/Tum`` YAML); TS-SLAM uses dt = 0.25 s on TUM."""
    cfg = Config(name="tum")
    cfg.data = DataConfig(dataset="tum", crop_edge=8, depth_scale=5000.0, depth_trunc=5.0)
    cfg.field = FieldConfig(log2_hashmap_size=16, voxel_sdf=0.02)
    cfg.render = RenderConfig(n_samples=64, n_range_d=21, range_d=0.25, far=5.0, truncation=0.05)
    cfg.loss = LossConfig(
        rgb_weight=1.0, depth_weight=0.1, sdf_weight=5000.0, fs_weight=10.0,
        smooth_weight=1e-8, smooth_pts=64, smooth_vox=0.04, smooth_margin=0.0, rgb_missing=1.0,
    )
    cfg.tracking = TrackingConfig(iters=10, lr_rot=1e-2, lr_trans=1e-2, best=False)
    cfg.mapping = MappingConfig(first_iters=1000, iters=20)
    cfg.spline = SplineConfig(dt=0.25)
    return cfg


def _two_core_budget(cfg: Config) -> Config:
    """The settings ``tum-cpu`` and ``synthetic-cpu`` share for 2 CPU cores (ours): 160 px wide
    images, a smaller hash table and fewer rays, samples and iterations.  Changes ``cfg`` in place."""
    cfg.data.resize_width = 160
    cfg.field.log2_hashmap_size = 16
    cfg.field.voxel_sdf = 0.04
    cfg.render.n_samples = 32
    cfg.render.n_range_d = 11
    cfg.tracking.n_rays = 512
    cfg.tracking.iters = 20
    # Adam moves each parameter by at most about lr per iteration, so 20 x 1e-3 (Co-SLAM's Replica
    # rate) caps a frame's rotation correction near 1.1 deg per axis: too little for hand-held
    # turns of 4-5 deg per frame (TUM-VI room2); with half of Co-SLAM's rays, 3e-3 also keeps the
    # steps steady (docs/system.md, "Tracking's step-size cap").
    cfg.tracking.lr_rot = cfg.tracking.lr_trans = 3e-3
    cfg.tracking.ignore_edge = 5
    cfg.mapping.first_iters = 200
    cfg.mapping.first_n_rays = 1024
    cfg.mapping.n_rays = 1024
    cfg.mapping.iters = 20
    cfg.local_ba.n_rays = 512
    cfg.mesh.voxel_final = 0.04
    return cfg


def tum_cpu() -> Config:
    """TUM settings for 2 CPU cores: :func:`_two_core_budget` on :func:`tum` (ours).

    Same losses, weights, truncation and schedule structure as :func:`tum`.
    """
    cfg = _two_core_budget(tum())
    cfg.name = "tum-cpu"
    cfg.data.crop_edge = 0  # in native pixels; the bundled slice is already 160 px wide
    cfg.tracking.best = True
    cfg.loss.smooth_pts = 32
    return cfg


def synthetic_cpu() -> Config:
    """Synthetic-scene settings for 2 CPU cores: :func:`_two_core_budget` on :func:`synthetic` (ours)."""
    cfg = _two_core_budget(synthetic())
    cfg.name = "synthetic-cpu"
    cfg.mapping.lr_embed = 0.01
    return cfg


def tiny() -> Config:
    """Smallest sensible settings for unit tests and notebooks (seconds on 2 cores; ours)."""
    cfg = synthetic_cpu()
    cfg.name = "tiny"
    cfg.field.log2_hashmap_size = 14
    cfg.field.voxel_sdf = 0.08
    cfg.render.n_samples = 24
    cfg.render.n_range_d = 8
    cfg.tracking.n_rays = 128
    cfg.tracking.iters = 5
    cfg.tracking.lr_rot = cfg.tracking.lr_trans = 1e-3  # the tests' and notebooks' figures use 1e-3
    cfg.mapping.first_iters = 30
    cfg.mapping.first_n_rays = 256
    cfg.mapping.n_rays = 256
    cfg.mapping.iters = 10
    cfg.local_ba.n_rays = 128
    cfg.local_ba.refine_iters = 5
    cfg.loss.smooth_pts = 16
    cfg.mesh.voxel_final = 0.08
    return cfg


PRESETS: Dict[str, Callable[[], Config]] = {
    "tum": tum,
    "scannet": scannet,
    "synthetic": synthetic,
    "replica": replica,
    "tum-cpu": tum_cpu,
    "synthetic-cpu": synthetic_cpu,
    "tiny": tiny,
}


# --------------------------------------------------------------------------------------------
# Conversion, overrides, files


def to_dict(cfg: Config) -> Dict[str, Any]:
    """Plain nested dict (JSON-serialisable) of a config."""
    return dataclasses.asdict(cfg)


def from_dict(values: Dict[str, Any], source: str = "<dict>") -> Config:
    """Build a Config from a nested dict; unknown sections or keys raise ValueError naming them."""
    cfg = Config()
    for key, value in values.items():
        if not hasattr(cfg, key):
            raise ValueError(f"{source}: unknown config section or key '{key}'")
        current = getattr(cfg, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ValueError(f"{source}: section '{key}' must be an object, got {type(value).__name__}")
            for sub_key, sub_value in value.items():
                if not hasattr(current, sub_key):
                    raise ValueError(f"{source}: unknown key '{key}.{sub_key}'")
                setattr(current, sub_key, sub_value)
        else:
            setattr(cfg, key, value)
    return validate(cfg, source)


# Ranges the code relies on (ours): "section.key": (comparison, bound).  Keys not listed only have
# their type checked.  A value outside its range raises before any work starts, instead of a
# division by zero or an empty loop deep inside a run.
def _type_problem(value: Any, annotation: Any) -> Optional[str]:
    """What is wrong with ``value`` for a field annotated ``annotation`` (None when it fits)."""
    if getattr(annotation, "__origin__", None) is not None and type(None) in getattr(annotation, "__args__", ()):
        if value is None:
            return None
        annotation = next(arg for arg in annotation.__args__ if arg is not type(None))
    if annotation is bool:
        return None if isinstance(value, bool) else "true or false"
    if annotation is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else "an integer"
    if annotation is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        return None if ok else "a finite number"
    if annotation is str:
        return None if isinstance(value, str) else "a string"
    return None  # lists (field.bound) are checked where they are used


def _check_range(value: Any, comparison: str, bound: Any) -> Tuple[bool, str]:
    """(whether ``value`` keeps the rule, the rule in words) for a field declared with :func:`ranged`."""
    if comparison == "in":
        return value in bound, "one of " + ", ".join(bound)
    if comparison == "[]":
        return bound[0] <= value <= bound[1], f"an integer in [{bound[0]}, {bound[1]}]"
    if comparison == "(]":
        return bound[0] < value <= bound[1], f"in ({bound[0]}, {bound[1]}]"
    if comparison == "()":
        return bound[0] < value < bound[1], f"in ({bound[0]}, {bound[1]})"
    if comparison == ">":
        return value > bound, f"> {bound}"
    return value >= bound, f">= {bound}"


def validate(cfg: Config, source: str = "config") -> Config:
    """Check every value's type against its field and the range it declares (:func:`ranged`).

    Raises ValueError naming ``source``, the key, the value and what was expected; returns
    ``cfg`` unchanged otherwise.  Called by :func:`apply_overrides`, :func:`from_dict` and
    ``slam.run_slam``.
    """
    sections = [("", cfg)] + [(f.name + ".", getattr(cfg, f.name)) for f in dataclasses.fields(cfg)
                              if dataclasses.is_dataclass(getattr(cfg, f.name))]
    for prefix, section in sections:
        for item in dataclasses.fields(section):
            value = getattr(section, item.name)
            if dataclasses.is_dataclass(value):
                continue
            key = prefix + item.name
            expected = _type_problem(value, item.type)
            if expected is not None:
                raise ValueError(f"{source}: {key} = {value!r} must be {expected}")
            if "range" not in item.metadata or value is None:
                continue
            ok, rule = _check_range(value, *item.metadata["range"])
            if not ok:
                raise ValueError(f"{source}: {key} = {value!r} must be {rule}")
    if not re.fullmatch(r"auto|cpu|cuda(:[0-9]+)?", cfg.device):
        raise ValueError(f"{source}: device = {cfg.device!r} must be auto, cpu, cuda or cuda:N")
    _check_bound(cfg.field.bound, source)
    if cfg.render.far <= cfg.render.near:
        raise ValueError(f"{source}: render.far = {cfg.render.far!r} must be > render.near = {cfg.render.near!r}")
    if cfg.local_ba.fit_controls > cfg.local_ba.window:
        raise ValueError(f"{source}: local_ba.fit_controls = {cfg.local_ba.fit_controls} must be <= "
                         f"local_ba.window = {cfg.local_ba.window}")
    return cfg


def _check_bound(bound: Any, source: str) -> None:
    """field.bound: None (estimated from frame 0) or [[xmin, xmax], [ymin, ymax], [zmin, zmax]] in m."""
    if bound is None:
        return
    expected = "None or [[xmin, xmax], [ymin, ymax], [zmin, zmax]] of finite numbers with min < max"
    try:
        rows = [[float(v) for v in row] for row in bound]
        ok = len(rows) == 3 and all(len(row) == 2 for row in rows) and not any(
            isinstance(v, bool) for row in bound for v in row)
    except (TypeError, ValueError):
        ok = False
    if ok:
        ok = all(math.isfinite(v) for row in rows for v in row) and all(row[0] < row[1] for row in rows)
    if not ok:
        raise ValueError(f"{source}: field.bound = {bound!r} must be {expected}")


def _parse_value(text: str) -> Any:
    try:
        return json.loads(text)
    except json.JSONDecodeError:
        if text in ("True", "False"):
            return text == "True"
        if text == "None":
            return None
        return text


def apply_overrides(cfg: Config, overrides: Sequence[str]) -> Config:
    """Return a copy of ``cfg`` with ``section.key=value`` overrides applied.

    Values are parsed as JSON (``3``, ``0.5``, ``true``, ``[[0,1],[0,1],[0,1]]``), else taken as
    strings; string fields keep the text as typed.  Raises ValueError naming the override for an
    unknown key, a malformed string, or a value of the wrong type or out of range (:func:`validate`).
    """
    cfg = copy.deepcopy(cfg)
    for item in overrides:
        if "=" not in item:
            raise ValueError(f"override '{item}' is not of the form section.key=value")
        path, text = item.split("=", 1)
        parts = path.strip().split(".")
        target = cfg
        for part in parts[:-1]:
            if not hasattr(target, part):
                raise ValueError(f"override '{item}': unknown section '{part}'")
            target = getattr(target, part)
        if not hasattr(target, parts[-1]) or dataclasses.is_dataclass(getattr(target, parts[-1])):
            raise ValueError(f"override '{item}': unknown key '{path}'")
        value = _parse_value(text.strip())
        if {f.name: f.type for f in dataclasses.fields(target)}[parts[-1]] is str and not isinstance(value, str):
            value = text.strip()  # a string field keeps the text as typed (data.path=2024)
        setattr(target, parts[-1], value)
    return validate(cfg, "overrides " + " ".join(overrides) if overrides else "config")


def load(name_or_file: str) -> Config:
    """A preset by name (see :data:`PRESETS`) or a JSON config file written by :func:`save`."""
    if name_or_file in PRESETS:
        return PRESETS[name_or_file]()
    if os.path.isfile(name_or_file):
        try:
            with open(name_or_file, encoding="utf-8") as handle:
                values = json.load(handle)
        except UnicodeDecodeError:
            raise ValueError(f"{name_or_file}: not a text file; expected a JSON config object") from None
        except json.JSONDecodeError as error:
            raise ValueError(f"{name_or_file}: not valid JSON ({error}); expected a JSON config object") from None
        if not isinstance(values, dict):
            raise ValueError(f"{name_or_file}: the JSON is a {type(values).__name__}; expected an object "
                             f"{{section: {{key: value}}}} like a run's config.json")
        return from_dict(values, source=name_or_file)
    raise ValueError(
        f"config '{name_or_file}' is neither a preset ({', '.join(PRESETS)}) nor an existing JSON file"
    )


def save(cfg: Config, path: str) -> None:
    """Write the config as JSON atomically (a new file in the same folder, then rename; files.py)."""
    from .files import atomic_write_text

    atomic_write_text(path, json.dumps(to_dict(cfg), indent=2))
