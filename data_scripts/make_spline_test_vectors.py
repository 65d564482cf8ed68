"""Generate the shipped spline conformance vectors in tsslam_ref/assets/spline_vectors/.

Each vector is one JSON file holding an input (convention, dt, t0, rotvecs, translations, times)
and our float64 output (R, p, v, a, omega_body, omegadot_body), in the format of
:mod:`tsslam_ref.conformance`.  The outputs are validated in tests/test_conformance.py against
oracles that do not use our closed forms (autograd in time, central differences, PyPose rotations,
scipy B-splines for translation, exact rational arithmetic at knot-adjacent times, the basalt golden
table of tsslam_ref/assets/spline_kit.md).

Deterministic: numpy ``default_rng(SEED)``.  Usage:

    python data_scripts/make_spline_test_vectors.py [--out DIR] [--force]
"""

import argparse
import json
import os
import sys

import numpy as np
import torch

from tsslam_ref import conformance, spline, spline_kit
from tsslam_ref.geometry import so3_exp, so3_log

SEED = 20250521
N_RANDOM_TIMES = 230

# name, convention, n_ctrl, dt (s), t0 (s), max relative rotation between knots (rad), translation scale (m)
RANDOM_SPLINES = [
    ("paper_dt0.03_tum_stamps", "paper", 8, 0.03, 1305031102.175304, 0.3, 0.05),
    ("paper_dt0.25_large_rot", "paper", 10, 0.25, 0.0, 2.0, 1.0),
    ("basalt_dt1_large_rot", "basalt", 7, 1.0, -2.5, 2.0, 2.0),
    ("basalt_dt0.1_floor_knots", "basalt", 12, 0.1, 0.1, 1.0, 0.5),
]

# Joint SE(3) ("representation": "se3"), same columns.
SE3_SPLINES = [
    ("se3_basalt_dt1_pypose", "basalt", 8, 1.0, 0.0, 1.0, 1.0),
    ("se3_paper_dt0.05_large_rot", "paper", 9, 0.05, 100.0, 2.0, 0.2),
]

# A smaller vector that also holds the Jacobians (M x 4 x 3 x 3 per quantity).
JACOBIAN_SPLINE = ("jacobians_paper_dt0.25", "paper", 8, 0.25, 0.5, 1.5, 1.0)
N_JACOBIAN_TIMES = 30

# Non-uniform knots ("knots" replaces convention, dt, t0): name, n_ctrl, first knot (s), spacings
# uniform in [min, max] (s), max relative rotation (rad), translation scale (m).  Its own generator
# (seed SEED + 1), so the uniform vectors above do not change.
KNOT_SPLINE = ("knots_uneven_tum_stamps", 11, 1305031102.175304, (0.02, 0.4), 1.5, 0.5)

# The basalt golden table's knots (tsslam_ref/assets/spline_kit.md; basalt convention, t0 = 0, dt = 0.5 s).
BASALT_GOLDEN_ROTVECS = [[0, 0, 0], [0.1, -0.2, 0.3], [0.4, -0.1, 0.5], [0.3, 0.3, 0.9], [-0.2, 0.6, 1.2], [-0.5, 0.4, 1.0]]
BASALT_GOLDEN_TRANSLATIONS = [[0, 0, 0], [1, 0, 0.5], [1.5, 1, 0.5], [1, 2, 0], [0, 2.5, -0.5], [-1, 2, -1]]
BASALT_GOLDEN_TIMES = [0.0, 0.35, 0.8, 1.2]


def random_control_points(rng: np.random.Generator, n_ctrl: int, max_angle: float, scale: float):
    """Random walk: R_k = R_{k-1} Exp(step), |step| uniform in [0, max_angle]; (N,3) rotvecs, (N,3) m."""
    rotation = so3_exp(torch.as_tensor(rng.normal(size=3)))
    rotations = [rotation]
    for _ in range(n_ctrl - 1):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        step = axis * rng.uniform(0.0, max_angle)
        rotation = rotation @ so3_exp(torch.as_tensor(step))
        rotations.append(rotation)
    rotvecs = so3_log(torch.stack(rotations)).numpy()
    translations = np.cumsum(rng.normal(scale=scale, size=(n_ctrl, 3)), axis=0)
    return rotvecs, translations


def query_times(rng: np.random.Generator, n_ctrl: int, dt: float, t0: float, convention: str) -> np.ndarray:
    """All knots in the domain (both ends included), the float64 neighbours just before and after
    every interior knot (where the segment choice is hardest), plus random times; sorted, float64,
    each time once (the knots include both domain ends)."""
    t_min, t_max = spline.valid_time_range(n_ctrl, dt, t0, convention)
    offset = 2 if convention == "paper" else 0
    knots = t0 + dt * np.arange(offset, offset + n_ctrl - 2, dtype=np.float64)
    random = t_min + (t_max - t_min) * rng.uniform(size=N_RANDOM_TIMES)
    interior = knots[1:-1]
    neighbours = [np.nextafter(interior, -np.inf), np.nextafter(interior, np.inf),
                  np.nextafter(np.nextafter(interior, -np.inf), -np.inf)]
    return np.unique(np.concatenate([[t_min, t_max], knots, *neighbours, random]))


def make_vector(convention, dt, t0, rotvecs, translations, times, description, representation="split",
                jacobians=False) -> dict:
    data = {"description": description, "representation": representation, "convention": convention, "dt": dt, "t0": t0,
            "rotvecs": np.asarray(rotvecs, dtype=np.float64).tolist(),
            "translations": np.asarray(translations, dtype=np.float64).tolist(),
            "times": np.asarray(times, dtype=np.float64).tolist()}
    data.update(conformance.evaluate_input(data, description, jacobians=jacobians))
    return data


