"""Interactive 3-D figures of the scene: point clouds, camera frusta, trajectories and meshes.

Course helper for the chapters (no equation of the paper of its own; it draws the quantities of
Sec. III: the camera poses T_wc, the back-projection p = T_wc (d K^-1 [u, v, 1]^T) behind Eq. (2)-(4),
the trajectory of Eq. (5)-(6) and the extracted mesh).  Each builder turns numpy or torch arrays
into one plotly trace; :func:`scene` puts traces into one figure with equal axes in metres;
:func:`show` displays it as ONE output holding two pictures of the same scene:

* ``application/vnd.plotly.v1+json``: the figure as JSON, rotated and zoomed by JupyterLab (the
  plotly extension that ships in plotly's wheel) and VS Code, offline, with no plotly.js embedded
  in the notebook;
* ``image/png``: a matplotlib rendering, which GitHub, nbviewer and plain viewers show.

Conventions: poses are camera-to-world (4, 4), camera axes are OpenCV's (x right, y down,
z forward), pixel centres sit at integer coordinates, so the image's outer corners are at
(-0.5, -0.5) and (W - 0.5, H - 0.5).  plotly is imported only when a figure is built.

| quantity | argument | shape | unit |
|---|---|---|---|
| points | ``points`` | (N, 3) | world, m |
| a value per point (depth, frame) | ``color`` | (N,) | any |
| an RGB colour per point | ``color`` | (N, 3) | [0, 1] |
| T_wc | ``poses`` | (M, 4, 4) | m |
| K | ``intrinsics`` | (3, 3) or (M, 3, 3) | pixels |
| camera positions | ``positions`` | (M, 3) or poses (M, 4, 4) | m |
| mesh | ``vertices``, ``faces`` | (V, 3), (F, 3) int | m, vertex index |
"""

import base64
import io
import json

import numpy as np

MIMETYPE = "application/vnd.plotly.v1+json"
DECIMALS = 4  # coordinates are stored to 0.1 mm: plain JSON lists any plotly.js version reads
COLORSCALES = {"Viridis": "viridis", "Turbo": "turbo", "Plasma": "plasma", "Cividis": "cividis",
               "Inferno": "inferno", "Magma": "magma"}
"""Colour scales drawn the same in both pictures: plotly name -> matplotlib name."""


def _graph_objects():
    """plotly.graph_objects, imported on first use, with a clear error when plotly is missing."""
    try:
        import plotly.graph_objects as go
    except ImportError as error:  # pragma: no cover - plotly is pinned in environment.txt
        raise ImportError("tsslam_ref.view3d needs plotly: pip install plotly "
                          "(the version pinned in environment.txt)") from error
    return go


def _array(value, name: str, shape: tuple) -> np.ndarray:
    """numpy / torch / list -> float64 numpy array checked against ``shape`` (None = any size)."""
    if hasattr(value, "detach"):
        value = value.detach().cpu().numpy()
    array = np.asarray(value, dtype=np.float64)
    fits = array.ndim == len(shape) and all(s is None or s == n for s, n in zip(shape, array.shape))
    if not fits:
        wanted = "(" + ", ".join("N" if s is None else str(s) for s in shape) + (",)" if len(shape) == 1 else ")")
        raise ValueError(f"{name} has shape {tuple(array.shape)}, expected {wanted}")
    if not np.isfinite(array).all():
        raise ValueError(f"{name} holds non-finite values (NaN or inf); drop them first")
    return array


def _rounded(array: np.ndarray) -> list:
    """Array -> nested list of floats rounded to DECIMALS (small, plain JSON)."""
    return np.round(array, DECIMALS).tolist()


def _colorscale(name: str) -> str:
    if name not in COLORSCALES:
        raise ValueError(f"colorscale = {name!r}, expected one of {sorted(COLORSCALES)}")
    return name


