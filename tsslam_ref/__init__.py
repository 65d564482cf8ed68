"""tsslam_ref: a readable, tested reference implementation of TS-SLAM.

TS-SLAM ("Optimizing NeRF-based SLAM with Trajectory Smoothness Constraints", He, Chen and Zhang,
ICRA 2025) keeps Co-SLAM's neural map and represents the camera trajectory as a uniform cubic
B-spline with a dynamics regulariser, a sliding-window local bundle adjustment and a global BA.

Modules, by layer (imports point downwards only):

* 0 base: ``config``, ``geometry``
* 1 math and map: ``spline``, ``dynamics``, ``field``, ``render``
* 2 objective: ``losses``
* 3 optimisers: ``tracking``, ``local_ba``, ``global_ba``
* 4 system: ``slam``, ``run`` (command line)
* side: ``data``, ``synthetic``, ``eval``, ``mesh``, ``plot``

Importing the package imports nothing heavy; import the module you need.
"""

__version__ = "0.1.0"