def knot_vector():
    """(name, data) of the non-uniform vector: every knot in the domain, its float64 neighbours, random times."""
    name, n_ctrl, first, (low, high), max_angle, scale = KNOT_SPLINE
    rng = np.random.default_rng(SEED + 1)
    rotvecs, translations = random_control_points(rng, n_ctrl, max_angle, scale)
    knot_vector = first + np.concatenate([[0.0], np.cumsum(rng.uniform(low, high, size=n_ctrl + 1))])
    domain_knots = knot_vector[2:n_ctrl]  # kappa_2 .. kappa_{N-1}
    interior = domain_knots[1:-1]
    random = domain_knots[0] + (domain_knots[-1] - domain_knots[0]) * rng.uniform(size=N_RANDOM_TIMES)
    times = np.unique(np.concatenate([domain_knots, np.nextafter(interior, -np.inf), np.nextafter(interior, np.inf),
                                      random]))
    data = {"description": f"{name}: random spline on uneven knots ({low}..{high} s apart) at TUM-like stamps, "
                           f"seed {SEED + 1}, n_ctrl={n_ctrl}, relative rotations <= {max_angle} rad",
            "representation": "split", "knots": knot_vector.tolist(), "rotvecs": rotvecs.tolist(),
            "translations": translations.tolist(), "times": times.tolist()}
    data.update(conformance.evaluate_input(data, name))
    return name, data


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").partition("\n")[0])
    default_out = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tsslam_ref", "assets", "spline_vectors")
    parser.add_argument("--out", default=default_out)
    parser.add_argument("--force", action="store_true", help="overwrite existing vector files")
    args = parser.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    rng = np.random.default_rng(SEED)
    vectors = {}
    for name, convention, n_ctrl, dt, t0, max_angle, scale in RANDOM_SPLINES:
        rotvecs, translations = random_control_points(rng, n_ctrl, max_angle, scale)
        times = query_times(rng, n_ctrl, dt, t0, convention)
        description = (f"{name}: random spline, seed {SEED}, n_ctrl={n_ctrl}, relative rotations <= {max_angle} rad")
        vectors[name] = make_vector(convention, dt, t0, rotvecs, translations, times, description)
    golden_times = np.unique(np.concatenate([BASALT_GOLDEN_TIMES, query_times(rng, 6, 0.5, 0.0, "basalt")]))
    vectors["basalt_golden_dt0.5"] = make_vector(
        "basalt", 0.5, 0.0, BASALT_GOLDEN_ROTVECS, BASALT_GOLDEN_TRANSLATIONS, golden_times,
        "basalt_golden_dt0.5: the knots of the basalt golden table (tsslam_ref/assets/spline_kit.md); our values "
        "at t = 0, 0.35, 0.8, 1.2 s agree with basalt-headers' to the table's 9 digits")
    for name, convention, n_ctrl, dt, t0, max_angle, scale in SE3_SPLINES:
        rotvecs, translations = random_control_points(rng, n_ctrl, max_angle, scale)
        times = query_times(rng, n_ctrl, dt, t0, convention)
        description = (f"{name}: random JOINT SE(3) spline (PyPose pp.bspline, Sophus), seed {SEED}, "
                       f"n_ctrl={n_ctrl}, relative rotations <= {max_angle} rad")
        vectors[name] = make_vector(convention, dt, t0, rotvecs, translations, times, description, "se3")
    name, convention, n_ctrl, dt, t0, max_angle, scale = JACOBIAN_SPLINE
    rotvecs, translations = random_control_points(rng, n_ctrl, max_angle, scale)
    t_min, t_max = spline.valid_time_range(n_ctrl, dt, t0, convention)
    knots = t0 + dt * np.arange(2, n_ctrl, dtype=np.float64)
    times = np.unique(np.concatenate([knots, t_min + (t_max - t_min) * rng.uniform(size=N_JACOBIAN_TIMES)]))
    description = (f"{name}: random spline with analytic Jacobians w.r.t. the 4 active control points "
                   f"(R_k <- Exp(delta) R_k, P_k <- P_k + tau; output R <- Exp(eps) R), seed {SEED}")
    vectors[name] = make_vector(convention, dt, t0, rotvecs, translations, times, description, jacobians=True)
    name, data = knot_vector()
    vectors[name] = data
    paths = {name: os.path.join(args.out, name + ".json") for name in vectors}
    foreign = [path for name, path in paths.items()
               if os.path.exists(path) and not args.force and not _written_here(path, name)]
    if foreign:  # checked before any file is written: all or none
        print(f"error: {foreign[0]} exists and was not written by this script ({len(foreign)} such file(s) in "
              f"{args.out}); pass --force to overwrite", file=sys.stderr)
        return 2
    for name, data in vectors.items():
        spline_kit.write_json_atomic(paths[name], data, force=True)
        print(f"{paths[name]}: {len(data['times'])} times, {os.path.getsize(paths[name]) / 1024:.0f} KiB")
    return 0


def _written_here(path: str, name: str) -> bool:
    """Whether ``path`` holds vector ``name`` as this script writes it (its description starts with
    the name): a re-run replaces its own files, not a file of someone else's of the same name."""
    try:
        with open(path) as stream:
            data = json.load(stream)
    except (OSError, ValueError):
        return False
    return isinstance(data, dict) and str(data.get("description", "")).startswith(f"{name}:")


if __name__ == "__main__":
    sys.exit(main())