def subsample(count: int, max_points: int, seed: int = 0) -> np.ndarray:
    """Sorted indices of at most ``max_points`` of ``count`` items, the same for a seed. (K,) int."""
    if int(max_points) < 1:
        raise ValueError(f"max_points = {max_points} must be >= 1")
    if count <= max_points:
        return np.arange(count)
    return np.sort(np.random.default_rng(seed).choice(count, size=int(max_points), replace=False))


def point_cloud(points, color=None, *, name: str = "points", color_title: str = "",
                colorscale: str = "Viridis", max_points: int = 20000, size: float = 1.5,
                seed: int = 0):
    """A point cloud as a plotly Scatter3d trace, randomly thinned to ``max_points``.

    Args:
        points: (N, 3) world points in metres.
        color: None (one colour), (N,) values drawn with ``colorscale`` and a colour bar titled
            ``color_title`` (e.g. depth in m, or the frame index to colour by frame), or (N, 3)
            RGB in [0, 1].
        max_points: keep at most this many points (chosen with ``seed``) so notebooks stay small.
    """
    points = _array(points, "points", (None, 3))
    keep = subsample(len(points), max_points, seed)
    marker = {"size": float(size)}
    if color is not None:
        color = _array(color, "color", (len(points),) if np.ndim(color) == 1 else (len(points), 3))
        if color.ndim == 1:
            marker.update(color=_rounded(color[keep]), colorscale=_colorscale(colorscale),
                          showscale=True, colorbar={"title": {"text": color_title}})
        else:
            if color.min() < 0 or color.max() > 1:
                raise ValueError(f"RGB color must lie in [0, 1], got [{color.min()}, {color.max()}]")
            marker["color"] = [f"rgb({r},{g},{b})" for r, g, b in np.round(color[keep] * 255).astype(int)]
    x, y, z = _rounded(points[keep].T)
    return _graph_objects().Scatter3d(x=x, y=y, z=z, mode="markers", marker=marker, name=name,
                                      meta={"colorscale": colorscale})


def frustum_corners(poses, intrinsics, image_size, depth: float = 0.1) -> np.ndarray:
    """World coordinates of each camera's four image corners back-projected to ``depth`` metres.

    Corner pixels (u, v) = (-0.5, -0.5), (W - 0.5, -0.5), (W - 0.5, H - 0.5), (-0.5, H - 0.5)
    (the image's outer edge), p_c = depth K^-1 [u, v, 1]^T, p_w = R p_c + t.

    Args:
        poses: (M, 4, 4) camera-to-world; intrinsics: (3, 3) or (M, 3, 3); image_size: (W, H).
    Returns:
        (M, 4, 3) corners, in the order above.
    """
    poses = _array(poses, "poses", (None, 4, 4))
    intrinsics = _array(intrinsics, "intrinsics", (3, 3) if np.ndim(intrinsics) == 2 else (len(poses), 3, 3))
    width, height = (float(s) for s in image_size)
    if not (width > 0 and height > 0 and float(depth) > 0):
        raise ValueError(f"image_size = {tuple(image_size)} and depth = {depth} must be > 0")
    pixels = np.array([[-0.5, -0.5, 1.0], [width - 0.5, -0.5, 1.0],
                       [width - 0.5, height - 0.5, 1.0], [-0.5, height - 0.5, 1.0]])
    rays = np.linalg.solve(np.broadcast_to(intrinsics, (len(poses), 3, 3))[:, None],
                           pixels[None, :, :, None])[..., 0]  # (M, 4, 3), z = 1
    return np.einsum("mij,mkj->mki", poses[:, :3, :3], float(depth) * rays) + poses[:, None, :3, 3]


