"""The procedural scene as a real capture would record it: a room around it, cameras on an arc."""

from __future__ import annotations

import math

import pytest
import torch

from agent.camera import unproject_depth
from agent.data.capture import capture_warnings, estimate_scene_box, field_box_mismatch
from agent.data.loaders import load_views, parse_procedural_spec
from agent.data.procedural import ProceduralConfig, procedural_views, render_procedural, scene_sdf, surface_colour
from agent.data.procedural.room import CEILING_Z, FLOOR_Z, ROOM_HALF_SIZE, room_sdf
from agent.data.procedural.scene import SCENE_BOX_WORLD
from agent.data.views import DataError
from agent.geometry import look_at


@pytest.fixture(scope="module")
def room():
    """Point-sampled views low enough that every one sees a wall above the floor."""
    return procedural_views(ProceduralConfig(num_views=8, width=40, height=32, seed=2, supersample=1, room=True,
                                             elevation_deg=(5.0, 30.0)))


def _azimuths(v):
    c = v.c2w[:, :3, 3].double()
    return torch.rad2deg(torch.atan2(c[:, 1], c[:, 0])) % 360


def test_room_views_are_rgb_and_every_pixel_sees_a_surface(room):
    assert room.images.shape == (8, 32, 40, 3) and not room.has_alpha
    assert bool((room.depth > 0).all()), "no background: every ray ends on an object or the room"
    for i in range(len(room)):
        pts = unproject_depth(room.depth[i], room.intrinsics[i], room.c2w[i])
        on_room = room_sdf(pts).abs() < 1e-4
        on_wall = on_room & ((pts[:, :2].abs() - ROOM_HALF_SIZE).abs() < 1e-4).any(-1)
        assert int(on_wall.sum()) > 20, f"view {i}: the walls are in the picture"
        assert bool((pts[on_room].abs().amax(-1) > 1.0).all()), "the room lies outside the scene box"


def test_the_box_of_a_capture_that_shows_its_room_holds_its_cameras(room):
    """Cameras left in the contracted shell would see their near space through cells ~|x|^2 too
    deep; with alpha, the object's box alone."""
    centre, half, source = estimate_scene_box(room)
    reach = float((room.c2w[:, :3, 3].double() - centre).abs().amax())
    assert source == "dataset" and reach * 1.05 < half < ROOM_HALF_SIZE
    obj = procedural_views(ProceduralConfig(num_views=8, width=40, height=32, seed=2, supersample=1))
    assert obj.has_alpha and estimate_scene_box(obj)[1] == pytest.approx(SCENE_BOX_WORLD["half_size"])
    assert not capture_warnings(obj, "dataset")
    obj.images[..., 3] = 1.0  # an alpha channel that masks nothing: bounded, and said so
    assert any("alpha opaque in every pixel" in w for w in capture_warnings(obj, "dataset"))
    assert "unbounded field" in capture_warnings(room, "dataset")[0]


def test_a_field_set_against_the_images_gets_its_own_box_and_a_warning(room):
    """field.unbounded set by hand: a box sized for that field where the config is known (the
    baseline); one line where the split sized it for the other (the daemon)."""
    obj = procedural_views(ProceduralConfig(num_views=8, width=40, height=32, seed=2, supersample=1))
    grown, obj_half = estimate_scene_box(room)[1], estimate_scene_box(obj)[1]
    assert estimate_scene_box(room, unbounded=False)[1] == pytest.approx(SCENE_BOX_WORLD["half_size"])
    assert SCENE_BOX_WORLD["half_size"] < grown
    assert estimate_scene_box(obj, unbounded=True)[1] > 3 * obj_half  # the object's cameras held
    assert estimate_scene_box(room, unbounded=True)[1] == grown
    assert field_box_mismatch(room, None) is None and field_box_mismatch(room, True) is None
    assert field_box_mismatch(obj, None) is None and field_box_mismatch(obj, False) is None
    assert "unbounded = false" in field_box_mismatch(room, False) and "masks" in field_box_mismatch(room, False)
    assert "unbounded = true" in field_box_mismatch(obj, True) and "floaters" in field_box_mismatch(obj, True)


def test_room_depth_lands_on_a_surface_with_the_rendered_colour(room):
    for i in range(0, len(room), 2):
        pts = unproject_depth(room.depth[i], room.intrinsics[i], room.c2w[i])
        assert float(scene_sdf(pts, room=True).abs().max()) < 1e-4
        err = (surface_colour(pts, room=True) - room.images[i].reshape(-1, 3).double()).abs().max(-1).values
        assert float((err < 1e-4).double().mean()) > 0.99


