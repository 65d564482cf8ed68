"""A procedural indoor room (analytic SDF + smooth texture) rendered along real or built-in motion.

Synthetic data for TS-SLAM experiments (paper §IV-A uses the NeuralRGBD synthetic scenes; this is a
small, license-free stand-in with exact ground truth).  Side layer: imports the
:mod:`tsslam_ref.datasets` camera model and TUM readers/writers.  Documented in docs/data.md; taught in
notebooks/00_data_and_cameras.ipynb.

* **Scene.** World frame z up, metres.  A 4 x 3 x 2.5 m room seen from inside
  (x in [-2, 2], y in [-1.5, 1.5], z in [0, 2.5]) holding boxes, spheres and vertical cylinders.
  The SDF is positive in free space: sdf(p) = min(-box_room(p), objects(p)).  Exact for each
  primitive; the min is exact outside all objects (enough for sphere tracing).
* **Texture.** Albedo = per-primitive base colour x (0.55 + 0.45 w(p)), w in [0, 1] the mean of four
  sinusoids in 3-D per channel, mapped from [-1, 1], with periods 0.4-2 m: smooth gradients
  everywhere, view independent, so photometric tracking has signal and colours agree exactly
  between views.
* **Rendering.** Sphere tracing of one ray per pixel centre (pixel centres at integer
  coordinates, OpenCV axes); depth is the camera z of the hit point.
* **Depth noise** (unless ``clean``), in the spirit of NeuralRGBD's simulated Kinect depth: axial
  Gaussian noise sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2 m (Nguyen et al., 3DIMPVT 2012), no depth
  where the incidence angle exceeds ~78 deg (|cos| < 0.2), 80 % of the pixels at depth edges
  (3x3 neighbourhood spread > 5 % of z) dropped, and 0.5 % random dropouts.
* **Trajectories.** A TUM-format file (real hand-held motion) is resampled at the frame times
  (positions linear, rotations slerp) and moved into the room by ONE rigid transform applied on
  the left, T_wc'(t) = T_place T_wc(t) with T_place chosen so that the first pose becomes
  ``START_POSITION`` (room centre, 1.3 m high) and ``START_ROTATION`` (looking along +x, tilted
  down by atan(0.15) = 8.5 deg).  The motion (speeds, accelerations, body-frame rotation rates)
  is unchanged.  For TUM-VI (IMU body frame) pass ``body_to_camera``.

| symbol | variable | shape | frame / unit |
|---|---|---|---|
| p | ``points`` | (N, 3) | world, m |
| sdf(p) | ``sdf`` | (N,) | m, > 0 in free space |
| T_wc | ``c2w`` | (4, 4) | camera-to-world, OpenCV axes |
"""

import contextlib
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Optional, Sequence, Tuple

import imageio.v3 as iio
import numpy as np
import torch

from tsslam_ref.datasets.intrinsics import Intrinsics, pixel_rays
from tsslam_ref.files import normal_folder
from tsslam_ref.datasets.tum_format import interpolate_poses, read_tum_trajectory, write_tum_trajectory

SEQUENCE_ENTRIES = frozenset({"rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "intrinsics.json",
                              "gt_mesh.ply", "scene.json"})
