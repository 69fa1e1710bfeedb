"""Reader for COLMAP's binary sparse model (cameras.bin, images.bin, points3D.bin).

Only what the loaders need: camera intrinsics, image poses with their 2D observations, and the
3D points with colours and tracks. Written from COLMAP's documented binary layout
(little-endian; src/colmap/scene/reconstruction_io.cc), no pycolmap dependency.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import BadInput, MissingInput

# model id -> (name, number of parameters)
CAMERA_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
}


@dataclass
class ColmapCamera:
    id: int
    model: str
    width: int
    height: int
    params: np.ndarray  # [P] in COLMAP's order for the model


@dataclass
class ColmapImage:
    id: int
    name: str
    camera_id: int
    qvec: np.ndarray      # [4] w, x, y, z (world -> camera)
    tvec: np.ndarray      # [3]
    xys: np.ndarray       # [M, 2] keypoints in pixels (COLMAP: pixel centres at +0.5)
    point3d_ids: np.ndarray  # [M] int64, -1 where the keypoint has no 3D point

    @property
    def R(self) -> np.ndarray:  # [3, 3] world -> camera
        return qvec_to_rotmat(self.qvec)


@dataclass
class ColmapModel:
    cameras: dict[int, ColmapCamera]
    images: dict[int, ColmapImage]
    point_ids: np.ndarray  # [P] int64
    xyz: np.ndarray        # [P, 3] float64
    rgb: np.ndarray        # [P, 3] uint8
    error: np.ndarray      # [P] mean reprojection error (pixels)
    track_len: np.ndarray  # [P] number of images observing the point


def qvec_to_rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


class _Reader:
    def __init__(self, path: Path):
        self.path = path
        self.buf = path.read_bytes()
        self.pos = 0

    def read(self, fmt: str):
        fmt = "<" + fmt
        n = struct.calcsize(fmt)
        if self.pos + n > len(self.buf):
            raise BadInput(f"{self.path}: truncated COLMAP binary file (needed {n} bytes at offset "
                             f"{self.pos}, file has {len(self.buf)})")
        out = struct.unpack_from(fmt, self.buf, self.pos)
        self.pos += n
        return out

    def array(self, dtype, count: int) -> np.ndarray:
        dt = np.dtype(dtype).newbyteorder("<")
        n = dt.itemsize * count
        if self.pos + n > len(self.buf):
            raise BadInput(f"{self.path}: truncated COLMAP binary file")
        out = np.frombuffer(self.buf, dtype=dt, count=count, offset=self.pos)
        self.pos += n
        return out

    def cstring(self) -> str:
        end = self.buf.find(b"\x00", self.pos)
        if end < 0:
            raise BadInput(f"{self.path}: truncated COLMAP binary file (unterminated image name)")
        s = self.buf[self.pos:end].decode("utf-8")
        self.pos = end + 1
        return s

    def done(self) -> None:
        if self.pos != len(self.buf):
            raise BadInput(f"{self.path}: {len(self.buf) - self.pos} trailing bytes; not a COLMAP binary model")


def read_cameras(path: Path) -> dict[int, ColmapCamera]:
    r = _Reader(path)
    (n,) = r.read("Q")
    cams = {}
    for _ in range(n):
        cid, model_id, w, h = r.read("iiQQ")
        if model_id not in CAMERA_MODELS:
            raise BadInput(f"{path}: unknown COLMAP camera model id {model_id}")
        name, npar = CAMERA_MODELS[model_id]
        cams[cid] = ColmapCamera(cid, name, int(w), int(h), r.array(np.float64, npar).copy())
    r.done()
    return cams


def read_images(path: Path) -> dict[int, ColmapImage]:
    r = _Reader(path)
    (n,) = r.read("Q")
    images = {}
    for _ in range(n):
        iid, qw, qx, qy, qz, tx, ty, tz, cid = r.read("idddddddi")
        name = r.cstring()
        (m,) = r.read("Q")
        rec = r.array(np.dtype([("x", "<f8"), ("y", "<f8"), ("id", "<i8")]), m)
        images[iid] = ColmapImage(iid, name, cid, np.array([qw, qx, qy, qz]), np.array([tx, ty, tz]),
                                  np.stack([rec["x"], rec["y"]], -1).astype(np.float64),
                                  rec["id"].astype(np.int64))
    r.done()
    return images


def read_points3d(path: Path):
    r = _Reader(path)
    (n,) = r.read("Q")
    ids = np.empty(n, np.int64)
    xyz = np.empty((n, 3), np.float64)
    rgb = np.empty((n, 3), np.uint8)
    err = np.empty(n, np.float64)
    tl = np.empty(n, np.int64)
    for i in range(n):
        pid, x, y, z, cr, cg, cb, e = r.read("QdddBBBd")
        (m,) = r.read("Q")
        r.array(np.int32, 2 * m)  # track: (image_id, point2D_idx) pairs
        ids[i], xyz[i], rgb[i], err[i], tl[i] = pid, (x, y, z), (cr, cg, cb), e, m
    r.done()
    return ids, xyz, rgb, err, tl


def read_model(folder: str | Path) -> ColmapModel:
    """Read cameras.bin, images.bin and points3D.bin from a COLMAP sparse model folder."""
    folder = Path(folder)
    missing = [f for f in ("cameras.bin", "images.bin", "points3D.bin") if not (folder / f).is_file()]
    if missing:
        raise MissingInput(f"{folder}: COLMAP sparse model is missing {', '.join(missing)}")
    ids, xyz, rgb, err, tl = read_points3d(folder / "points3D.bin")
    return ColmapModel(read_cameras(folder / "cameras.bin"), read_images(folder / "images.bin"),
                       ids, xyz, rgb, err, tl)
