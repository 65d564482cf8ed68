"""One configuration system for the whole package: nested dataclasses, presets, overrides.

Layer 0 (base): dataclasses only, no torch.

* One dataclass per concept (``DataConfig``, ``FieldConfig``, ``RenderConfig``, ``LossConfig``,
  ``TrackingConfig``, ``MappingConfig``, ``SplineConfig``, ``DynamicsConfig``, ``LocalBAConfig``,
  ``MeshConfig``) gathered in :class:`Config`.
* Every field says its unit and its source: "Co-SLAM" means the official YAML/code at commit
  3bb904e (github.com/HengyiWang/Co-SLAM); "paper" means TS-SLAM (ICRA 2025, arXiv:2410.08780);
  "ours" means a choice of this project (see docs/deviations.md).
* Presets are functions registered in :data:`PRESETS`: ``tum``, ``scannet``, ``synthetic``,
  ``replica`` (the original numbers), ``tum-cpu`` and ``synthetic-cpu`` (same structure, fewer rays
  and samples, for 2 CPU cores), and ``tiny`` (tests and notebooks); their values live in
  presets.py.
* :func:`load` accepts a preset name or a JSON file written by :func:`save` (every run saves its
  resolved config as ``config.json``).
* Overrides (:func:`apply_overrides`, ``--set section.key=value``), :func:`validate` (every value's
  type and the range its field declares with :func:`ranged`), :func:`to_dict` and :func:`save`
  live in config_io.py and are re-exported here.
"""

import difflib
import operator
import os
from dataclasses import dataclass
from dataclasses import field as _field
from typing import Any, Callable, Dict, List, Optional, Sequence, Tuple

from .config_io import apply_overrides, save, to_dict, validate  # noqa: F401  (re-exported here)
from .config_io import read_json_values, set_values
from .presets import PRESET_LAYERS


class _Settings:
    """Base of every settings dataclass: assigning a name that is not one of its fields is refused
    (``cfg.tracking.itres = 5`` would otherwise add an attribute nothing reads)."""

    def __setattr__(self, name: str, value: Any) -> None:
        known = getattr(type(self), "__dataclass_fields__", {})
        if name not in known:
            close = difflib.get_close_matches(name, list(known), n=1)
            hint = f" (did you mean {close[0]!r}?)" if close else f"; its settings: {', '.join(known)}"
            raise AttributeError(f"{type(self).__name__} has no setting {name!r}{hint}")
        object.__setattr__(self, name, value)


def ranged(default: Any, comparison: str, bound: Any) -> Any:
    """A dataclass field with its default and the values it allows, kept in the field's metadata.

    ``comparison`` is one of ``">"``, ``">="`` (``bound`` a number), ``"(]"``, ``"()"``, ``"[]"``
    (``bound`` a pair) or ``"in"`` (``bound`` the allowed values); :func:`validate` reads it.
    """
    return _field(default=default, metadata={"range": (comparison, bound)})


@dataclass
class DataConfig(_Settings):
    """Which frames to read and how to pre-process them."""

    dataset: str = ranged("auto", "in", ("auto", "tum", "scannet", "neural_rgbd", "replica", "folder"))
    """Layout of ``path`` (ours; a folder ``data synthesize`` wrote is ``tum``)."""
    path: str = ""
    """Dataset folder; empty means the bundled default sequence (ours)."""
    resize_width: Optional[int] = ranged(None, ">=", 8)
    """Shrink colour and depth to this width in pixels (aspect kept, intrinsics scaled exactly);
    narrower images keep their size, never enlarged; None keeps the native size (ours)."""
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
    require_gt: bool = True
    """Use only the frames with a ground-truth pose (as Co-SLAM); false keeps every frame, for data
    whose ground truth covers part of the sequence or none of it (ours)."""


