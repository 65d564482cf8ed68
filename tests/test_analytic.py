"""AnalyticField returns a scene's colour and exact clamped normalised TSDF.

Oracles: the closed-form signed distance of a sphere and of the room's floor plane written here,
not the scene's own code; the true depth of a ray to the floor for rendering through Eq. (2)-(3).
"""

import pytest
import torch

import tsslam_ref.config
from tsslam_ref.analytic import AnalyticField
from tsslam_ref.render import render_rays
from tsslam_ref.synthetic import ProceduralRoom

CENTRE, RADIUS, COLOUR = (0.0, 0.0, 1.2), 0.4, (0.2, 0.4, 0.9)


@pytest.fixture(scope="module")
def sphere_room():
    return ProceduralRoom(boxes=(), spheres=((CENTRE, RADIUS, COLOUR),), cylinders=(), seed=0)


def test_tsdf_is_the_clamped_sphere_distance_over_truncation(sphere_room):
    generator = torch.Generator().manual_seed(0)
    centre = torch.tensor(CENTRE, dtype=torch.float64)
    points = centre + 0.25 * torch.randn(500, 3, generator=generator, dtype=torch.float64)  # near the sphere, far from walls
    truncation = 0.1
    colour, tsdf = AnalyticField(sphere_room, truncation)(points)
    exact = ((points - centre).norm(dim=-1) - RADIUS) / truncation  # closed-form sphere SDF
    assert torch.allclose(tsdf, exact.clamp(-1.0, 1.0), atol=1e-12)
    assert 0 < int((exact.abs() < 1).sum()) < len(points), "the sample must cover both the band and the clamp"
    assert colour.shape == (500, 3) and bool(((colour >= 0) & (colour <= 1)).all())


def test_tsdf_near_the_floor_is_the_height(sphere_room):
    points = torch.tensor([[1.5, 1.0, 0.02], [1.5, -1.0, 0.05], [-1.5, 0.5, 0.3]], dtype=torch.float64)
    _, tsdf = AnalyticField(sphere_room, 0.1)(points)
    assert torch.allclose(tsdf, torch.tensor([0.2, 0.5, 1.0], dtype=torch.float64), atol=1e-12)


def test_rendering_a_ray_to_the_floor_gives_its_true_depth(sphere_room):
    cfg = tsslam_ref.config.tiny().render
    cfg.perturb = False
    origin = torch.tensor([[1.5, 1.0, 1.0]])  # 1 m above the floor, away from the sphere
    down = torch.tensor([[0.0, 0.0, -1.0]])
    out = render_rays(AnalyticField(sphere_room, cfg.truncation), origin, down, torch.tensor([1.0]), cfg)
    assert abs(float(out["depth"][0]) - 1.0) < 0.01, f"rendered depth {float(out['depth'][0]):.4f} m, true 1 m"


def test_it_has_no_parameters_and_rejects_bad_input(sphere_room):
    field = AnalyticField(sphere_room, 0.1)
    assert list(field.parameters()) == []
    with pytest.raises(ValueError, match="truncation = 0"):
        AnalyticField(sphere_room, 0.0)
    with pytest.raises(TypeError, match="sdf"):
        AnalyticField(object(), 0.1)
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        field(torch.zeros(4, 2))