"""What :func:`synthesize` writes into its folder, and all that ``--force`` may replace."""
ROOM_MIN = (-2.0, -1.5, 0.0)
ROOM_MAX = (2.0, 1.5, 2.5)
DEFAULT_BOXES = (  # (centre xyz, half extents xyz, base colour rgb)
    ((1.2, 0.7, 0.375), (0.5, 0.35, 0.375), (0.75, 0.55, 0.35)),  # table
    ((-1.55, -0.9, 0.6), (0.35, 0.5, 0.6), (0.35, 0.55, 0.75)),  # cabinet
    ((0.3, -1.35, 1.4), (0.6, 0.15, 0.1), (0.8, 0.8, 0.5)),  # wall shelf
)
DEFAULT_SPHERES = (  # (centre xyz, radius, colour)
    ((1.1, 0.6, 0.95), 0.2, (0.9, 0.3, 0.3)),
    ((-0.9, 1.0, 0.3), 0.3, (0.3, 0.8, 0.4)),
)
DEFAULT_CYLINDERS = (  # (axis x, y, z_min, z_max, radius, colour); vertical
    ((1.4, -0.9, 0.0, 1.1), 0.25, (0.6, 0.4, 0.8)),
    ((-1.5, 1.0, 0.0, 1.6), 0.15, (0.9, 0.7, 0.2)),
)
ROOM_COLOUR = (0.85, 0.85, 0.8)
START_POSITION = (0.0, 0.0, 1.3)
"""Where a real trajectory's first camera is placed (world, m)."""
MIN_CLEARANCE = 0.15
"""Camera centres closer than this (m) to a surface are rejected (the camera would be in a wall)."""
HIT_TOLERANCE = 1e-3
"""A traced ray counts as a hit when |sdf| at its end is below this (m)."""
MAX_RESAMPLE_GAP = 0.1
"""Largest trajectory sample gap (s) bridged by interpolation when resampling at frame times."""
DEPTH_PNG_SCALE = 5000.0


@contextlib.contextmanager
def _one_intra_op_thread():
    """Run the tracing loop on one intra-op thread, restoring the previous setting afterwards.

    Sphere tracing is hundreds of small element-wise ops (<= 19,200 rays); on the shared 2-core
    machine two threads made a 80x60 render 5-15x slower (0.16 s -> 1-2.5 s) through thread
    synchronisation, so one thread is both simpler and faster here.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def look_rotation(forward: Sequence[float], up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world rotation (3, 3) of an OpenCV camera looking along ``forward`` with world ``up``.

    Columns: x_c = forward x up (right), y_c = z_c x x_c (down), z_c = forward.
    """
    z = np.asarray(forward, dtype=np.float64)
    z = z / np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        raise ValueError(f"forward {forward} is parallel to up {up}")
    x /= np.linalg.norm(x)
    return np.stack([x, np.cross(z, x), z], axis=1)


START_ROTATION = look_rotation((1.0, 0.0, -0.15))
"""First camera's orientation: looking along +x, slightly down."""


def _box_sdf(points: torch.Tensor, centres: torch.Tensor, halves: torch.Tensor) -> torch.Tensor:
    """Exact SDF of axis-aligned boxes.  (N, 3), (B, 3), (B, 3) -> (N, B)."""
    q = (points[:, None, :] - centres).abs() - halves  # (N, B, 3)
    outside = torch.linalg.vector_norm(q.clamp(min=0.0), dim=-1)
    inside = q.amax(dim=-1).clamp(max=0.0)
    return outside + inside