@dataclass
class FieldConfig(_Settings):
    """Co-SLAM joint encoding: OneBlob + multi-resolution hash grid + two tiny MLPs (Sec. III-A)."""

    bound: Optional[List[List[float]]] = None
    """Scene box [[xmin,xmax],[ymin,ymax],[zmin,zmax]] in metres; None = estimated from frame 0's
    depth (ours; Co-SLAM needs it in every scene YAML)."""
    bound_margin: float = ranged(1.0, ">=", 0)
    """Margin (m) added on every side when the bound is estimated from frame 0's depth (ours: later
    frames see beyond frame 0, so the margin is generous)."""
    n_levels: int = ranged(16, ">=", 2)
    """Hash-grid levels (Co-SLAM, fixed in code)."""
    n_features_per_level: int = ranged(2, ">=", 1)
    """Features per level (Co-SLAM, fixed in code)."""
    base_resolution: int = ranged(16, ">=", 2)
    """Coarsest grid resolution (Co-SLAM, fixed in code)."""
    log2_hashmap_size: int = ranged(16, ">=", 4)
    """log2 of the per-level table size T (Co-SLAM ``grid.hash_size``)."""
    voxel_sdf: float = ranged(0.02, ">", 0)
    """Finest cell size in metres; finest resolution = int(max box side / voxel_sdf) (Co-SLAM).  As in
    Co-SLAM a value above 10 is the resolution itself, and a finest resolution below
    ``base_resolution`` (a small box) makes the finer levels coarser, not finer."""
    oneblob_bins: int = ranged(16, ">=", 2)
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
    compiled_oneblob: bool = True
    """On the CPU, compute the OneBlob encoding and its gradient in the compiled kernel
    (``csrc/oneblob.cpp``) instead of about 30 PyTorch operations (ours; needs
    ``compiled_kernel``'s extension to build).  Faster (docs/system.md, "Where the time goes") and
    equal bit for bit to the PyTorch path and its autograd gradient, so it changes no result;
    False runs the PyTorch path."""


@dataclass
class RenderConfig(_Settings):
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
    """Rays per chunk of ``render.render_image`` (whole images; ours).  A SLAM run renders none."""


@dataclass
class LossConfig(_Settings):
    """Weights of the five reconstruction losses (Sec. III-A, Eq. 4; Co-SLAM section 3.4)."""

    rgb_weight: float = ranged(5.0, ">=", 0)
    depth_weight: float = ranged(0.1, ">=", 0)
    sdf_weight: float = ranged(1000.0, ">=", 0)
    fs_weight: float = ranged(10.0, ">=", 0)
    smooth_weight: float = ranged(1e-5, ">=", 0)
    """Feature total-variation weight, in every optimisation that moves the map after the first frame
    (Co-SLAM: its global BA; here also the map update and local BA's joint stage, off by default)."""
    smooth_pts: int = ranged(32, ">=", 2)
    """Lattice points per axis for the smoothness term (Co-SLAM)."""
    smooth_vox: float = ranged(0.1, ">", 0)
    """Lattice spacing (m) (Co-SLAM)."""
    smooth_margin: float = ranged(0.05, ">=", 0)
    """Margin (m) from the box when placing the lattice (Co-SLAM)."""
    rgb_missing: float = ranged(0.05, ">=", 0)
    """Colour-loss factor for rays without valid depth, applied inside the square (weight 0.05² here);
    Co-SLAM's boolean weight tensor turns any nonzero value into 1: ``1.0`` reproduces it
    (docs/deviations.md)."""


@dataclass
class TrackingConfig(_Settings):
    """Per-frame pose optimisation with the map frozen (Sec. III-D, Tracking Thread)."""

    iters: int = ranged(10, ">=", 1)
    """Adam iterations per frame (Co-SLAM ``tracking.iter``)."""
    n_rays: int = ranged(1024, ">=", 1)
    """Pixels sampled per frame, reused for all iterations (Co-SLAM ``tracking.sample``)."""
    lr_rot: float = ranged(1e-3, ">", 0)
    """Learning rate of the rotation increment (Co-SLAM: 1e-3, TUM 1e-2; ScanNet preset 2e-3 for
    Co-SLAM's quaternion, see ``presets.SCANNET``)."""
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
class MappingConfig(_Settings):
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
    """BA rotation learning rate (Co-SLAM; ScanNet preset 2e-3, see ``presets.SCANNET``)."""
    lr_trans: float = ranged(1e-3, ">", 0)
    """BA translation learning rate (Co-SLAM)."""
    optim_cur: bool = True
    """Optimise the current frame's pose in BA (Co-SLAM: False for ScanNet)."""
    pose_accum_step: int = ranged(5, ">=", 1)
    """Pose optimiser steps every n BA iterations with accumulated gradients (Co-SLAM)."""


