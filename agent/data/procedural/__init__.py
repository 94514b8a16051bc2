"""The project's own scene: a few textured analytic objects, rendered exactly for any camera.

Why it exists: the demo, the quick start and the fast tests must run on a fresh clone with
nothing downloaded, and evaluation of novel views needs ground truth for *any* camera, not only
for the views of a dataset.

- :mod:`.objects`: the analytic shapes (intersection, SDF, normal, albedo);
- :mod:`.scene`: the objects in the box ``[-1, 1]^3``, their textures and shading;
- :mod:`.room`: walls, floor and ceiling around them, for captures with a background;
- :mod:`.render`: exact, anti-aliased rendering for any camera (colour, alpha, z-depth);
- :mod:`.config`: :class:`ProceduralConfig` and the cameras it describes;
- :mod:`.dataset`: :func:`procedural_views`, the dataset ``procedural:...`` loads.

Alpha is the covered fraction of the pixel (RGB 0 where it is 0, straight alpha); depth is the
exact z-depth of the ray through the pixel centre, 0 where it misses.
"""

from agent.data.procedural.config import ProceduralConfig, procedural_cameras
from agent.data.procedural.dataset import procedural_views
from agent.data.procedural.render import render_procedural
from agent.data.procedural.scene import SCENE_BOX_WORLD, scene_sdf, surface_colour

__all__ = [
    "ProceduralConfig",
    "procedural_cameras",
    "procedural_views",
    "render_procedural",
    "scene_sdf",
    "surface_colour",
    "SCENE_BOX_WORLD",
]
