"""Ray generation against the camera conventions of agent.data.views (OpenGL c2w, pixel centre at u + 0.5)."""

from __future__ import annotations

import torch

from agent.data.loaders import load_views
from agent.data.procedural import scene_sdf
from agent.geometry import look_at, random_rotation, sim3_from_params, transform_c2w, transform_points
from agent.nerf.rays import image_rays, pixel_rays, transform_rays

D = torch.float64


def a_camera() -> torch.Tensor:
    """A generic camera (not axis-aligned) looking roughly at the origin.  -> c2w [4, 4] float64."""
    return look_at(torch.tensor([2.0, -3.0, 1.5]), torch.tensor([0.2, 0.1, -0.3]), torch.tensor([0.0, 0.0, 1.0]))


def test_centre_pixel_ray_is_the_camera_minus_z_axis_and_rows_go_down():
    c2w = a_camera()
    w, h = 7, 5  # odd sizes: one pixel sits exactly on the principal point
    intr = torch.tensor([9.0, 11.0, w / 2, h / 2], dtype=D)
    rays = image_rays(c2w, intr, w, h)  # R = 35, row-major
    centre = (h // 2) * w + w // 2
    assert torch.allclose(rays.directions[centre], -c2w[:3, 2], atol=1e-12)
    assert torch.allclose(rays.origins, c2w[:3, 3].expand(w * h, 3))
    assert float(rays.z_per_t[centre]) == 1.0
    cam = rays.directions @ c2w[:3, :3]  # [R, 3] directions in the camera frame
    assert bool((cam[:, 2] < 0).all())  # every ray looks forward (-Z)
    top_left, bottom_right = 0, w * h - 1
    assert cam[top_left, 0] < 0 and cam[top_left, 1] > 0  # column 0 is left (-X), row 0 is up (+Y)
    assert cam[bottom_right, 0] > 0 and cam[bottom_right, 1] < 0
    assert torch.allclose(rays.directions.norm(dim=-1), torch.ones(w * h, dtype=D))


def test_a_projected_point_lies_on_the_ray_through_its_pixel():
    g = torch.Generator().manual_seed(1)
    c2w = a_camera()
    fx, fy, cx, cy = 70.0, 64.0, 41.3, 27.9  # non-square pixels, off-centre principal point
    cam_pts = torch.empty(50, 3, dtype=D)
    cam_pts[:, 2] = -(1.0 + 4.0 * torch.rand(50, generator=g, dtype=D))  # in front: z < 0
    cam_pts[:, :2] = (torch.rand(50, 2, generator=g, dtype=D) - 0.5) * (-cam_pts[:, 2:]) * 0.8
    world = transform_points(c2w, cam_pts)  # [50, 3]
    u = cx + fx * cam_pts[:, 0] / -cam_pts[:, 2]  # pinhole, OpenGL camera, image v axis downwards
    v = cy - fy * cam_pts[:, 1] / -cam_pts[:, 2]
    rays = pixel_rays(c2w.expand(50, 4, 4), torch.tensor([fx, fy, cx, cy], dtype=D).expand(50, 4), u, v)
    t = ((world - rays.origins) * rays.directions).sum(-1)  # [50] distance of the closest point on the ray
    assert bool((t > 0).all())
    closest = rays.origins + t[:, None] * rays.directions
    assert torch.allclose(closest, world, atol=1e-10)
    # z_per_t turns that distance into the z-depth of the point
    assert torch.allclose(t * rays.z_per_t, -cam_pts[:, 2], atol=1e-10)


def test_procedural_depth_along_our_rays_lands_on_the_scene_surface():
    """The dataset's own renderer and the NeRF's ray generator agree on pixels, axes and z-depth."""
    views = load_views("procedural:views=3,width=24")
    hits = 0
    for i in range(len(views)):
        rays = image_rays(views.c2w[i].double(), views.intrinsics[i].double(), views.width, views.height)
        depth = views.depth[i].reshape(-1).double()  # [R] z-depth, 0 = background
        fg = depth > 0
        points = rays.origins[fg] + (depth[fg] / rays.z_per_t[fg])[:, None] * rays.directions[fg]
        sdf = scene_sdf(points)
        # float32 depth of a scene ~4 units away: ~1e-7 units; a half-pixel shift gives ~0.07, much more than any pixel footprint
        assert float(sdf.abs().max()) < 1e-5
        hits += int(fg.sum())
    assert hits > 100


def test_transform_rays_by_a_similarity_keeps_directions_unit_and_maps_points():
    g = torch.Generator().manual_seed(2)
    rays = pixel_rays(a_camera().expand(20, 4, 4), torch.tensor([30.0, 30.0, 16.0, 16.0], dtype=D).expand(20, 4),
                      torch.rand(20, generator=g, dtype=D) * 32, torch.rand(20, generator=g, dtype=D) * 32)
    s = 0.37
    transform = torch.eye(4, dtype=D)
    transform[:3, :3] = s * random_rotation(g)
    transform[:3, 3] = torch.tensor([0.4, -1.2, 2.0], dtype=D)
    moved = transform_rays(rays, transform)
    assert torch.allclose(moved.directions.norm(dim=-1), torch.ones(20, dtype=D), atol=1e-12)
    t = 0.5 + 3 * torch.rand(20, generator=g, dtype=D)  # [20] distances in the source frame
    source_pts = rays.origins + t[:, None] * rays.directions
    # the same point is at distance s * t along the moved ray ...
    assert torch.allclose(moved.origins + (s * t)[:, None] * moved.directions, transform_points(transform, source_pts),
                          atol=1e-12)
    # ... and z_per_t of the moved ray still gives the source camera's z-depth of that point
    assert torch.allclose(s * t * moved.z_per_t, t * rays.z_per_t, atol=1e-12)


def test_pose_gradients_flow_through_ray_origins_and_directions():
    """Gradcheck (float64) from (log s, phi, t) of a Sim(3) through transform_c2w and pixel_rays."""
    g = torch.Generator().manual_seed(3)
    c2w = torch.stack([a_camera(), look_at(torch.tensor([-3.0, 1.0, 2.0]), torch.zeros(3), torch.tensor([0.0, 0, 1]))])
    intr = torch.tensor([[40.0, 42.0, 16.0, 15.0], [35.0, 35.0, 17.0, 16.5]], dtype=D)
    u = torch.rand(2, generator=g, dtype=D) * 32
    v = torch.rand(2, generator=g, dtype=D) * 32

    def rays_of(log_s, phi, trans):
        cams = transform_c2w(sim3_from_params(log_s, phi, trans), c2w)  # [2, 4, 4]
        rays = pixel_rays(cams, intr, u, v)
        return torch.cat([rays.origins, rays.directions], -1)  # [2, 6]

    params = (torch.tensor(0.2, dtype=D, requires_grad=True), torch.tensor([0.3, -0.2, 0.5], dtype=D, requires_grad=True),
              torch.tensor([0.1, 0.4, -0.3], dtype=D, requires_grad=True))
    assert torch.autograd.gradcheck(rays_of, params)
    out = rays_of(*params)
    out.sum().backward()
    for p in params:
        assert p.grad is not None and float(p.grad.abs().sum()) > 0
    # rotation moves the directions, scale and translation only the origins
    dirs_grad = torch.autograd.grad(rays_of(*params)[:, 3:].sum(), params, allow_unused=True)
    assert float(dirs_grad[1].abs().sum()) > 0
    assert dirs_grad[0] is None or float(dirs_grad[0].abs().max()) < 1e-12
    assert dirs_grad[2] is None or float(dirs_grad[2].abs().max()) < 1e-12