def camera_frusta(poses, intrinsics, image_size, *, depth: float = 0.1, name: str = "cameras",
                  color: str = "black", every: int = 1):
    """Camera frusta (apex at the camera centre, the image rectangle at ``depth`` m) as one
    line trace; the image's top edge is drawn as a small roof so "up" (-y) reads.

    Args:
        poses: (M, 4, 4) camera-to-world; intrinsics: (3, 3) or (M, 3, 3); image_size: (W, H);
        every: draw every ``every``-th camera.
    """
    if int(every) < 1:
        raise ValueError(f"every = {every} must be >= 1")
    poses = _array(poses, "poses", (None, 4, 4))
    if np.ndim(intrinsics) == 3:
        intrinsics = _array(intrinsics, "intrinsics", (len(poses), 3, 3))[::every]
    poses = poses[::every]
    corners = frustum_corners(poses, intrinsics, image_size, depth)
    roof = poses[:, :3, :3] @ np.array([0.0, -0.25 * depth, 0.0]) + 0.5 * (corners[:, 0] + corners[:, 1])
    nan = np.full((len(poses), 1, 3), np.nan)
    apex, c = poses[:, None, :3, 3], corners
    path = np.concatenate([apex, c[:, :1], c[:, 1:2], apex, c[:, 2:3], c[:, 3:4], apex, c[:, 3:4],
                           c[:, :1], roof[:, None], c[:, 1:2], c[:, 2:3], nan], axis=1).reshape(-1, 3)
    x, y, z = (np.where(np.isnan(a), None, np.round(a, DECIMALS)).tolist() for a in path.T)
    return _graph_objects().Scatter3d(x=x, y=y, z=z, mode="lines", name=name,
                                      line={"color": color, "width": 2}, connectgaps=False)


def trajectory(positions, *, name: str = "trajectory", color: str | None = None,
               width: float = 4.0, start_marker: bool = True):
    """A camera path as a line trace (with a marker at its first position).

    Args:
        positions: (M, 3) camera centres in metres, or (M, 4, 4) camera-to-world poses (their
            translations are used).
    """
    if np.ndim(positions) == 3:
        positions = _array(positions, "positions", (None, 4, 4))[:, :3, 3]
    positions = _array(positions, "positions", (None, 3))
    x, y, z = _rounded(positions.T)
    line = {"width": float(width)} if color is None else {"width": float(width), "color": color}
    mode = "lines+markers" if start_marker else "lines"
    marker = {"size": [6] + [0] * (len(positions) - 1), "color": color}
    return _graph_objects().Scatter3d(x=x, y=y, z=z, mode=mode, name=name, line=line, marker=marker)


def mesh(vertices, faces, vertex_colors=None, *, name: str = "mesh", color: str = "lightgrey",
         opacity: float = 1.0):
    """A triangle mesh as a plotly Mesh3d trace.

    Args:
        vertices: (V, 3) in metres; faces: (F, 3) vertex indices in [0, V);
        vertex_colors: None (one ``color``), or (V, 3) RGB / (V, 4) RGBA (alpha ignored) as
            floats in [0, 1] or as integers 0-255 (an integer array, as a read ``mesh.ply``'s
            ``visual.vertex_colors``, is taken as 0-255).
    """
    vertices = _array(vertices, "vertices", (None, 3))
    faces_f = _array(faces, "faces", (None, 3))
    if (faces_f != np.round(faces_f)).any() or faces_f.min(initial=0) < 0 or faces_f.max(initial=0) >= len(vertices):
        raise ValueError(f"faces must be integer indices in [0, {len(vertices)}), "
                         f"got range [{faces_f.min(initial=0)}, {faces_f.max(initial=0)}]")
    faces = faces_f.astype(np.int64)
    x, y, z = _rounded(vertices.T)
    i, j, k = faces.T.tolist()
    style = {"color": color}
    if vertex_colors is not None:
        integers = np.issubdtype(np.asarray(vertex_colors).dtype, np.integer)
        channels = np.shape(vertex_colors)[-1] if np.ndim(vertex_colors) == 2 else 3
        rgb = _array(vertex_colors, "vertex_colors", (len(vertices), 4 if channels == 4 else 3))[:, :3]
        rgb = rgb / 255.0 if integers or rgb.max(initial=0) > 1 else rgb
        style = {"vertexcolor": [f"rgb({r},{g},{b})" for r, g, b in np.round(rgb * 255).astype(int)]}
    return _graph_objects().Mesh3d(x=x, y=y, z=z, i=i, j=j, k=k, name=name, opacity=float(opacity),
                                   showlegend=True, flatshading=True, **style)


