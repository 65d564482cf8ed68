"""Benchmark: spline pose + all derivatives (Eq. 5-9) at many times, vs two baselines in the same run.

Prints throughput (times per second) of :func:`tsslam_ref.spline.evaluate` with ``derivatives=2``
in float32 and float64, and ratios to, measured in the same run:

(a) derivatives by autograd through time (forward mode, ``torch.func.jvp`` twice) on a
    subsample, scaled per time;  target: closed form >= 5x faster;
(b) PyPose ``pp.bspline`` producing poses only (joint SE(3), no derivatives) for the same number
    of samples;  target: ours (pose + derivatives) at least as fast.

Usage: python benchmarks/bench_spline.py [--n 1000000] [--chunk 131072] [--threads 2]
Timings depend on machine load; report them with that caveat.
"""

import time

import numpy as np
import pypose as pp
import torch
from scipy.spatial.transform import Rotation

from tsslam_ref import spline
from tsslam_ref.geometry import so3_exp, vee
from tsslam_ref.cli_args import OneLineParser, number_in


def random_control_points(n_ctrl: int, dtype: torch.dtype, seed: int = 0):
    rng = np.random.default_rng(seed)
    steps = torch.as_tensor(rng.normal(scale=0.1, size=(n_ctrl, 3)))
    rotations = [so3_exp(steps[0])]
    for k in range(1, n_ctrl):
        rotations.append(rotations[-1] @ so3_exp(steps[k]))
    translations = torch.as_tensor(np.cumsum(rng.normal(scale=0.05, size=(n_ctrl, 3)), axis=0))
    return torch.stack(rotations).to(dtype), translations.to(dtype)


def best_of(function, repeats: int = 3) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - start)
    return best


def ours(R, P, times, dt, chunk):
    for begin in range(0, times.shape[0], chunk):
        spline.evaluate(R, P, times[begin:begin + chunk], dt, 0.0, derivatives=2)


def autograd_in_time(R, P, times, dt):
    t = torch.as_tensor(times)
    ones = torch.ones_like(t)

    def pose(x):
        sample = spline.evaluate(R, P, x, dt, 0.0)
        return sample.rotation, sample.translation

    def first(x):
        return torch.func.jvp(pose, (x,), (ones,))

    (R_t, _), (R_dot, _) = first(t)
    _, (_, (R_ddot, _)) = torch.func.jvp(first, (t,), (ones,))
    Rt = R_t.transpose(-1, -2)
    return vee(Rt @ R_dot), vee(Rt @ R_ddot)


def main() -> None:
    parser = OneLineParser(description=(__doc__ or "").partition("\n")[0])
    parser.add_argument("--n", type=number_in("--n", 1, 1000000000, integer=True), default=1_000_000, help="number of query times")
    parser.add_argument("--chunk", type=number_in("--chunk", 1, 1000000000, integer=True), default=131072, help="times per evaluate call (memory bound)")
    parser.add_argument("--n-ctrl", type=number_in("--n-ctrl", 4, 10**7, integer=True), default=1000)
    parser.add_argument("--autograd-fraction", type=number_in("--autograd-fraction", 0, 1, low_open=True), default=0.01, help="subsample for baseline (a)")
    parser.add_argument("--threads", type=number_in("--threads", 1, 1024, integer=True), default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    dt = 0.03
    rng = np.random.default_rng(1)
    if args.n < args.n_ctrl - 2:  # PyPose's interval (N - 3) / n must stay below 1
        parser.error(f"--n {args.n} must be at least --n-ctrl - 2 = {args.n_ctrl - 2} (PyPose samples each of the "
                     f"{args.n_ctrl - 3} segments at least once)")
    t_min, t_max = spline.valid_time_range(args.n_ctrl, dt, 0.0)
    times = np.sort(rng.uniform(t_min, t_max, size=args.n))
    n_sub = max(1000, int(args.n * args.autograd_fraction))
    print(f"torch {torch.__version__}, {torch.get_num_threads()} threads, n={args.n:,} times, "
          f"n_ctrl={args.n_ctrl}, chunk={args.chunk:,}")
    for dtype in (torch.float32, torch.float64):
        R, P = random_control_points(args.n_ctrl, dtype)
        ours(R, P, times[:1000], dt, args.chunk)  # warm-up
        t_ours = best_of(lambda: ours(R, P, times, dt, args.chunk))
        autograd_in_time(R, P, times[:1000], dt)  # warm-up
        sub = times[:: max(1, args.n // n_sub)][:n_sub]
        t_auto = best_of(lambda: autograd_in_time(R, P, sub, dt)) * args.n / sub.shape[0]
        quats = Rotation.from_matrix(R.double().numpy()).as_quat()
        data = pp.SE3(torch.as_tensor(np.concatenate([P.double().numpy(), quats], -1)).to(dtype))
        interval = (args.n_ctrl - 3) / args.n  # (N-3)/interval + 1 ≈ n poses
        poses = pp.bspline(data, interval=interval)
        t_pypose = best_of(lambda: pp.bspline(data, interval=interval))
        name = str(dtype).replace("torch.", "")
        print(f"\n[{name}]")
        print(f"  ours, pose + v, a, omega, omegadot : {t_ours:8.3f} s  {args.n / t_ours / 1e6:7.3f} M times/s")
        print(f"  (a) autograd-in-time (scaled from {sub.shape[0]:,}): {t_auto:8.3f} s  ratio {t_auto / t_ours:6.1f}x "
              f"(target >= 5x)")
        print(f"  (b) PyPose pp.bspline, poses only ({poses.shape[-2]:,}): {t_pypose:8.3f} s  ratio "
              f"{t_pypose / t_ours:6.2f}x (target >= 1x)")


if __name__ == "__main__":
    main()