@dataclass
class SplineConfig(_Settings):
    """Cubic B-spline trajectory (Sec. III-B): uniform knots, or knots placed by the motion (ours)."""

    dt: float = ranged(0.3, "(]", (0, 10))
    """Knot spacing Delta t in seconds (paper: 0.30 ScanNet/synthetic, 0.25 TUM); at most 10 s: the
    knot times are float64 seconds of dataset time (about 1.3e9 s for TUM), and a spacing of
    hours would leave a hand-held camera's motion unmodelled while the basis coordinate
    (t - t0) / dt loses precision (at 1e6 s positions fall onto a 1/64 m grid)."""
    convention: str = ranged("paper", "in", ('paper', 'basalt'))
    """Index convention: 'paper' (segment [t_i, t_i+1) uses points i-2..i+1) or 'basalt' (i..i+3)."""
    knots: str = ranged("uniform", "in", ('uniform', 'adaptive'))
    """'uniform': every interval dt long (the paper).  'adaptive' (ours, beyond the paper): the first
    interval is dt long, each later one's length is chosen by the knot policy from the motion
    tracked over the last two intervals, h = sqrt(6 eps / a) within [dt_min, dt_max] (knot_policy.py)."""
    last_interval: str = ranged("last_frame", "in", ('planned', 'last_frame'))
    """Where the run's last interval, which no frame closes, ends when it is mapped at the end of
    the run: 'last_frame' (ours, the default): a quarter frame spacing after the last frame, so the
    last frames are fitted near the end of their interval, or 'planned' (its knot as scheduled,
    ``dt`` after its start with uniform knots: the paper's loop); measured in docs/system.md, "The
    run's last interval"."""
    dt_min: float = ranged(0.1, "(]", (0, 10))
    """Shortest adaptive interval (s): at the 30 Hz of RGB-D cameras 0.1 s holds about three frames,
    the fewest whose tracked poses still constrain the interval's new control point."""
    dt_max: float = ranged(0.4, "(]", (0, 10))
    """Longest adaptive interval (s): hand-held and walking motion changes direction at 1-2 Hz (gait,
    turns of the head), and a cubic B-spline needs at least about two intervals per half period
    to bend with it, which 0.4 s still gives at 1 Hz."""
    rotation_tolerance: float = ranged(0.005, ">", 0)
    """Approximation error (rad, about 0.3 deg) the adaptive policy allows per interval: below the
    few-tenths-of-a-degree rotation error of RGB-D tracking, so the curve's smoothing stays under
    what tracking can resolve."""
    position_tolerance: float = ranged(0.005, ">", 0)
    """Approximation error (m) the adaptive policy allows per interval: the depth noise of RGB-D
    sensors at 1-2 m (a few mm), below which tracked positions do not resolve the motion."""


@dataclass
class DynamicsConfig(_Settings):
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
class LocalBAConfig(_Settings):
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
class MeshConfig(_Settings):
    """Marching-cubes meshes (Co-SLAM section 6.1)."""

    voxel_final: float = ranged(0.03, ">", 0)
    """Voxel size (m) of the final mesh (Co-SLAM: 0.02 Replica/Synthetic, 0.03 ScanNet/TUM)."""
    sdf_cutoff: float = ranged(3.0, ">", 0)
    """Skip cells where any of the 8 corners has |normalised SDF| >= this; a cell is kept only
    when all its corners are below it (Co-SLAM NumpyMarchingCubes)."""


