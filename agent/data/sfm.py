"""Structure from motion on one robot's own images (pycolmap), for robots that have no poses.

A robot whose folder holds images only gets its local poses, its intrinsics and a sparse depth
prior from an incremental SfM of its own images. The frame and the scale of the result are
arbitrary (whatever COLMAP picked): that is exactly why relative poses between such robots are
Sim(3) and not SE(3).

Everything runs on the CPU with a fixed number of threads (the machines have 2 cores shared with
other work) and is cached: SfM of 50 images takes minutes, so the result is stored in
``cache_dir`` under a key made of the image bytes and the configuration; a second call with the
same images returns from the cache, changed images or settings recompute.

Conventions of the output are those of :class:`agent.data.views.Views`: OpenGL camera-to-world,
intrinsics ``(fx, fy, cx, cy)`` with the centre of pixel column u at ``u + 0.5`` (COLMAP uses the
same pixel convention, so no half-pixel shift is needed), z-depth with 0 = unknown.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import re
import shutil
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from agent.camera import w2c_opencv_to_c2w_opengl
from agent.data.images import read_image, resize_image
from agent.data.views import DataError, Views
from agent.progress import stage, track

__all__ = ["SfmConfig", "run_sfm", "list_images", "read_image", "read_camera_file", "write_camera_file",
           "CAMERA_FILE", "IMAGE_SUFFIXES"]

log = logging.getLogger("dinerf.sfm")

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".webp")
_CACHE_FORMAT = 1  # bump when the layout of result.npz changes


@dataclass(frozen=True)
class SfmConfig:
    """Settings of the per-robot SfM. The defaults suit a few dozen images on 2 CPU cores."""

    max_image_size: int = 800  # SfM runs on the images downscaled to at most this many pixels a side
    camera_model: str = "SIMPLE_PINHOLE"  # Views has no distortion terms: keep the model pinhole
    focal_px: float | None = None  # known focal length in pixels of the original images (else guessed)
    refine_focal: bool = True  # let bundle adjustment refine the focal length (even a known one)
    max_num_features: int = 4096  # SIFT features per image
    exhaustive_max_images: int = 150  # exhaustive matching up to this many images (~30 s at 100);
    # sequential above, which assumes the file names follow the capture order (a trajectory)
    sequential_overlap: int = 10  # neighbours (in natural name order) matched in sequential mode
    num_threads: int = 2
    seed: int = 0
    background: float = 1.0  # RGBA images are composited onto this grey level before SfM
    min_registered: int = 3  # fewer registered images than this is an error ...
    min_registered_fraction: float = 0.3  # ... and so is fewer than this fraction of the images
    structure_less_fallback: bool = False  # COLMAP 4's 2-D-only registration fallback: it placed views mirrored
    abs_pose_min_inliers: int = 30  # COLMAP's default; 15 let planar-ambiguity (mirrored) poses in
    filter_max_reproj_error: float = 4.0  # px, COLMAP's default: observations off by more are dropped during mapping
    filter_min_tri_angle: float = 1.5  # deg, COLMAP's default: points triangulated at a smaller angle are dropped
    depth_min_track_length: int = 2  # SfM points seen by fewer images do not enter the depth prior
    depth_max_reproj_error: float = 2.0  # px; nor do points with a larger mean reprojection error
    max_runtime_seconds: int = -1  # mapper time limit, -1 = none
    verbose: bool = False  # COLMAP's own progress log (very chatty) on stderr


# --------------------------------------------------------------------------------------------
# Image files


def _natural_key(name: str) -> list:
    """Sort ``r_2`` before ``r_10``: sequential matching relies on capture order."""
    return [int(tok) if tok.isdigit() else tok.lower() for tok in re.split(r"(\d+)", name)]


def list_images(image_dir: str | Path) -> list[Path]:
    """Image files directly inside ``image_dir``, in natural name order."""
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise DataError(f"image folder {image_dir} does not exist")
    files = [p for p in image_dir.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(files, key=lambda p: _natural_key(p.name))


def _composite(img: np.ndarray, background: float) -> np.ndarray:
    """[H, W, 3|4] -> [H, W, 3]: straight RGBA over a constant grey (white for the NeRF datasets)."""
    if img.shape[2] == 3:
        return img
    alpha = img[:, :, 3:4]
    return img[:, :, :3] * alpha + background * (1.0 - alpha)


def _fit_size(width: int, height: int, max_side: int) -> tuple[int, int]:
    scale = min(1.0, max_side / max(width, height)) if max_side > 0 else 1.0
    return max(1, round(width * scale)), max(1, round(height * scale))


# --------------------------------------------------------------------------------------------
# A calibrated camera

CAMERA_FILE = "camera.json"  # beside the images: the robot's camera calibration, if it has one


def write_camera_file(folder: str | Path, focal_px: float, width: int, fixed: bool = True) -> Path:
    """Record a robot's calibrated focal length (pixels at ``width``) for its SfM to use."""
    path = Path(folder) / CAMERA_FILE
    path.write_text(json.dumps({"focal_px": float(focal_px), "width": int(width), "fixed": bool(fixed)}, indent=2))
    return path


