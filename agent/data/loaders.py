"""Load any supported dataset into :class:`~agent.data.views.Views`, whatever its layout.

One entry point, :func:`load_views`, looks at what it is given and picks the loader:

- ``"procedural"`` or ``"procedural:views=100,width=64,seed=0"``: the embedded scene
  (:mod:`agent.data.procedural`), so that nothing ever has to be downloaded;
- a ``transforms.json`` / ``transforms_train.json`` (or a folder holding one) in the Blender,
  nerfstudio or instant-ngp conventions (:mod:`agent.data.transforms_json`);
- a COLMAP sparse model (``sparse/0/`` or a folder with ``cameras``/``images``/``points3D`` as
  ``.bin`` or ``.txt``), read with pycolmap (:mod:`agent.data.colmap`);
- an LLFF folder: ``poses_bounds.npy`` with ``images/`` and/or ``images_N/`` (:mod:`agent.data.llff`);
- a folder of images only, handed to ``agent.data.sfm.run_sfm`` when that module is installed;
- a ROS 2 bag (rosbag2 folder, ``.mcap`` or ``.db3``): its keyframes (:mod:`agent.data.ros`).

Every loader returns the conventions of :mod:`agent.data.views` (OpenGL camera-to-world,
per-view ``fx, fy, cx, cy`` with the pixel centre at ``u + 0.5``, z-depth with 0 = unknown,
straight RGBA kept, pinhole cameras: lens distortion is undone at load time), masks beside the
images become alpha (:mod:`agent.data.masks`), and every failure the user can fix is a
:class:`DataError` that names the file and says what was expected.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import typing
from pathlib import Path
from typing import Any

from agent.data.colmap import find_colmap_model, load_colmap
from agent.data.images import IMAGE_EXTENSIONS, list_image_files, resize_views
from agent.data.llff import POSES_BOUNDS, load_llff
from agent.data.ros import is_bag, load_bag
from agent.data.transforms_json import load_transforms
from agent.data.views import EXPECTED_LAYOUTS, DataError, Views

__all__ = [
    "load_views",
    "parse_procedural_spec",
    # the loaders load_views picks from, importable from here as before
    "load_transforms",
    "load_colmap",
    "load_llff",
    "find_colmap_model",
    "resize_views",
    "IMAGE_EXTENSIONS",
    "EXPECTED_LAYOUTS",
]


def load_views(
    source: str | Path,
    *,
    width: int | None = None,
    load_depth: bool = True,
    images_dir: str | Path | None = None,
    sfm_cache_dir: str | Path | None = None,
    sfm: Any = None,
    undistort: bool = True,
    ros: Any = None,
    keyframe_cache_dir: str | Path | None = None,
) -> Views:
    """Load ``source`` (a path or ``procedural[:k=v,...]``) as :class:`Views`.

    width: target image width in pixels (downscale only, area interpolation; the height follows
    the aspect ratio and intrinsics are scaled with the image). ``None`` keeps the native size.
    load_depth: read depth maps when the dataset has them (transforms.json ``depth_file_path``;
    COLMAP sparse depth from the 3-D points).
    images_dir: where a COLMAP model's images are, when not next to the model.
    sfm_cache_dir: where SfM of an images-only folder keeps its result (default: not cached).
    sfm: the ``agent.data.sfm.SfmConfig`` of that SfM (default: its defaults).
    undistort: undo lens distortion (OpenCV, at the native size, new pinhole intrinsics; see
    :mod:`agent.data.lens`). False keeps the distorted images and ignores radial-tangential
    distortion with a note (e.g. to measure what that costs); a fisheye is then an error.
    """
    if width is not None and (not isinstance(width, int) or width < 1):
        raise DataError(f"width must be a positive integer, got {width!r}")
    text = str(source)
    if (text == "procedural" or text.startswith("procedural:")) and not Path(text).exists():
        from agent.data.procedural import procedural_views

        from agent.data.frames import undistort_views

        views = procedural_views(parse_procedural_spec(text, width=width))
        return undistort_views(views) if undistort else views  # its lens undone as a dataset's would be

    path = Path(source).expanduser()
    if not path.exists():
        raise DataError(f"{path}: no such file or folder; {EXPECTED_LAYOUTS}")
    if is_bag(path):
        if not undistort:
            raise DataError(f"{path}: a bag's lens is always undone (undistort=False is for the image formats)")
        return load_bag(path, width=width, cfg=ros, cache_dir=keyframe_cache_dir)
    if path.is_file():
        if path.suffix.lower() == ".json":
            return load_transforms(path, width=width, load_depth=load_depth, undistort=undistort)
        if path.stem in ("cameras", "images", "points3D") and path.suffix in (".bin", ".txt"):
            return load_colmap(path.parent, width=width, load_depth=load_depth, images_dir=images_dir, undistort=undistort)
        if path.name == POSES_BOUNDS:
            return load_llff(path.parent, width=width)
        raise DataError(f"{path}: not a dataset file; {EXPECTED_LAYOUTS}")

    for name in ("transforms.json", "transforms_train.json"):
        if (path / name).is_file():
            return load_transforms(path / name, width=width, load_depth=load_depth, undistort=undistort)
    model = find_colmap_model(path)
    if model is not None:  # before LLFF: an LLFF folder's sparse/0 has the lens and the depth
        return load_colmap(model, width=width, load_depth=load_depth, images_dir=images_dir, undistort=undistort)
    if (path / POSES_BOUNDS).is_file():
        return load_llff(path, width=width)
    images = list_image_files(path) or list_image_files(path / "images")
    if images:
        return _load_images_only(path, images, width=width, cache_dir=sfm_cache_dir, config=sfm)
    if (path / "split.json").is_file():
        robots = sorted(p.name for p in path.glob("robot*") if p.is_dir())
        raise DataError(f"{path} is the output of `dinerf-agent split`; load one of its folders: {robots + ['eval']}")
    found = sorted(p.name + ("/" if p.is_dir() else "") for p in path.iterdir())[:12]
    raise DataError(f"{path}: no known dataset layout; {EXPECTED_LAYOUTS}. Found: {found or 'an empty folder'}")


def parse_procedural_spec(text: str, width: int | None = None):
    """``procedural:views=100,width=64,seed=0`` -> ``ProceduralConfig``.

    Keys are the fields of ``ProceduralConfig`` (``views`` is short for ``num_views``, ``arc`` for
    ``arc_deg``); values are numbers, ``0``/``1`` for a switch such as ``room=1``, or ``a/b`` for
    a pair such as ``elevation_deg=10/60``. A width without a height keeps the aspect ratio;
    ``width`` given to :func:`load_views` wins over the spec.
    """
    from agent.data.procedural import ProceduralConfig

    fields = {f.name: f for f in dataclasses.fields(ProceduralConfig)}
    hints = typing.get_type_hints(ProceduralConfig)
    aliases = {"views": "num_views", "n": "num_views", "fov": "fov_deg", "elevation": "elevation_deg",
               "arc": "arc_deg", "arc_start": "arc_start_deg"}
    kwargs: dict[str, Any] = {}
    _, _, body = text.partition(":")
    for item in filter(None, (s.strip() for s in body.split(","))):
        key, eq, value = item.partition("=")
        key = aliases.get(key.strip(), key.strip())
        if not eq or key not in fields:
            raise DataError(
                f"procedural spec {text!r}: bad item {item!r}; expected key=value with keys "
                f"{sorted(set(fields) | {'views', 'arc'})}"
            )
        kwargs[key] = _spec_value(text, key, value.strip(), hints[key])
    if "width" in kwargs and "height" not in kwargs:  # a width alone keeps the default aspect ratio
        default = ProceduralConfig()
        kwargs["height"] = max(1, round(default.height * kwargs["width"] / default.width))
    cfg = ProceduralConfig(**kwargs)
    if width is not None and width != cfg.width:
        height = max(1, round(cfg.height * width / cfg.width))
        cfg = dataclasses.replace(cfg, width=width, height=height)
    return cfg


def _spec_value(text: str, key: str, value: str, kind: Any) -> Any:
    """One value of a procedural spec as the field's type: int, float (or None), bool, pair of floats."""
    try:
        if kind is bool:
            if value.lower() not in ("0", "1", "true", "false"):
                raise ValueError
            return value.lower() in ("1", "true")
        if kind is int:
            return int(value)
        if kind is float or type(None) in typing.get_args(kind):
            return float(value)
        lo, hi = value.split("/")  # a pair of floats
        return float(lo), float(hi)
    except ValueError:
        raise DataError(f"procedural spec {text!r}: cannot read {key}={value!r}") from None


