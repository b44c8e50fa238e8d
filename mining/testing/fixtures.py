"""Writers that turn real RGB stereo frames into other datasets' on-disk formats (test-only).

Tests and benchmarks use them to build RobotCar-layout traversals and ROS 2 MCAP logs
from real KITTI frames, so the ``oxford`` and ``mcap`` adapters are exercised on real
image content without shipping those datasets.
"""

from __future__ import annotations

import shutil
import tarfile
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from mining.sources.oxford import PAIRS
from mining.types import StereoCalib

# ours: RobotCar's Bumblebee XB3 runs at 16 Hz (SOURCES.md §4).
ROBOTCAR_HZ = 16.0

# Row/column offsets of the R, G (twice) and B sites in a 2×2 Bayer cell, per pattern.
BAYER_SITES: dict[str, dict[str, list[tuple[int, int]]]] = {
    "gbrg": {"G": [(0, 0), (1, 1)], "B": [(0, 1)], "R": [(1, 0)]},
    "rggb": {"R": [(0, 0)], "G": [(0, 1), (1, 0)], "B": [(1, 1)]},
    "bggr": {"B": [(0, 0)], "G": [(0, 1), (1, 0)], "R": [(1, 1)]},
    "grbg": {"G": [(0, 0), (1, 1)], "R": [(0, 1)], "B": [(1, 0)]},
}


def bayer_mosaic(rgb: np.ndarray, pattern: str = "gbrg") -> np.ndarray:
    """Sample an RGB image (H, W, 3) as a single-channel Bayer sensor would."""
    raw = np.empty(rgb.shape[:2], rgb.dtype)
    for channel, sites in BAYER_SITES[pattern].items():
        c = "RGB".index(channel)
        for dy, dx in sites:
            raw[dy::2, dx::2] = rgb[dy::2, dx::2, c]
    return raw


def radial_distortion_maps(calib: StereoCalib, k1: float) -> tuple[np.ndarray, np.ndarray]:
    """For every undistorted pixel, the distorted pixel it comes from (one-coefficient
    radial model about the principal point): float64 maps (H, W), RobotCar LUT semantics."""
    K = calib.K
    maps = cv2.initUndistortRectifyMap(
        K, np.array([k1, 0.0, 0.0, 0.0]), None, K, (calib.width, calib.height), cv2.CV_32FC1
    )
    return maps[0].astype(np.float64), maps[1].astype(np.float64)


def distort_image(rgb: np.ndarray, calib: StereoCalib, k1: float) -> np.ndarray:
    """What a camera with radial distortion ``k1`` would have recorded: for each
    distorted pixel, sample the undistorted image where that pixel undistorts to."""
    h, w = rgb.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=-1).reshape(-1, 1, 2)
    K = calib.K
    und = cv2.undistortPointsIter(
        pts, K, np.array([k1, 0.0, 0.0, 0.0]), None, K, (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-6)
    ).reshape(h, w, 2)
    return cv2.remap(
        rgb, und[..., 0].astype(np.float32), und[..., 1].astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT
    )