def read_camera_file(folder: str | Path) -> dict | None:
    """The robot's camera calibration, or None when it has none.

    A robot usually knows its camera (a factory or checkerboard calibration) even when it knows
    none of its poses. SfM then starts from that focal length, and keeps it fixed unless the file
    says ``"fixed": false``. Robots that each guess their own focal length end up 1-3% apart,
    which no Sim(3) between their frames can absorb (docs/results.md, images-only lego).
    """
    path = Path(folder) / CAMERA_FILE
    if not path.is_file():
        return None
    try:
        raw = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise DataError(f"{path}: not readable JSON ({e})") from None
    if not isinstance(raw, dict):
        raise DataError(f"{path}: expected an object like {{\"focal_px\": 555.6, \"width\": 400}}")
    focal, width, fixed = raw.get("focal_px"), raw.get("width"), raw.get("fixed", True)
    if isinstance(focal, bool) or not isinstance(focal, (int, float)) or not np.isfinite(focal) or focal <= 0:
        raise DataError(f"{path}: focal_px must be a positive number of pixels, got {focal!r}")
    if isinstance(width, bool) or not isinstance(width, int) or width <= 0:
        raise DataError(f"{path}: width must be the positive image width (pixels) focal_px refers to, got {width!r}")
    if not isinstance(fixed, bool):
        raise DataError(f"{path}: fixed must be true or false, got {fixed!r}")
    return {"focal_px": float(focal), "width": width, "fixed": fixed}


# --------------------------------------------------------------------------------------------
# Cache


def _file_digests(files: list[Path]) -> list[tuple[str, bytes]]:
    return [(f.name, hashlib.sha256(f.read_bytes()).digest()) for f in files]


def _images_key(digests: list[tuple[str, bytes]]) -> str:
    """The images alone (names and bytes): what a robot's SfM frame is made of."""
    h = hashlib.sha256(b"images;")
    for name, digest in digests:
        h.update(name.encode() + b"\0" + digest)
    return h.hexdigest()


def _cache_key(digests: list[tuple[str, bytes]], config: SfmConfig) -> str:
    """The images, the settings and the COLMAP version: any change recomputes (unless keep_frame)."""
    import pycolmap

    h = hashlib.sha256()
    h.update(f"format={_CACHE_FORMAT};pycolmap={pycolmap.__version__};".encode())
    h.update(json.dumps(dataclasses.asdict(config), sort_keys=True).encode())
    for name, digest in digests:
        h.update(name.encode() + b"\0")
        h.update(digest)
    return h.hexdigest()


# --------------------------------------------------------------------------------------------
# SfM proper