def test_wall_depth_is_exact():
    # a camera 3 units up on the z axis looking along +x sees the wall x = 7 at z-depth 7 in its centre,
    # and, turned to look down, the floor at z-depth 3 - FLOOR_Z
    eye = torch.tensor([0.0, 0.0, 3.0])
    forward = look_at(eye, torch.tensor([1.0, 0.0, 3.0]), torch.tensor([0.0, 0.0, 1.0]))
    down = look_at(eye, torch.tensor([0.0, 0.0, 0.0]), torch.tensor([1.0, 0.0, 0.0]))
    k = torch.tensor([[20.0, 20.0, 8.0, 8.0]]).repeat(2, 1)
    _, depth = render_procedural(torch.stack([forward, down]).float(), k, 16, 16, room=True)
    centre = depth[:, 7:9, 7:9]  # the four pixels round the optical axis, all at (nearly) the same depth
    assert float(centre[0].mean()) == pytest.approx(ROOM_HALF_SIZE, abs=1e-4)
    assert float(depth[0].max()) < math.dist((0, 0, 3), (ROOM_HALF_SIZE, ROOM_HALF_SIZE, CEILING_Z))
    # looking straight down at (0, 0) the camera sees the base slab (z = -0.75), not the floor
    assert float(centre[1].mean()) == pytest.approx(3.75, abs=1e-4)
    assert float(depth[1, 0, 0]) == pytest.approx(3.0 - FLOOR_Z, abs=1e-4), "a corner ray passes the slab"


def test_objects_look_the_same_in_the_room():
    cfg = ProceduralConfig(num_views=4, width=32, height=32, seed=5, supersample=1)
    bare, boxed = procedural_views(cfg), procedural_views(ProceduralConfig(**{**vars(cfg), "room": True}))
    obj = bare.images[..., 3] > 0
    assert torch.equal(boxed.images[obj], bare.images[..., :3][obj]) and torch.equal(boxed.depth[obj], bare.depth[obj])
    for i in range(len(boxed)):  # and where the bare scene is empty, the room is what is seen
        depth = torch.where(obj[i], 0.0, boxed.depth[i])
        assert float(room_sdf(unproject_depth(depth, boxed.intrinsics[i], boxed.c2w[i])).abs().max()) < 1e-4


def test_cameras_on_an_arc_in_capture_order():
    v = procedural_views(ProceduralConfig(num_views=30, width=8, height=8, arc_deg=90.0, arc_start_deg=315.0, seed=1))
    rel = (_azimuths(v) - 315.0) % 360  # crosses 0 deg
    assert float(rel.max()) < 90.0 and float(rel.max() - rel.min()) > 60.0
    assert bool((rel.diff() >= 0).all()), "names follow the capture order along the arc"
    elev = torch.rad2deg(torch.asin(v.c2w[:, 2, 3].double() / 4.0))
    assert float(elev.min()) >= 5 - 1e-3 and float(elev.max()) <= 75 + 1e-3, "elevations as on the full circle"
    default = procedural_views(ProceduralConfig(num_views=30, width=8, height=8, seed=1))
    assert float(_azimuths(default).max() - _azimuths(default).min()) > 300.0


def test_spec_options_and_bad_values():
    cfg = parse_procedural_spec("procedural:views=60,width=48,room=1,arc=90,arc_start=30,k1=0.06")
    assert (cfg.room, cfg.arc_deg, cfg.arc_start_deg, cfg.distortion) == (True, 90.0, 30.0, (0.06, 0.0, 0.0, 0.0))
    assert parse_procedural_spec("procedural").arc_deg is None
    v = load_views("procedural:views=2,width=16,room=1")
    assert v.images.shape[-1] == 3 and not v.has_alpha
    with pytest.raises(DataError, match="room=1"):
        parse_procedural_spec("procedural:views=4,room=1,radius=7")
    with pytest.raises(DataError, match="inside the room"):
        ProceduralConfig(room=True, elevation_deg=(-60.0, 10.0))
    with pytest.raises(DataError, match="arc_deg"):
        ProceduralConfig(arc_deg=0.0)
    with pytest.raises(DataError, match="room"):
        parse_procedural_spec("procedural:room=yes")
    with pytest.raises(DataError, match="cannot be inverted"):
        ProceduralConfig(k1=-2.0)


def test_a_box_derived_for_unseen_robots_holds_their_cameras_wherever_they_stand():
    import math

    import torch

    from agent.data.capture import estimate_scene_box
    from agent.data.views import Views
    from agent.geometry import look_at

    def ring(azimuths_deg):  # RGB cameras at radius 4 round the origin, looking at it
        eyes = torch.tensor([[4 * math.cos(math.radians(a)), 4 * math.sin(math.radians(a)), 0.5] for a in azimuths_deg])
        c2w = torch.stack([look_at(e, torch.zeros(3), torch.tensor([0.0, 0.0, 1.0])) for e in eyes]).float()
        n = len(azimuths_deg)
        return Views(torch.zeros(n, 8, 8, 3), c2w, torch.tensor([[8.0, 8.0, 4.0, 4.0]] * n), [str(a) for a in azimuths_deg])

    own = ring([35, 40, 45, 50, 55])  # one robot's cameras, diagonal to the axes
    others = ring([-5, 0, 5])  # another robot's, on an axis: as far from the centre, farther along x
    centre, half, _ = estimate_scene_box(own, True)
    centre2, shared, _ = estimate_scene_box(own, True, cameras_elsewhere=True)
    reach = float((others.c2w[:, :3, 3].double() - centre).abs().amax())
    assert torch.equal(centre, centre2) and half < reach <= shared  # outside the box of its own views, inside this one
