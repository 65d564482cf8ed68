"""An exact stand-in for the neural map: a scene's own colour and normalised TSDF as a field.

Course helper for the tracking and local-BA chapters.  The learned map of the paper's Eq. (1)
(``tsslam_ref.field.SceneField``) returns, for points p, a colour c(p) and a normalised truncated
SDF s(p) = sdf(p) / tr in [-1, 1] (Co-SLAM's convention, read by ``render.render_rays`` for Eq. (2)-(3)).
:class:`AnalyticField` returns the same pair computed exactly from a scene with an analytic SDF and
colour (``synthetic.ProceduralRoom``, or any object with ``sdf`` and ``color`` methods), so with it
the true camera pose is the minimum of the rendering loss and pose errors can be read in cm and
degrees.  Side layer: imports nothing from the package.

| symbol | variable | shape | unit |
|---|---|---|---|
| p | ``points`` | (N, 3) | world, m |
| c(p) | ``colour`` | (N, 3) | [0, 1] |
| s(p) | ``tsdf`` | (N,) | sdf / tr, clamped to [-1, 1] |
| tr | ``truncation`` | scalar | m |
"""

import torch


class AnalyticField(torch.nn.Module):
    """Colour and clamped normalised TSDF of an analytic scene, called like ``SceneField``.

    Args:
        scene: object with ``sdf(points) -> (N,)`` (m, > 0 in free space) and
            ``color(points) -> (N, 3)`` (in [0, 1]); e.g. ``synthetic.ProceduralRoom``.
        truncation: tr in metres (``cfg.render.truncation``), > 0.

    It has no parameters: optimisers that freeze or train "the map" see an empty parameter list.
    """

    def __init__(self, scene, truncation: float):
        super().__init__()
        if not (hasattr(scene, "sdf") and hasattr(scene, "color")):
            raise TypeError(f"scene must have sdf(points) and color(points) methods, got {type(scene).__name__}")
        if not float(truncation) > 0:
            raise ValueError(f"truncation = {truncation} must be > 0 (metres)")
        self.scene, self.truncation = scene, float(truncation)

    def forward(self, points: torch.Tensor):
        """(N, 3) world points -> (colour (N, 3), normalised TSDF (N,) in [-1, 1])."""
        if points.ndim != 2 or points.shape[-1] != 3:
            raise ValueError(f"AnalyticField expects points of shape (N, 3), got {tuple(points.shape)}")
        tsdf = (self.scene.sdf(points) / self.truncation).clamp(-1.0, 1.0)
        return self.scene.color(points), tsdf