def _reconstruct(files: list[Path], work: Path, config: SfmConfig) -> dict:
    """Run pycolmap in ``work``; return the arrays of the largest model (SfM resolution)."""
    import pycolmap

    if pycolmap.has_cuda:  # the Device.cpu arguments below already force the CPU path
        log.info("pycolmap was built with CUDA; forcing the CPU")
    pycolmap.set_random_seed(config.seed)
    # 3 = fatal only: a failed reconstruction is reported by our own one-line error (sfm.verbose: COLMAP's log)
    pycolmap.logging.minloglevel = 0 if config.verbose else 3

    img_dir = work / "images"
    names, size = _write_sfm_images(files, img_dir, config)
    sfm_w, sfm_h = _fit_size(size[0], size[1], config.max_image_size)
    db = work / "database.db"
    if db.exists():
        db.unlink()
    with stage(f"SfM: features of {len(names)} images"):
        _extract_features(db, img_dir, names, size, (sfm_w, sfm_h), config)
    with stage("SfM: matching"):
        matcher = _match_features(db, len(names), config)
    sparse = work / "sparse"
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir()
    with stage("SfM: incremental mapping"):
        models = pycolmap.incremental_mapping(db, img_dir, sparse, options=_mapping_options(config))
    if not models:
        return {"names": names, "registered": [], "size": (sfm_w, sfm_h), "matcher": matcher}
    best = max(models, key=lambda k: (models[k].num_reg_images(), -k))
    rec = models[best]
    (sparse / "largest").mkdir()
    rec.write(sparse / "largest")  # kept next to the cache for inspection with the COLMAP GUI
    reg_ids = sorted(rec.reg_image_ids(), key=lambda i: names.index(rec.image(i).name))
    return {
        "names": names,
        "registered": [rec.image(i).name for i in reg_ids],
        "size": (sfm_w, sfm_h),
        "matcher": matcher,
        **_model_arrays(rec, reg_ids, config),
        "num_models": len(models),
        "mean_reproj_error": float(rec.compute_mean_reprojection_error()),
    }


def _write_sfm_images(files: list[Path], img_dir: Path, config: SfmConfig) -> tuple[list[str], tuple[int, int]]:
    """The images as SfM sees them (composited, downscaled 8-bit PNG) in ``img_dir`` -> (names, original size)."""
    if img_dir.exists():
        shutil.rmtree(img_dir)
    img_dir.mkdir(parents=True)
    names: list[str] = []
    size = None
    for f in track(files, "SfM: preparing images"):
        img = read_image(f)
        if size is None:
            size = (img.shape[1], img.shape[0])
        elif (img.shape[1], img.shape[0]) != size:
            raise DataError(f"{f.name} is {img.shape[1]}x{img.shape[0]}, the others {size[0]}x{size[1]}: "
                            "one robot folder must hold images of one camera and size")
        w, h = _fit_size(size[0], size[1], config.max_image_size)
        rgb = resize_image(_composite(img, config.background), w, h)
        name = f.stem + ".png"
        if name in names:
            raise DataError(f"two images in {f.parent} share the stem {f.stem!r}")
        names.append(name)
        out = np.clip(np.rint(rgb[:, :, ::-1] * 255.0), 0, 255).astype(np.uint8)
        cv2.imwrite(str(img_dir / name), out)
    assert size is not None
    return names, size


def _extract_features(db: Path, img_dir: Path, names: list[str], size: tuple[int, int], sfm_size: tuple[int, int],
                      config: SfmConfig) -> None:
    import pycolmap

    sfm_w, sfm_h = sfm_size
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = config.camera_model
    if config.focal_px is not None:  # prior at the SfM resolution; principal point at the centre
        f = config.focal_px * sfm_w / size[0]
        pp = f"{sfm_w / 2},{sfm_h / 2}"
        reader.camera_params = f"{f},{pp}" if config.camera_model == "SIMPLE_PINHOLE" else f"{f},{f},{pp}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    extraction.num_threads = config.num_threads
    extraction.max_image_size = config.max_image_size
    extraction.sift.max_num_features = config.max_num_features
    pycolmap.extract_features(db, img_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)


def _match_features(db: Path, num_images: int, config: SfmConfig) -> str:
    """Exhaustive matching for few images, sequential (capture order) for many. -> which one ran."""
    import pycolmap

    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = config.num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = config.seed
    if num_images <= config.exhaustive_max_images:
        pycolmap.match_exhaustive(db, matching_options=matching, verification_options=verification,
                                  device=pycolmap.Device.cpu)
        return "exhaustive"
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = config.sequential_overlap
    pairing.num_threads = config.num_threads
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing,
                              verification_options=verification, device=pycolmap.Device.cpu)
    return "sequential"