def _load_images_only(folder: Path, images: list[Path], *, width: int | None, cache_dir: str | Path | None = None,
                      config: Any = None) -> Views:
    """Hand a folder of unposed images to ``agent.data.sfm.run_sfm``, imported lazily.

    The SfM module may return :class:`Views` or the path of a COLMAP model it wrote; both are
    accepted. Only the keyword arguments its signature declares are passed.
    """
    try:  # import_module consults sys.modules first, so tests can simulate presence and absence
        sfm = importlib.import_module("agent.data.sfm")
    except ImportError as e:
        raise DataError(
            f"{folder}: holds {len(images)} images but no poses, and SfM support (agent.data.sfm) is not "
            f"installed ({e}); {EXPECTED_LAYOUTS}"
        ) from None
    run = getattr(sfm, "run_sfm", None)
    if run is None:
        raise DataError(f"{folder}: holds only images, and agent.data.sfm has no run_sfm(); SfM support is not installed")
    params = inspect.signature(run).parameters
    kwargs: dict[str, Any] = {"width": width} if "width" in params else {}
    if cache_dir is not None and "cache_dir" in params:
        kwargs["cache_dir"] = cache_dir
        if "keep_frame" in params:  # the run's own SfM is the robot's frame: never silently redone
            kwargs["keep_frame"] = True
    if config is not None and "config" in params:
        kwargs["config"] = config
    result = run(folder, **kwargs)
    if isinstance(result, Views):
        return resize_views(result, width) if width is not None and width != result.width else result
    if isinstance(result, (str, Path)):
        return load_colmap(Path(result), width=width)
    raise DataError(f"{folder}: run_sfm returned {type(result).__name__}; expected Views or a COLMAP model path")