def write_camera_model(path: Path, calib: StereoCalib, translation_y: float) -> None:
    """A RobotCar model file: ``fx fy cx cy`` and the G_camera_image of the SDK's stereo
    models (image axes → camera base axes), offset ``translation_y`` to the right."""
    G = np.array([[0.0, 0.0, 1.0, 0.0], [1.0, 0.0, 0.0, translation_y], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    lines = [f"{calib.fx:.6f} {calib.fy:.6f} {calib.cx:.6f} {calib.cy:.6f}"]
    lines += [" ".join(f"{v:.6f}" for v in row) for row in G]
    path.write_text("\n".join(lines) + "\n")


def write_robotcar_fixture(
    out_dir: str | Path,
    left_frames: Sequence[np.ndarray],
    right_frames: Sequence[np.ndarray],
    calib: StereoCalib,
    traversal: str = "2015-01-01-00-00-00",
    pair: str = "wide",
    k1: float = -0.08,
    t0_us: int = 1_420_070_400_000_000,
    frames_per_chunk: int = 2,
    missing_chunks: Sequence[int] = (),
    list_missing: bool = True,
    write_lut: bool = True,
) -> Path:
    """Write a RobotCar traversal (and ``models/``) under ``out_dir`` from RGB frames.

    Each RGB frame is distorted with radial coefficient ``k1`` and mosaicked to GBRG; the
    LUT written beside the models maps back, so demosaic + remap recovers the frames.
    Chunk ids start at 1, ``frames_per_chunk`` frames each; chunks in ``missing_chunks``
    get no images (as if not downloaded) and, unless ``list_missing``, no timestamps
    either. Returns the traversal folder.
    """
    out_dir = Path(out_dir)
    (left_dir, left_model), (right_dir, right_model) = PAIRS[pair]
    models = out_dir / "models"
    models.mkdir(parents=True, exist_ok=True)
    write_camera_model(models / f"{left_model}.txt", calib, 0.0)
    write_camera_model(models / f"{right_model}.txt", calib, calib.baseline_m)
    if write_lut:
        map_x, map_y = radial_distortion_maps(calib, k1)
        lut = np.concatenate([map_x.ravel(), map_y.ravel()]).astype("<f8")
        for name in (left_model, right_model):
            lut.tofile(models / f"{name}_distortion_lut.bin")

    trav = out_dir / traversal
    for d in (left_dir, right_dir):
        (trav / "stereo" / d).mkdir(parents=True, exist_ok=True)
    lines = []
    for i, (lf, rf) in enumerate(zip(left_frames, right_frames, strict=True)):
        t_us = t0_us + round(i * 1e6 / ROBOTCAR_HZ)
        chunk = 1 + i // frames_per_chunk
        if chunk in missing_chunks:
            if list_missing:
                lines.append(f"{t_us} {chunk}")
            continue
        lines.append(f"{t_us} {chunk}")
        for d, rgb in ((left_dir, lf), (right_dir, rf)):
            raw = bayer_mosaic(distort_image(rgb, calib, k1) if write_lut else rgb, "gbrg")
            cv2.imwrite(str(trav / "stereo" / d / f"{t_us}.png"), raw)
    (trav / "stereo.timestamps").write_text("\n".join(lines) + "\n")
    return trav


def robotcar_as_downloaded(extracted: str | Path, out_dir: str | Path, traversal: str, small: str = "tar") -> Path:
    """The extracted RobotCar root ``extracted``'s ``traversal`` written under ``out_dir`` as it is
    downloaded: ``<traversal>_stereo_<camera>_<NN>.tar`` per camera and chunk id (uncompressed,
    members ``<traversal>/stereo/<camera>/<µs>.png``), ``models/`` copied. ``small``: "tar" puts
    ``stereo.timestamps`` (and ``vo/vo.csv`` when there is one) in ``<traversal>_stereo_timestamps.tar``
    (and ``<traversal>_vo.tar``), "plain" copies them as files. Returns ``out_dir``."""
    src, out = Path(extracted) / traversal, Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    shutil.copytree(Path(extracted) / "models", out / "models", dirs_exist_ok=True)
    chunk_of = {int(t): int(c) for t, c in (ln.split() for ln in (src / "stereo.timestamps").read_bytes().decode().split("\n")
                                            if ln.strip())}
    for cam_dir in sorted((src / "stereo").iterdir()):
        by_chunk: dict[int, list[Path]] = {}
        for png in sorted(cam_dir.glob("*.png")):
            by_chunk.setdefault(chunk_of[int(png.stem)], []).append(png)
        for chunk, pngs in by_chunk.items():
            with tarfile.open(out / f"{traversal}_stereo_{cam_dir.name}_{chunk:02d}.tar", "w", format=tarfile.GNU_FORMAT) as tf:
                for png in pngs:
                    tf.add(png, f"{traversal}/stereo/{cam_dir.name}/{png.name}")
    for rel, archive in (("stereo.timestamps", "stereo_timestamps"), ("vo/vo.csv", "vo")):
        if not (src / rel).is_file():
            continue
        if small == "tar":
            with tarfile.open(out / f"{traversal}_{archive}.tar", "w") as tf:
                tf.add(src / rel, f"{traversal}/{rel}")
        else:
            (out / traversal / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(src / rel, out / traversal / rel)
    return out


# -- ROS 2 MCAP ------------------------------------------------------------------------------

# Message definitions in the concatenated "ros2msg" form rosbag2 stores in MCAP schemas,
# written from the ROS 2 (Humble) interface files of sensor_msgs, std_msgs and
# builtin_interfaces.
_SEP = "=" * 80
_TIME_MSG = "int32 sec\nuint32 nanosec\n"
_HEADER_MSG = "builtin_interfaces/Time stamp\nstring frame_id\n"
_DEPS = f"{_SEP}\nMSG: std_msgs/Header\n{_HEADER_MSG}{_SEP}\nMSG: builtin_interfaces/Time\n{_TIME_MSG}"
IMAGE_MSGDEF = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring encoding\nuint8 is_bigendian\nuint32 step\n"
    "uint8[] data\n" + _DEPS
)
COMPRESSED_IMAGE_MSGDEF = "std_msgs/Header header\nstring format\nuint8[] data\n" + _DEPS
CAMERA_INFO_MSGDEF = (
    "std_msgs/Header header\nuint32 height\nuint32 width\nstring distortion_model\nfloat64[] d\n"
    "float64[9] k\nfloat64[9] r\nfloat64[12] p\nuint32 binning_x\nuint32 binning_y\n"
    "sensor_msgs/RegionOfInterest roi\n"
    f"{_SEP}\nMSG: sensor_msgs/RegionOfInterest\n"
    "uint32 x_offset\nuint32 y_offset\nuint32 height\nuint32 width\nbool do_rectify\n" + _DEPS
)

def camera_info(calib: StereoCalib, stamp_ns: int, frame_id: str, right: bool) -> dict:
    """A rectified sensor_msgs/CameraInfo; the right P carries −fx·baseline (ROS convention)."""
    K = [calib.fx, 0.0, calib.cx, 0.0, calib.fy, calib.cy, 0.0, 0.0, 1.0]
    tx = -calib.fx * calib.baseline_m if right else 0.0
    P = [calib.fx, 0.0, calib.cx, tx, 0.0, calib.fy, calib.cy, 0.0, 0.0, 0.0, 1.0, 0.0]
    return {
        "header": _header(stamp_ns, frame_id),
        "height": calib.height,
        "width": calib.width,
        "distortion_model": "plumb_bob",
        "d": [0.0] * 5,
        "k": K,
        "r": [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        "p": P,
        "binning_x": 0,
        "binning_y": 0,
        "roi": {"x_offset": 0, "y_offset": 0, "height": 0, "width": 0, "do_rectify": False},
    }


def _header(stamp_ns: int, frame_id: str) -> dict:
    return {"stamp": {"sec": stamp_ns // 1_000_000_000, "nanosec": stamp_ns % 1_000_000_000}, "frame_id": frame_id}


def image_message(rgb: np.ndarray, stamp_ns: int, frame_id: str, encoding: str = "rgb8") -> dict:
    """A sensor_msgs/Image holding ``rgb`` in ``encoding`` (rgb8, bgr8, mono8, bayer_*8)."""
    if encoding == "rgb8":
        data = rgb
    elif encoding == "bgr8":
        data = rgb[..., ::-1]
    elif encoding == "mono8":
        data = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    elif encoding.startswith("bayer_") and encoding.endswith("8"):
        data = bayer_mosaic(rgb, encoding[len("bayer_") : -1])
    else:
        raise ValueError(f"fixture writer does not handle encoding {encoding!r}")
    data = np.ascontiguousarray(data)
    h, w = data.shape[:2]
    return {
        "header": _header(stamp_ns, frame_id),
        "height": h,
        "width": w,
        "encoding": encoding,
        "is_bigendian": 0,
        "step": data.strides[0],
        "data": data.tobytes(),
    }


def compressed_image_message(rgb: np.ndarray, stamp_ns: int, frame_id: str, fmt: str = "png") -> dict:
    """A sensor_msgs/CompressedImage as image_transport writes it (BGR inside the file)."""
    ok, buf = cv2.imencode("." + fmt, np.ascontiguousarray(rgb[..., ::-1]))
    if not ok:
        raise ValueError(f"OpenCV could not encode {fmt}")
    return {"header": _header(stamp_ns, frame_id), "format": f"rgb8; {fmt} compressed bgr8", "data": buf.tobytes()}


def write_stereo_mcap(
    path: str | Path,
    left_frames: Sequence[np.ndarray],
    right_frames: Sequence[np.ndarray],
    calib: StereoCalib,
    t0_ns: int = 1_700_000_000_000_000_000,
    hz: float = 10.0,
    compressed: bool = False,
    encoding: str = "rgb8",
    namespace: str = "/stereo",
    right_offset_ns: int = 0,
    log_delay_ns: int = 3_000_000,
    with_camera_info: bool = True,
    skip_right: Sequence[int] = (),
    stamps_ns: Sequence[int] | None = None,
) -> dict[str, str]:
    """Write a ROS 2 MCAP with left/right images and CameraInfo, one message each per frame.

    Header stamps are ``t0_ns + i/hz`` (the right camera ``right_offset_ns`` later); log
    times are the stamps plus ``log_delay_ns``, as a recorder sees them. Frames listed in
    ``skip_right`` get no right image; ``stamps_ns`` gives each frame's stamp instead
    (repeats allowed, to stage duplicate stamps). Returns the topic names used.
    """
    from mcap_ros2.writer import Writer

    suffix = "image_raw/compressed" if compressed else "image_raw"
    topics = {
        "left": f"{namespace}/left/{suffix}",
        "right": f"{namespace}/right/{suffix}",
        "left_info": f"{namespace}/left/camera_info",
        "right_info": f"{namespace}/right/camera_info",
    }
    with open(path, "wb") as f:
        writer = Writer(f)
        if compressed:
            img_schema = writer.register_msgdef("sensor_msgs/msg/CompressedImage", COMPRESSED_IMAGE_MSGDEF)
        else:
            img_schema = writer.register_msgdef("sensor_msgs/msg/Image", IMAGE_MSGDEF)
        info_schema = writer.register_msgdef("sensor_msgs/msg/CameraInfo", CAMERA_INFO_MSGDEF)
        for i, (lf, rf) in enumerate(zip(left_frames, right_frames, strict=True)):
            stamp = t0_ns + round(i * 1e9 / hz) if stamps_ns is None else int(stamps_ns[i])
            for side, rgb, t in (("left", lf, stamp), ("right", rf, stamp + right_offset_ns)):
                if side == "right" and i in skip_right:
                    continue
                frame_id = f"{namespace.strip('/')}_{side}_optical"
                if with_camera_info:
                    info = camera_info(calib, t, frame_id, right=side == "right")
                    writer.write_message(topics[f"{side}_info"], info_schema, info, log_time=t + log_delay_ns)
                msg = (
                    compressed_image_message(rgb, t, frame_id)
                    if compressed
                    else image_message(rgb, t, frame_id, encoding)
                )
                writer.write_message(topics[side], img_schema, msg, log_time=t + log_delay_ns)
        writer.finish()
    return topics