def _mapping_options(config: SfmConfig):
    import pycolmap

    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = config.num_threads
    mapping.random_seed = config.seed
    mapping.mapper.random_seed = config.seed
    mapping.mapper.num_threads = config.num_threads
    mapping.triangulation.random_seed = config.seed
    mapping.mapper.abs_pose_min_num_inliers = config.abs_pose_min_inliers
    mapping.mapper.filter_max_reproj_error = config.filter_max_reproj_error
    mapping.mapper.filter_min_tri_angle = config.filter_min_tri_angle
    mapping.structure_less_registration_fallback = config.structure_less_fallback
    mapping.ba_use_gpu = False
    mapping.ba_refine_principal_point = False
    mapping.ba_refine_focal_length = config.refine_focal
    mapping.mapper.abs_pose_refine_focal_length = config.refine_focal
    mapping.max_runtime_seconds = int(config.max_runtime_seconds)
    return mapping


def _model_arrays(rec, reg_ids: list[int], config: SfmConfig) -> dict:
    """OpenGL c2w, intrinsics, the depth prior's observations (image, keypoint, z) and the points of a model."""
    c2w = np.zeros((len(reg_ids), 4, 4))
    intr = np.zeros((len(reg_ids), 4))
    obs_img, obs_xy, obs_z = [], [], []
    for k, image_id in enumerate(reg_ids):
        image = rec.image(image_id)
        cam = image.camera
        w2c = np.eye(4)
        w2c[:3, :] = image.cam_from_world().matrix()
        c2w[k] = w2c_opencv_to_c2w_opengl(w2c)
        intr[k] = [cam.focal_length_x, cam.focal_length_y, cam.principal_point_x, cam.principal_point_y]
        for p2d in image.points2D:
            if not p2d.has_point3D():
                continue
            p3d = rec.point3D(p2d.point3D_id)
            if p3d.track.length() < config.depth_min_track_length or p3d.error > config.depth_max_reproj_error:
                continue
            z = float((w2c[:3, :3] @ p3d.xyz + w2c[:3, 3])[2])
            if z <= 0:
                continue
            obs_img.append(k)
            obs_xy.append(p2d.xy)
            obs_z.append(z)
    return {
        "c2w": c2w,
        "intrinsics": intr,
        "obs_image": np.asarray(obs_img, dtype=np.int32),
        "obs_xy": np.asarray(obs_xy, dtype=np.float32).reshape(-1, 2),
        "obs_z": np.asarray(obs_z, dtype=np.float32),
        "points": np.array([p.xyz for p in rec.points3D.values()], dtype=np.float32).reshape(-1, 3),
    }


def _save(path: Path, key: str, images_key: str, res: dict) -> None:
    arrays = {k: v for k, v in res.items() if isinstance(v, np.ndarray)}
    info = {k: v for k, v in res.items() if not isinstance(v, np.ndarray)}
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, key=np.array(key), images_key=np.array(images_key), info=np.array(json.dumps(info)), **arrays)
    tmp.replace(path)


def _load(path: Path, key: str, images_key: str | None = None) -> tuple[dict, bool, bool] | None:
    """The cached result for ``key``; with ``images_key``, also one of the same images made with other
    settings.  -> (result, made with other settings, the file records its images key), or None."""
    if not path.exists():
        return None
    try:
        with np.load(path) as z:
            has_images_key = "images_key" in z.files
            same_images = images_key is not None and has_images_key and str(z["images_key"]) == images_key
            if str(z["key"]) != key and not same_images:
                return None
            res = json.loads(str(z["info"]))
            res.update({k: z[k] for k in z.files if k not in ("key", "images_key", "info")})
            settings_changed = str(z["key"]) != key
    except (OSError, ValueError, KeyError) as exc:  # a damaged cache is recomputed, not fatal
        log.warning("ignoring unreadable SfM cache %s: %s", path, exc)
        return None
    res["size"] = tuple(res["size"])
    return res, settings_changed, has_images_key