def scene(*traces, title: str = "", view: tuple = (25.0, -60.0), width: int = 720,
          height: int = 540):
    """Traces -> one plotly Figure: equal axes (aspectmode 'data'), axis titles in metres.

    Args:
        view: (elevation, azimuth) in degrees of the starting viewpoint, z up (matplotlib's
            convention; the PNG of :func:`show` uses the same).
    """
    go = _graph_objects()
    elevation, azimuth = np.radians(float(view[0])), np.radians(float(view[1]))
    eye = 2.0 * np.array([np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth),
                          np.sin(elevation)])
    axes = {f"{a}axis": {"title": {"text": f"{a} (m)"}} for a in "xyz"}
    figure = go.Figure(data=list(traces))
    figure.update_layout(
        title={"text": title}, width=int(width), height=int(height),
        margin={"l": 0, "r": 0, "t": 40 if title else 10, "b": 0},
        legend={"x": 0.0, "y": 1.0},
        scene={**axes, "aspectmode": "data",
               "camera": {"eye": dict(zip("xyz", eye.round(4).tolist())), "up": {"x": 0, "y": 0, "z": 1}}})
    figure.layout.meta = {"view": [float(view[0]), float(view[1])]}
    return figure


def _nan_gaps(values) -> np.ndarray:
    """A trace's coordinate list (None = a gap between line pieces) -> float array with NaN gaps."""
    return np.array([np.nan if v is None else v for v in values], dtype=np.float64)


def _draw_scatter(axes, trace, colormaps) -> None:
    """One Scatter3d trace onto matplotlib 3-D axes: markers as points, lines as polylines."""
    x, y, z = (_nan_gaps(trace[a]) for a in "xyz")
    if "lines" in trace.mode:
        axes.plot(x, y, z, color=trace.line.color or "tab:blue", linewidth=0.5 * (trace.line.width or 2),
                  label=trace.name)
        if "markers" in trace.mode:
            axes.scatter(x[:1], y[:1], z[:1], color=trace.line.color or "tab:blue", s=25)
        return
    color = trace.marker.color
    if isinstance(color, (tuple, list)) and color and isinstance(color[0], str):
        color = [tuple(int(c) / 255 for c in s[4:-1].split(",")) for s in color]
    elif isinstance(color, (tuple, list)):
        cmap = colormaps[COLORSCALES[_scale_name(trace)]]
        drawn = axes.scatter(x, y, z, c=np.asarray(color, dtype=np.float64), cmap=cmap, s=2,
                             depthshade=False, label=trace.name)
        axes.figure.colorbar(drawn, ax=axes, shrink=0.6, pad=0.08,
                             label=trace.marker.colorbar.title.text or None)
        return
    axes.scatter(x, y, z, c=color, s=2, depthshade=False, label=trace.name)


def _scale_name(trace) -> str:
    """The plotly name of a trace's colour scale (plotly stores the expanded scale)."""
    return trace.meta["colorscale"] if trace.meta else "Viridis"


