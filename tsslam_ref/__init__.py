"""tsslam_ref: a readable, tested reference implementation of TS-SLAM.

TS-SLAM ("Optimizing NeRF-based SLAM with Trajectory Smoothness Constraints", He, Chen and Zhang,
ICRA 2025) keeps Co-SLAM's neural map and represents the camera trajectory as a uniform cubic
B-spline with a dynamics regulariser, a sliding-window local bundle adjustment and a global BA.

Modules, by layer (a module imports modules of its own layer or lower ones, never higher ones,
and no import cycle; :data:`LAYERS` is the table, tests/test_layers.py checks every import):

* 0 base: ``config`` (settings), ``presets`` (their named values), ``config_io`` (overrides,
  validation, JSON files), ``geometry`` (SO(3), poses, pixel rays), ``files`` (atomic
  writes), ``cli_args`` (command-line value parsing shared by the command lines), ``times``
  (timestamps: float64 seconds, narrower floats refused)
* 1 math and map: ``spline`` (the curve, Eq. 5-9), ``knots`` (its non-uniform form), ``spline_fit`` (curve approximation, Eq. 11),
  ``spline_jacobians``, ``se3_spline`` (joint SE(3) variant), ``trajectory`` (the spline
  trajectory type), ``knot_policy`` (adaptive interval lengths), ``dynamics`` (L_DR), ``hash_kernel`` (compiled hash-grid kernel), ``field``
  (Eq. 1), ``render`` (Eq. 2-3)
* 1.5 side, beside the stack (they import layers 0-1 and each other; the command line imports
  them): ``data`` and ``datasets.*`` (loaders), ``synthetic`` (procedural scenes),
  ``trajectory_metrics`` (ATE, RPE), ``reconstruction_metrics`` (culling, Acc/Comp, Depth L1),
  ``eval`` (their command line), ``conformance``, ``conformance_hints`` and ``spline_kit`` (spline conformance kit),
  ``analytic`` (an exact stand-in map for the chapters and tests), ``view3d`` (interactive 3-D
  figures with a static picture)
* 2 objective: ``losses`` (Eq. 4), ``mapping`` (map fitting with known poses), ``mesh``
* 2.5 shared optimisation: ``bundle`` (pose models, keyframe rays, the joint loop)
* 3 optimisers: ``tracking``, ``local_ba``, ``global_ba``
* 4 system: ``slam`` (the loop), ``parallel`` (tracking and mapping in two threads), ``run``
  (command line) with ``run_outputs`` (what a run writes) and ``run_summaries`` (its metrics' summaries and
  per-frame table), and their support ``device``, ``timings``, ``export``,
  ``knot_schedule`` (adaptive knots in the loop), ``checkpoint`` (the run's state on disk)

Importing the package imports nothing heavy; import the module you need.
"""

__version__ = "0.1.0"

LAYERS = {
    # 0 base
    "config": 0,
    "presets": 0,
    "config_io": 0,
    "geometry": 0,
    "files": 0,
    "cli_args": 0,
    "times": 0,
    # 1 math and map
    "spline": 1,
    "knots": 1,
    "knot_policy": 1,
    "spline_fit": 1,
    "spline_jacobians": 1,
    "se3_spline": 1,
    "trajectory": 1,
    "dynamics": 1,
    "hash_kernel": 1,
    "field": 1,
    "render": 1,
    # 1.5 side: loaders, synthetic scenes, evaluation, the spline conformance kit
    "data": 1.5,
    "datasets": 1.5,
    "datasets.images": 1.5,
    "datasets.intrinsics": 1.5,
    "datasets.layouts": 1.5,
    "datasets.sequence": 1.5,
    "datasets.tum_format": 1.5,
    "synthetic": 1.5,
    "trajectory_metrics": 1.5,
    "reconstruction_metrics": 1.5,
    "eval": 1.5,
    "conformance": 1.5,
    "conformance_hints": 1.5,
    "spline_kit": 1.5,
    "analytic": 1.5,
    "view3d": 1.5,
    # 2 objective
    "losses": 2,
    "mapping": 2,
    "mesh": 2,
    # 2.5 shared optimisation
    "bundle": 2.5,
    # 3 optimisers
    "tracking": 3,
    "local_ba": 3,
    "global_ba": 3,
    # 4 system and its support
    "slam": 4,
    "parallel": 4,
    "run": 4,
    "run_outputs": 4,
    "run_summaries": 4,
    "device": 4,
    "timings": 4,
    "export": 4,
    "knot_schedule": 4,
    "checkpoint": 4,
}
"""Layer of every module (dotted name below the package); an import may point to the same or a
lower number only."""