def _sphere_sdf(points: torch.Tensor, centres: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """Exact SDF of spheres.  (N, 3), (S, 3), (S,) -> (N, S)."""
    return torch.linalg.vector_norm(points[:, None, :] - centres, dim=-1) - radii


def _cylinder_sdf(points: torch.Tensor, axes: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
    """Exact SDF of vertical capped cylinders, axes rows (x, y, z_min, z_max).  (N, 3), (C, 4), (C,) -> (N, C)."""
    radial = torch.linalg.vector_norm(points[:, None, :2] - axes[:, :2], dim=-1) - radii  # (N, C)
    axial = (points[:, None, 2] - 0.5 * (axes[:, 2] + axes[:, 3])).abs() - 0.5 * (axes[:, 3] - axes[:, 2])
    d = torch.stack([radial, axial], dim=-1)  # (N, C, 2)
    return torch.linalg.vector_norm(d.clamp(min=0.0), dim=-1) + d.amax(dim=-1).clamp(max=0.0)


class ProceduralRoom:
    """Analytic indoor scene: room box seen from inside plus boxes, spheres, vertical cylinders.

    Args:
        boxes, spheres, cylinders: primitive lists (see the DEFAULT_* constants for the format).
        seed: seeds the texture's wave directions and phases (numpy ``default_rng``).
    """

    def __init__(self, boxes=DEFAULT_BOXES, spheres=DEFAULT_SPHERES, cylinders=DEFAULT_CYLINDERS, seed: int = 0):
        self.boxes, self.spheres, self.cylinders = tuple(boxes), tuple(spheres), tuple(cylinders)
        self.room_centre = tuple(0.5 * (a + b) for a, b in zip(ROOM_MIN, ROOM_MAX))
        self.room_half = tuple(0.5 * (b - a) for a, b in zip(ROOM_MIN, ROOM_MAX))
        self.colours = np.asarray([ROOM_COLOUR] + [b[2] for b in self.boxes] + [s[2] for s in self.spheres]
                                  + [c[2] for c in self.cylinders], dtype=np.float64)  # (P, 3)
        rng = np.random.default_rng(seed)
        directions = rng.normal(size=(3, 4, 3))
        directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
        wavenumbers = rng.uniform(2 * math.pi / 2.0, 2 * math.pi / 0.4, size=(3, 4, 1))  # rad/m
        self.wave_vectors = directions * wavenumbers  # (3 channels, 4 waves, 3)
        self.wave_phases = rng.uniform(0, 2 * math.pi, size=(3, 4))
        self.seed = seed
        self._cache = {}

    @property
    def bound(self) -> np.ndarray:
        """(3, 2) [[xmin, xmax], [ymin, ymax], [zmin, zmax]] of the room, metres."""
        return np.stack([np.asarray(ROOM_MIN), np.asarray(ROOM_MAX)], axis=1)

    def _tensors(self, like: torch.Tensor) -> dict:
        """Primitive parameters as tensors on ``like``'s dtype and device (cached)."""
        key = (like.dtype, like.device)
        if key not in self._cache:
            as_tensor = lambda values, width: like.new_tensor(np.asarray(values, dtype=np.float64).reshape(-1, width))
            self._cache[key] = {
                "room": (as_tensor([self.room_centre], 3), as_tensor([self.room_half], 3)),
                "boxes": (as_tensor([b[0] for b in self.boxes], 3), as_tensor([b[1] for b in self.boxes], 3)),
                "spheres": (as_tensor([s[0] for s in self.spheres], 3), as_tensor([s[1] for s in self.spheres], 1)[:, 0]),
                "cylinders": (as_tensor([c[0] for c in self.cylinders], 4), as_tensor([c[1] for c in self.cylinders], 1)[:, 0]),
                "colours": like.new_tensor(self.colours),
                "wave_vectors": like.new_tensor(self.wave_vectors),
                "wave_phases": like.new_tensor(self.wave_phases),
            }
        return self._cache[key]

    def primitive_sdfs(self, points: torch.Tensor) -> torch.Tensor:
        """SDF of every primitive (room first).  (N, 3) -> (N, P), positive outside each object."""
        p = self._tensors(points)
        return torch.cat([
            -_box_sdf(points, *p["room"]),
            _box_sdf(points, *p["boxes"]),
            _sphere_sdf(points, *p["spheres"]),
            _cylinder_sdf(points, *p["cylinders"]),
        ], dim=-1)  # (N, P)

    def sdf(self, points: torch.Tensor) -> torch.Tensor:
        """Signed distance (m), > 0 in free space.  (N, 3) -> (N,); dtype/device of ``points``."""
        if points.ndim != 2 or points.shape[-1] != 3:
            raise ValueError(f"sdf expects points of shape (N, 3), got {tuple(points.shape)}")
        return self.primitive_sdfs(points).amin(dim=-1)

    def color(self, points: torch.Tensor) -> torch.Tensor:
        """Albedo in [0, 1] of the nearest primitive's surface.  (N, 3) -> (N, 3)."""
        p = self._tensors(points)
        nearest = self.primitive_sdfs(points).abs().argmin(dim=-1)  # (N,)
        base = p["colours"][nearest]  # (N, 3)
        phase = torch.einsum("cwk,nk->ncw", p["wave_vectors"], points)  # (N, 3, 4)
        wave = torch.sin(phase + p["wave_phases"]).mean(dim=-1)  # (N, 3) in [-1, 1]
        return (base * (0.55 + 0.45 * (0.5 + 0.5 * wave))).clamp(0.0, 1.0)

    def normal(self, points: torch.Tensor, step: float = 1e-4) -> torch.Tensor:
        """Unit SDF gradient by central differences.  (N, 3) -> (N, 3)."""
        offsets = torch.eye(3, dtype=points.dtype, device=points.device) * step  # (3, 3)
        plus = self.sdf((points[:, None, :] + offsets).reshape(-1, 3)).reshape(-1, 3)
        minus = self.sdf((points[:, None, :] - offsets).reshape(-1, 3)).reshape(-1, 3)
        return torch.nn.functional.normalize(plus - minus, dim=-1)

    def mesh(self, voxel: float = 0.03):
        """Ground-truth surface by marching cubes (scikit-image) of the SDF on a grid of ``voxel`` m.

        Returns a ``trimesh.Trimesh`` in world metres, normals pointing into free space, vertex
        colours from :meth:`color`.
        """
        import trimesh
        from skimage.measure import marching_cubes

        low, high = self.bound[:, 0] - 2 * voxel, self.bound[:, 1] + 2 * voxel
        axes = [np.arange(lo, hi + 0.5 * voxel, voxel) for lo, hi in zip(low, high)]
        grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1)  # (X, Y, Z, 3)
        with torch.no_grad():
            values = self.sdf(torch.from_numpy(grid.reshape(-1, 3))).numpy().reshape(grid.shape[:3])
        vertices, faces, _, _ = marching_cubes(values, level=0.0, spacing=(voxel, voxel, voxel))
        vertices = vertices + low
        mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
        with torch.no_grad():
            centres = torch.from_numpy(np.array(mesh.triangles_center))
            agreement = (self.normal(centres).numpy() * mesh.face_normals).sum(-1).mean()
            colours = self.color(torch.from_numpy(vertices)).numpy()
        if agreement < 0:
            mesh.invert()
        mesh.visual.vertex_colors = np.concatenate(
            [np.round(colours * 255), np.full((len(vertices), 1), 255)], axis=1
        ).astype(np.uint8)
        return mesh


def trace(scene, origins: torch.Tensor, directions: torch.Tensor, max_steps: int = 256, epsilon: float = 1e-6,
          far: float = 20.0) -> Tuple[torch.Tensor, torch.Tensor]:
    """Sphere tracing: march t <- t + sdf(o + t d) until sdf < epsilon.

    Args:
        origins: (N, 3) world, in free space.  directions: (N, 3) unit, world.

    Returns:
        t (N,) distance along the ray (m) and hit (N,) bool (|sdf| < HIT_TOLERANCE, t < far).
    """
    t = torch.zeros(origins.shape[0], dtype=origins.dtype, device=origins.device)
    active = torch.arange(origins.shape[0], device=origins.device)
    for _ in range(max_steps):
        if active.numel() == 0:
            break
        step = scene.sdf(origins[active] + t[active, None] * directions[active])  # (n_active,)
        t[active] = t[active] + step
        active = active[(step > epsilon) & (t[active] < far)]
    residual = scene.sdf(origins + t[:, None] * directions).abs()
    return t, (residual < HIT_TOLERANCE) & (t < far)


def _depth_noise(depth: torch.Tensor, cos_incidence: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Kinect-like noise on a clean (H, W) depth map; 0 stays 0.  See the module docstring."""
    sigma = 0.0012 + 0.0019 * (depth - 0.4) ** 2
    noisy = depth + sigma * torch.randn(depth.shape, generator=generator, dtype=depth.dtype)
    padded = torch.nn.functional.pad(depth[None, None], (1, 1, 1, 1), mode="replicate")
    spread = (torch.nn.functional.max_pool2d(padded, 3, stride=1) + torch.nn.functional.max_pool2d(-padded, 3, stride=1))[0, 0]
    edge = spread > 0.05 * depth
    drop = (cos_incidence < 0.2) | (edge & (torch.rand(depth.shape, generator=generator, dtype=depth.dtype) < 0.8))
    drop |= torch.rand(depth.shape, generator=generator, dtype=depth.dtype) < 0.005
    return torch.where(drop | (depth <= 0), torch.zeros_like(noisy), noisy.clamp(min=0.0))


def render_rgbd(scene, c2w, intrinsics: Intrinsics, clean: bool = True, generator: Optional[torch.Generator] = None,
                max_steps: int = 256) -> Tuple[np.ndarray, np.ndarray]:
    """Render colour and depth of ``scene`` from camera pose ``c2w`` by sphere tracing.

    Args:
        scene: object with ``sdf`` and ``color`` ((N, 3) -> (N,), (N, 3)), e.g. ProceduralRoom.
        c2w: (4, 4) camera-to-world, OpenCV axes (numpy or torch; computed in float64 on its device).
        intrinsics: pinhole camera; one ray through each pixel centre (integers).
        clean: False adds the depth noise of the module docstring (needs ``generator``).

    Returns:
        rgb (H, W, 3) float32 in [0, 1] and depth (H, W) float32 metres (camera z; 0 = no hit).
    """
    device = c2w.device if isinstance(c2w, torch.Tensor) else None
    pose = torch.as_tensor(np.asarray(c2w.cpu() if isinstance(c2w, torch.Tensor) else c2w), dtype=torch.float64, device=device)
    if pose.shape != (4, 4):
        raise ValueError(f"c2w must be (4, 4), got {tuple(pose.shape)}")
    rays_cam = torch.as_tensor(pixel_rays(intrinsics), device=device).reshape(-1, 3)  # (H*W, 3) float64
    norms = torch.linalg.vector_norm(rays_cam, dim=-1)  # (H*W,)
    directions = (rays_cam / norms[:, None]) @ pose[:3, :3].T  # (H*W, 3) world
    origins = pose[:3, 3].expand_as(directions)
    with torch.no_grad(), _one_intra_op_thread():
        t, hit = trace(scene, origins, directions, max_steps=max_steps)
        points = origins + t[:, None] * directions  # (H*W, 3)
        rgb = torch.where(hit[:, None], scene.color(points), torch.zeros_like(points))
        depth = torch.where(hit, t / norms, torch.zeros_like(t))  # camera z
        shape = (intrinsics.height, intrinsics.width)
        depth = depth.reshape(shape)
        if not clean:
            if generator is None:
                raise ValueError("render_rgbd(clean=False) needs a torch.Generator for the depth noise")
            cos_incidence = (scene.normal(points) * directions).sum(-1).abs().reshape(shape)
            # noise is drawn on the CPU with the caller's CPU generator: identical on every device
            depth = _depth_noise(depth.cpu(), cos_incidence.cpu(), generator)
    return rgb.reshape(*shape, 3).cpu().numpy().astype(np.float32), depth.cpu().numpy().astype(np.float32)


def builtin_trajectory(times: np.ndarray) -> np.ndarray:
    """Smooth default path: an ellipse of 0.4 x 0.3 m at ~1.3 m height, one turn per 12 s, looking
    outwards with gentle yaw and pitch oscillations.  (N,) s -> (N, 4, 4) camera-to-world."""
    times = np.asarray(times, dtype=np.float64)
    angle = 2 * math.pi * times / 12.0
    poses = np.zeros((len(times), 4, 4))
    for n, (a, t) in enumerate(zip(angle, times)):
        yaw = a + 0.25 * math.sin(1.3 * t)
        pitch = -0.15 + 0.08 * math.sin(0.9 * t)
        forward = (math.cos(yaw) * math.cos(pitch), math.sin(yaw) * math.cos(pitch), math.sin(pitch))
        poses[n, :3, :3] = look_rotation(forward)
        poses[n, :3, 3] = (0.4 * math.cos(a), 0.3 * math.sin(a), 1.3 + 0.1 * math.sin(2 * a))
        poses[n, 3, 3] = 1.0
    return poses


def resample_trajectory(path, n_frames: int, fps: float, start_time: Optional[float] = None,
                        body_to_camera: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
    """Poses of a TUM-format trajectory at ``start + k / fps`` (linear positions, slerp rotations).

    Duplicate stamps keep their first line.  ``body_to_camera`` (4, 4) is right-multiplied
    (T_wc = T_wb T_bc) for body-frame trajectories such as TUM-VI.

    Returns:
        frame times (n_frames,) float64 s (dataset time) and poses (n_frames, 4, 4).

    Raises:
        ValueError: naming the file and the first frame time that falls outside the trajectory or
            in a gap longer than MAX_RESAMPLE_GAP.
    """
    stamps, poses = read_tum_trajectory(path)
    unique = np.concatenate([[True], np.diff(stamps) > 0])
    stamps, poses = stamps[unique], poses[unique]
    start = stamps[0] if start_time is None else float(start_time)
    times = start + np.arange(n_frames, dtype=np.float64) / fps
    resampled = interpolate_poses(times, stamps, poses, max_gap=MAX_RESAMPLE_GAP)
    bad = ~np.isfinite(resampled).all(axis=(1, 2))
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{path}: no pose for frame {first} at t={times[first]:.6f} s (trajectory covers "
            f"{stamps[0]:.6f}..{stamps[-1]:.6f} s, gaps > {MAX_RESAMPLE_GAP} s are not bridged); "
            f"choose another start_time or fewer frames"
        )
    if body_to_camera is not None:
        resampled = resampled @ np.asarray(body_to_camera, dtype=np.float64)
    return times, resampled


def place_in_room(poses: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Left-multiply all poses by the rigid T_place that maps the first pose to the start pose.

    T_place = T_start T_0^-1 with T_start = (START_ROTATION, START_POSITION).  (N, 4, 4) ->
    ((N, 4, 4), T_place (4, 4)).  Relative motion between any two frames is unchanged.
    """
    start = np.eye(4)
    start[:3, :3], start[:3, 3] = START_ROTATION, START_POSITION
    first_inverse = np.eye(4)
    first_inverse[:3, :3] = poses[0, :3, :3].T
    first_inverse[:3, 3] = -poses[0, :3, :3].T @ poses[0, :3, 3]
    place = start @ first_inverse
    return place @ poses, place


def default_intrinsics(width: int, height: int) -> Intrinsics:
    """Kinect-like field of view (fx = fy = 525 / 640 * width), principal point at the image centre."""
    focal = 525.0 / 640.0 * width
    return Intrinsics(focal, focal, (width - 1) / 2.0, (height - 1) / 2.0, width, height)


def _writable_output(out_dir, overwrite: bool) -> Path:
    """``out_dir`` as an absolute path ('.' has no parent to build the new folder in beside it),
    refused when non-empty without ``overwrite`` or when it is, or holds, the current folder."""
    out = Path(out_dir).absolute()
    if out.exists() and (not out.is_dir() or any(out.iterdir())) and not overwrite:
        raise FileExistsError(f"{out} exists and is not empty; pass overwrite=True (--force) to replace it")
    here = Path.cwd().resolve()
    if out.resolve() == here or out.resolve() in here.parents:
        raise ValueError(f"{out_dir} is the current folder or holds it: replacing it would delete the folder this "
                         f"process works in; choose a folder beside it")
    return out


def synthesize(out_dir, trajectory=None, n_frames: int = 60, width: int = 160, height: int = 120, fps: float = 30.0,
               seed: int = 0, clean_depth: bool = False, overwrite: bool = False, mesh_voxel: float = 0.03,
               start_time: Optional[float] = None, body_to_camera: Optional[np.ndarray] = None) -> Path:
    """Render a synthetic sequence in TUM layout that :func:`tsslam_ref.data.load_sequence` reads back.

    Writes rgb.txt, depth.txt, groundtruth.txt (poses at the frame times), rgb/*.png, depth/*.png
    (16-bit, metres x 5000), intrinsics.json (read by the TUM loader instead of the fr3 defaults),
    scene.json (bound, intrinsics, placement, settings) and gt_mesh.ply.  Built in a temporary
    folder, then renamed into place.

    Args:
        out_dir: output folder; an existing non-empty one needs ``overwrite``.
        trajectory: TUM-format file (resampled and placed in the room) or None for the built-in path.
        n_frames, width, height, fps: sequence size; seed: texture and noise seed.
        clean_depth: True writes noise-free depth.  mesh_voxel: marching-cubes voxel (m).

    Raises:
        FileExistsError: ``out_dir`` is non-empty and ``overwrite`` is False.
        ValueError: bad sizes, a trajectory that leaves the room's free space, or ``out_dir`` the
            current folder or one holding it.
    """
    out = _writable_output(out_dir, overwrite)
    if n_frames < 1 or width < 8 or height < 8 or not fps > 0:
        raise ValueError(f"need n_frames >= 1, width/height >= 8, fps > 0; got {n_frames}, {width}x{height}, {fps}")
    scene = ProceduralRoom(seed=seed)
    intrinsics = default_intrinsics(width, height)
    if trajectory is None:
        times = np.arange(n_frames, dtype=np.float64) / fps
        poses, place, source = builtin_trajectory(times), np.eye(4), "builtin"
    else:
        times, raw = resample_trajectory(trajectory, n_frames, fps, start_time, body_to_camera)
        (poses, place), source = place_in_room(raw), str(trajectory)
    clearance = scene.sdf(torch.from_numpy(poses[:, :3, 3].copy())).numpy()
    if clearance.min() < MIN_CLEARANCE:
        bad = int(np.argmin(clearance))
        raise ValueError(
            f"trajectory {source}: frame {bad} puts the camera {clearance[bad]:.2f} m from a surface "
            f"(need >= {MIN_CLEARANCE} m; the room is {ROOM_MIN}..{ROOM_MAX}); use fewer frames or another start_time"
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    # the parent as the system finds it ('link/..' goes up from the link's target, not as text)
    temporary = normal_folder(tempfile.mkdtemp(dir=os.path.realpath(out.parent), prefix=f".{out.name}."))
    try:
        _write_sequence(temporary, scene, intrinsics, times, poses, clean_depth, seed, mesh_voxel)
        settings = {"bound": scene.bound.tolist(), "intrinsics": intrinsics.to_dict(), "fps": fps, "seed": seed,
                    "n_frames": n_frames, "clean_depth": clean_depth, "trajectory": source,
                    "placement_T": place.tolist(), "depth_scale": DEPTH_PNG_SCALE, "mesh_voxel": mesh_voxel,
                    "world": "z up, metres; poses camera-to-world with OpenCV camera axes"}
        (temporary / "scene.json").write_text(json.dumps(settings, indent=2) + "\n")
        if out.exists():
            shutil.rmtree(out) if out.is_dir() else out.unlink()
        os.replace(temporary, out)
    except BaseException:
        shutil.rmtree(temporary, ignore_errors=True)
        raise
    return out


def _write_sequence(folder: Path, scene, intrinsics, times, poses, clean_depth, seed, mesh_voxel) -> None:
    (folder / "rgb").mkdir()
    (folder / "depth").mkdir()
    generator = torch.Generator().manual_seed(seed)
    rgb_lines = ["# color images (tsslam_ref synthetic room)", "# timestamp filename"]
    depth_lines = ["# depth maps (metres x 5000)", "# timestamp filename"]
    for stamp, pose in zip(times, poses):
        rgb, depth = render_rgbd(scene, pose, intrinsics, clean=clean_depth, generator=generator)
        name = f"{stamp:.6f}.png"
        iio.imwrite(folder / "rgb" / name, np.round(rgb * 255).astype(np.uint8))
        iio.imwrite(folder / "depth" / name, np.round(depth * DEPTH_PNG_SCALE).clip(0, 65535).astype(np.uint16))
        rgb_lines.append(f"{stamp:.6f} rgb/{name}")
        depth_lines.append(f"{stamp:.6f} depth/{name}")
    (folder / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (folder / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    write_tum_trajectory(folder / "groundtruth.txt", np.round(times, 6), poses)
    calibration = dict(intrinsics.to_dict(), depth_scale=DEPTH_PNG_SCALE)
    (folder / "intrinsics.json").write_text(json.dumps(calibration, indent=2) + "\n")
    scene.mesh(mesh_voxel).export(folder / "gt_mesh.ply")