# --------------------------------------------------------------------------------------------
# Public entry point


def _with_camera_file(config: SfmConfig, robot_dir: Path, files: list[Path]) -> SfmConfig:
    """``config`` with the focal length of the robot's camera file, if it has one."""
    cam = read_camera_file(robot_dir)
    if cam is None or config.focal_px is not None:  # the caller's own calibration wins
        return config
    w = read_image(files[0]).shape[1]  # focal_px of SfmConfig is in pixels of the original images
    return dataclasses.replace(config, focal_px=cam["focal_px"] * w / cam["width"], refine_focal=not cam["fixed"])


def run_sfm(image_dir: str | Path, cache_dir: str | Path | None = None, *, width: int | None = None,
            config: SfmConfig = SfmConfig(), keep_frame: bool = False) -> Views:
    """Poses, intrinsics and a sparse depth prior for a folder of images, from their own SfM.

    Returns the registered images only, at their original size (or ``width`` pixels wide), with
    OpenGL c2w in SfM's arbitrary frame and scale and ``depth`` [M, H, W] holding the z-depth of
    the triangulated points each image observes (0 elsewhere). ``meta`` says which images did not
    register, the SfM resolution, the point cloud (``sfm_points`` [N, 3]) and whether the cache hit.
    Raises :class:`DataError` when the folder has no images or too few of them register.

    ``keep_frame``: a result cached in ``cache_dir`` for these same images is used even if it was
    made with other settings (another version of this code, a new option). A robot's SfM is its
    local frame: its checkpoint (relative pose, per-view camera corrections) and its report are
    only valid in the frame it trained in, and a second SfM run is not that frame, even with the
    same settings (COLMAP on 2 threads is not bit-reproducible).
    """
    robot_dir = Path(image_dir)
    image_dir, files = _robot_images(robot_dir)
    config = _with_camera_file(config, robot_dir, files)
    res, cache_hit, settings_changed = _cached_reconstruction(files, cache_dir, config, keep_frame, image_dir)
    n_reg = len(res["registered"])
    need = max(config.min_registered, int(np.ceil(config.min_registered_fraction * len(files))))
    if n_reg < need:
        raise DataError(f"SfM registered {n_reg} of {len(files)} images in {image_dir} (need at least {need}): "
                        "the images overlap too little or have too little texture")

    by_name = {f.stem + ".png": f for f in files}
    images, (out_w, out_h) = _output_images([by_name[n] for n in res["registered"]], width)
    sfm_w, sfm_h = res["size"]
    sx, sy = out_w / sfm_w, out_h / sfm_h
    intr = np.asarray(res["intrinsics"], dtype=np.float64) * np.array([sx, sy, sx, sy])
    return Views(
        images=torch.from_numpy(images.astype(np.float32)),
        c2w=torch.from_numpy(np.asarray(res["c2w"], dtype=np.float64)).float(),
        intrinsics=torch.from_numpy(intr).float(),
        names=[Path(n).stem for n in res["registered"]],
        depth=torch.from_numpy(_sparse_depth(res, n_reg, out_w, out_h, sx, sy)),
        meta=_meta(res, files, image_dir, config, cache_hit, settings_changed),
    )


def _robot_images(robot_dir: Path) -> tuple[Path, list[Path]]:
    """(the folder holding the images, the image files): the robot's folder or its images/ subfolder."""
    image_dir = robot_dir
    files = list_images(image_dir)
    if not files and (image_dir / "images").is_dir():  # the usual layout <robot>/images/*.png
        image_dir = image_dir / "images"
        files = list_images(image_dir)
    if not files:
        raise DataError(f"no images ({', '.join(IMAGE_SUFFIXES)}) in {image_dir}")
    return image_dir, files