def _draw_mesh(axes, trace) -> None:
    """One Mesh3d trace onto matplotlib 3-D axes as a Poly3DCollection."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    vertices = np.stack([np.asarray(trace[a], dtype=np.float64) for a in "xyz"], axis=1)
    faces = np.stack([np.asarray(trace[a], dtype=np.int64) for a in "ijk"], axis=1)
    if trace.vertexcolor is not None:
        rgb = np.array([[int(c) / 255 for c in s[4:-1].split(",")] for s in trace.vertexcolor])
        facecolors = rgb[faces].mean(axis=1)
    else:
        facecolors = trace.color or "lightgrey"
    axes.add_collection3d(Poly3DCollection(vertices[faces], facecolors=facecolors, edgecolors="none",
                                           alpha=trace.opacity, label=trace.name))


def _equal_axes(axes, figure) -> None:
    """Equal scale on x, y, z around the data of every trace (plotly's aspectmode 'data')."""
    coordinates = np.concatenate([np.stack([_nan_gaps(t[a]) for a in "xyz"], axis=1) for t in figure.data])
    low, high = np.nanmin(coordinates, axis=0), np.nanmax(coordinates, axis=0)
    span = np.maximum(high - low, 1e-3)
    axes.set_xlim(low[0], low[0] + span[0])
    axes.set_ylim(low[1], low[1] + span[1])
    axes.set_zlim(low[2], low[2] + span[2])
    axes.set_box_aspect(tuple(span))


def render_png(figure, dpi: int = 90) -> bytes:
    """A static matplotlib picture of a :func:`scene` figure (same traces, colours, viewpoint,
    equal axes), as PNG bytes.  Draws Scatter3d (markers, lines) and Mesh3d traces."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    width, height = figure.layout.width or 720, figure.layout.height or 540
    canvas_figure = Figure(figsize=(width / 100, height / 100), dpi=100)
    FigureCanvasAgg(canvas_figure)
    axes = canvas_figure.add_subplot(projection="3d")
    for trace in figure.data:
        if trace.type == "scatter3d":
            _draw_scatter(axes, trace, colormaps)
        elif trace.type == "mesh3d":
            _draw_mesh(axes, trace)
        else:
            raise ValueError(f"render_png draws scatter3d and mesh3d traces, got {trace.type!r}")
    _equal_axes(axes, figure)
    view = (figure.layout.meta or {}).get("view", (25.0, -60.0))
    axes.view_init(elev=view[0], azim=view[1])
    axes.set_xlabel("x (m)"), axes.set_ylabel("y (m)"), axes.set_zlabel("z (m)")
    axes.set_title(figure.layout.title.text or "")
    if len(figure.data) > 1:
        axes.legend(loc="upper left", fontsize=8, markerscale=3)
    buffer = io.BytesIO()
    canvas_figure.savefig(buffer, format="png", dpi=dpi, bbox_inches="tight")
    return buffer.getvalue()


def plotly_json(figure) -> dict:
    """The figure as the JSON-compatible dict of the plotly mimetype (data, layout, config)."""
    figure_dict = json.loads(figure.to_json(validate=False))
    figure_dict["config"] = {"displaylogo": False}
    return figure_dict


def mimebundle(figure, dpi: int = 90) -> dict:
    """The display bundle of :func:`show`: plotly JSON, a PNG of the same scene, and plain text."""
    png = render_png(figure, dpi=dpi)
    return {MIMETYPE: plotly_json(figure), "image/png": base64.b64encode(png).decode("ascii"),
            "text/plain": f"<3-D figure: {', '.join(t.name or t.type for t in figure.data)}>"}


def show(figure, dpi: int = 90) -> None:
    """Display ``figure`` in a notebook as one output: interactive where the plotly mimetype is
    rendered (JupyterLab, VS Code), a static PNG elsewhere (GitHub, nbviewer, plain viewers)."""
    from IPython.display import display

    display(mimebundle(figure, dpi=dpi), raw=True)


def png_bytes(figure, dpi: int = 90) -> bytes:
    """The PNG picture alone (e.g. to save it next to a run's other figures)."""
    return base64.b64decode(mimebundle(figure, dpi=dpi)["image/png"])


__all__ = ["point_cloud", "frustum_corners", "camera_frusta", "trajectory", "mesh", "scene",
           "show", "mimebundle", "plotly_json", "png_bytes", "render_png", "subsample"]