@dataclass
class Config(_Settings):
    """Everything a run needs.  Saved as ``config.json`` beside every run's outputs."""

    name: str = ranged("default", "in", ("default",) + tuple(PRESET_LAYERS))
    """Preset name this config started from."""
    method: str = ranged("tsslam", "in", ('tsslam', 'coslam'))
    """tsslam (B-spline trajectory) or coslam (one pose per frame, the baseline)."""
    seed: int = ranged(0, "[]", (0, 2**32 - 1))  # PyTorch's CPU generator keeps 32 bits of a seed
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


# Settings one method never reads: a ``--set`` meant for the other method is noted, not silently
# taken as effective (a key ending in "." stands for its whole section).
IGNORED_BY_METHOD: Dict[str, Tuple[Tuple[str, ...], str]] = {
    "coslam": (("spline.", "dynamics.", "local_ba.", "mapping.tsslam_map_every"),
               "the baseline keeps one pose per frame: no spline, local BA or dynamics term"),
    "tsslam": (("mapping.map_every",), "TS-SLAM maps once per spline interval and every mapping.tsslam_map_every frames"),
}


ADAPTIVE_ONLY = ("spline.dt_min", "spline.dt_max", "spline.rotation_tolerance", "spline.position_tolerance")
"""The knot policy's settings: read only with ``spline.knots=adaptive``."""

UNREAD_WHEN_OFF: Tuple[Tuple[str, Tuple[str, ...], str], ...] = (
    ("local_ba.use_spline", ("dynamics.", "local_ba.use_dynamics", "local_ba.fit_iters", "local_ba.fit_controls",
                             "local_ba.max_deviation", "spline.last_interval"),
     "one pose per frame: no curve approximation, deviation check or L_DR"),
    ("local_ba.enabled", ("local_ba.fit_iters", "local_ba.refine_iters", "local_ba.joint_iters", "local_ba.n_rays",
                          "local_ba.lr_rot", "local_ba.lr_trans"), "no curve fit and no window stages"),
    ("local_ba.use_dynamics", ("dynamics.",), "no L_DR"),
)
"""TS-SLAM's ablation switches (paper Table V): each switch, the keys it leaves unread when false, why."""


def overrides_without_effect(method: str, overrides: Sequence[str], cfg: Optional["Config"] = None) -> List[str]:
    """Of the overrides ``KEY=VALUE``, those whose key the run never reads, each as 'KEY=VALUE has no
    effect with --method M (reason)'; with ``cfg`` also, for TS-SLAM, the knot policy's settings
    with uniform knots and the keys an ablation switch set to false leaves unread ('... has no effect
    with local_ba.enabled=false (reason)'); ``render.chunk`` is read by ``render_image`` alone."""
    keys, reason = IGNORED_BY_METHOD.get(method, ((), ""))
    rules = [(keys, f"with --method {method} ({reason})"), (("render.chunk",), "in a run (it renders no whole image)")]
    if cfg is not None and method == "tsslam":
        if cfg.spline.knots == "uniform":
            rules.append((ADAPTIVE_ONLY, "with uniform knots (read only with spline.knots=adaptive)"))
        rules += [(unread, f"with {switch}=false ({why})") for switch, unread, why in UNREAD_WHEN_OFF
                  if not operator.attrgetter(switch)(cfg)]

    def reads_none(text: str, names: Sequence[str]) -> bool:
        key = text.split("=", 1)[0].strip()
        return any(key.startswith(name) if name.endswith(".") else key == name for name in names)

    notes = [(text, next((why for names, why in rules if reads_none(text, names)), None)) for text in overrides]
    return [f"{text} has no effect {why}" for text, why in notes if why is not None]


# --------------------------------------------------------------------------------------------
# Presets (values in presets.py) and loading


def from_dict(values: Dict[str, Any], source: str = "<dict>") -> Config:
    """Build a Config from a nested dict; unknown sections or keys raise ValueError naming them."""
    return validate(set_values(Config(), values, source), source)