def _cached_reconstruction(files: list[Path], cache_dir: str | Path | None, config: SfmConfig, keep_frame: bool,
                           image_dir: Path) -> tuple[dict, bool, bool]:
    """The SfM of ``files``, from ``cache_dir`` when it holds it, else computed and cached there.

    -> (result, cache hit, the cached result was made with other settings: ``keep_frame``).
    """
    digests = _file_digests(files)
    images_key, key = _images_key(digests), _cache_key(digests, config)
    tmp_ctx = tempfile.TemporaryDirectory(prefix="dinerf-sfm-") if cache_dir is None else None
    work = Path(tmp_ctx.name) if tmp_ctx is not None else Path(cache_dir)
    try:
        work.mkdir(parents=True, exist_ok=True)
        result_path = work / "sfm_result.npz"
        t0 = time.perf_counter()
        cached = _load(result_path, key, images_key if keep_frame else None)
        if cached is None:
            res, settings_changed = _reconstruct(files, work, config), False
            res["seconds"] = time.perf_counter() - t0
            _save(result_path, key, images_key, res)
        else:
            res, settings_changed, has_images_key = cached
            if not has_images_key:  # a cache from before images_key: add it, keep_frame needs it
                _save(result_path, key, images_key, res)
        if settings_changed:
            log.warning("%s: keeping the SfM cached in %s, made with other settings: it is the frame this robot "
                        "trained in", image_dir, work)
    finally:
        if tmp_ctx is not None:
            tmp_ctx.cleanup()
    return res, cached is not None, settings_changed


def _output_images(reg_files: list[Path], width: int | None) -> tuple[np.ndarray, tuple[int, int]]:
    """The registered images at their original size or ``width`` wide -> ([M, H, W, C], (W, H))."""
    first = read_image(reg_files[0])
    h0, w0 = first.shape[:2]
    out_w = w0 if width is None else int(width)
    out_h = h0 if width is None else max(1, round(h0 * out_w / w0))
    images = np.stack([resize_image(first if i == 0 else read_image(f), out_w, out_h) for i, f in enumerate(reg_files)])
    return images, (out_w, out_h)


def _sparse_depth(res: dict, n_reg: int, out_w: int, out_h: int, sx: float, sy: float) -> np.ndarray:
    """Sparse z-depth [M, H, W]: one pixel per observation; where two land on one pixel keep the nearer."""
    depth = np.zeros((n_reg, out_h, out_w), dtype=np.float32)
    if len(res["obs_z"]):
        u = np.clip(np.floor(res["obs_xy"][:, 0] * sx).astype(np.int64), 0, out_w - 1)
        v = np.clip(np.floor(res["obs_xy"][:, 1] * sy).astype(np.int64), 0, out_h - 1)
        flat = np.full(n_reg * out_h * out_w, np.inf, dtype=np.float32)
        np.minimum.at(flat, (res["obs_image"].astype(np.int64) * out_h + v) * out_w + u, res["obs_z"])
        flat[np.isinf(flat)] = 0.0
        depth = flat.reshape(n_reg, out_h, out_w)
    return depth


def _meta(res: dict, files: list[Path], image_dir: Path, config: SfmConfig, cache_hit: bool, settings_changed: bool) -> dict:
    sfm_w, sfm_h = res["size"]
    return {
        "source": "sfm",
        "image_dir": str(image_dir),
        "num_images": len(files),
        "num_registered": len(res["registered"]),
        "unregistered": [f.name for f in files if f.stem + ".png" not in set(res["registered"])],
        "sfm_size": (int(sfm_w), int(sfm_h)),
        "sfm_seconds": float(res.get("seconds", 0.0)),
        "sfm_matcher": res.get("matcher"),
        "sfm_num_models": int(res.get("num_models", 0)),
        "sfm_mean_reproj_error": float(res.get("mean_reproj_error", float("nan"))),
        "sfm_points": np.asarray(res["points"], dtype=np.float32),
        "cache_hit": cache_hit,
        "sfm_settings_changed": settings_changed,  # keep_frame reused an SfM made with other settings
        "depth_metric": True,  # the sparse depth lives in the same frame and scale as the poses
        "scale_known": False,  # SfM scale is arbitrary: relative poses must be Sim(3)
        "focal_calibrated": config.focal_px is not None and not config.refine_focal,  # a known camera: keep it
    }