def _preset(name: str) -> Config:
    """The preset ``name``: its value layers (presets.py) applied in order on the defaults."""
    cfg = Config()
    for values in PRESET_LAYERS[name]:
        set_values(cfg, values, source=f"preset {name}")
    return cfg


def replica() -> Config:
    """Co-SLAM's Replica settings (its ``configs/Replica`` YAML)."""
    return _preset("replica")


def synthetic() -> Config:
    """Co-SLAM's NeuralRGBD synthetic settings (its ``configs/Synthetic`` YAML); also our synthetic scenes."""
    return _preset("synthetic")


def scannet() -> Config:
    """Co-SLAM's ScanNet settings (its ``configs/ScanNet`` YAML)."""
    return _preset("scannet")


def tum() -> Config:
    """Co-SLAM's TUM RGB-D settings (its ``configs/Tum`` YAML); TS-SLAM uses dt = 0.25 s on TUM."""
    return _preset("tum")


def tum_cpu() -> Config:
    """TUM settings for 2 CPU cores: the two-core budget shared with :func:`synthetic_cpu` on
    :func:`tum` (ours).  Same losses, weights and truncation as :func:`tum`; tracking keeps its
    best iteration over 20 (Co-SLAM's "Co-SLAM†" rule, ``configs/Tum_dagger``), the first frame
    maps 200 iterations and the smoothness lattice is 32³ (docs/deviations.md, "CPU presets")."""
    return _preset("tum-cpu")


def synthetic_cpu() -> Config:
    """Synthetic-scene settings for 2 CPU cores: the two-core budget shared with :func:`tum_cpu` on
    :func:`synthetic` (ours)."""
    return _preset("synthetic-cpu")


def tiny() -> Config:
    """Smallest sensible settings for unit tests and notebooks (seconds on 2 cores; ours)."""
    return _preset("tiny")


PRESETS: Dict[str, Callable[[], Config]] = {
    "tum": tum,
    "scannet": scannet,
    "synthetic": synthetic,
    "replica": replica,
    "tum-cpu": tum_cpu,
    "synthetic-cpu": synthetic_cpu,
    "tiny": tiny,
}


def load(name_or_file: str) -> Config:
    """A preset by name (see :data:`PRESETS`) or a JSON config file (as :func:`save` writes).

    A file's values are set on the preset its ``"name"`` names (a saved config names the preset it
    started from), so ``{"name": "tum-cpu", "tracking": {"iters": 10}}`` is tum-cpu with 10
    tracking iterations; a file without a name, or named ``"default"``, starts from
    :class:`Config`'s defaults; any other name is refused (a misspelt preset).
    """
    if name_or_file in PRESETS:
        return PRESETS[name_or_file]()
    if os.path.isfile(name_or_file):
        values = read_json_values(name_or_file)
        base = values.get("name")
        if isinstance(base, str) and base in PRESETS:
            return validate(set_values(PRESETS[base](), values, name_or_file), name_or_file)
        if isinstance(base, str) and base != Config.name:  # a misspelt preset would run on the defaults
            raise ValueError(f"{name_or_file}: \"name\": {base!r} is no preset; a config file's name says "
                             f"which preset its values start from: {', '.join(PRESETS)}, or "
                             f"{Config.name!r} (or no name) for the built-in defaults")
        return from_dict(values, source=name_or_file)
    raise ValueError(
        f"config '{name_or_file}' is neither a preset ({', '.join(PRESETS)}) nor an existing JSON file"
    )


def read_data_folder(cfg: Config, path: str, config_name: Optional[str]) -> None:
    """``cfg.data.path = path``.  With a preset (``config_name`` a preset's name or None) the folder
    is the user's own: its layout is detected and its depth scale is its own (calibration file, else
    the layout's standard), not the preset's dataset's; a config file keeps its ``data`` settings.
    ``--dataset`` and ``--set data.*`` applied afterwards still decide."""
    cfg.data.path = path
    if config_name is None or config_name in PRESETS:
        cfg.data.dataset, cfg.data.depth_scale = "auto", None
