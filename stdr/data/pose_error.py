"""How far one set of cameras is from another: a similarity alignment of their centres, then the
angles between their rays (stdr-data capture's checks against a reference capture)."""
from __future__ import annotations


import cv2
import numpy as np


def align_similarity(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Least-squares similarity (s, R, t) with dst ~ s R src + t (Umeyama 1991); src, dst [N, 3], N >= 3."""
    src, dst = np.asarray(src, np.float64), np.asarray(dst, np.float64)
    if src.shape != dst.shape or src.ndim != 2 or src.shape[1] != 3 or len(src) < 3:
        raise ValueError(f"align_similarity: two [N, 3] arrays with N >= 3, got {src.shape} and {dst.shape}")
    mu_s, mu_d = src.mean(0), dst.mean(0)
    a, b = src - mu_s, dst - mu_d
    cov = b.T @ a / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (a ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var)
    return s, R, mu_d - s * R @ mu_s


def camera_rays(cam: dict, points=((0.5, 0.5), (0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75))) -> np.ndarray:
    """World directions [P, 3] of the rays through image points given as fractions of the image
    size, for a Nerfies camera file's content (its intrinsics and lens distortion applied)."""
    R = np.asarray(cam["orientation"], dtype=np.float64)
    f = float(cam["focal_length"])
    fy = f * float(cam.get("pixel_aspect_ratio", 1.0))
    cx, cy = cam["principal_point"]
    W, H = cam["image_size"]
    k = (list(cam.get("radial_distortion", [0.0, 0.0, 0.0])) + [0.0, 0.0])[:3]
    p = list(cam.get("tangential_distortion", [0.0, 0.0]))
    K = np.array([[f, float(cam.get("skew", 0.0)), cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    px = np.array([[[u * W, v * H]] for u, v in points], dtype=np.float64)
    xy = cv2.undistortPoints(px, K, np.array([k[0], k[1], p[0], p[1], k[2]]))[:, 0]
    d = np.concatenate([xy, np.ones((len(xy), 1))], 1) @ R  # R^T x for each row
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def ray_errors(cams_est: list[dict], cams_ref: list[dict]) -> dict:
    """Camera poses of an estimate against a reference (Nerfies camera files' content, matched
    by position), after the similarity that best maps the estimated centres onto the
    reference's. Centres: distance in units of the reference trajectory's extent (the largest
    distance between two reference centres). Orientation: the angle between the two world rays
    through the same image points (centre and quarter points), each camera with its own
    intrinsics and distortion, so that two solutions that trade a principal-point offset
    against a rotation (which look alike in the image) are compared by what they see."""
    c_est = np.stack([np.asarray(c["position"], np.float64) for c in cams_est])
    c_ref = np.stack([np.asarray(c["position"], np.float64) for c in cams_ref])
    s, A, t = align_similarity(c_est, c_ref)
    c_al = (s * (A @ c_est.T)).T + t
    extent = float(max(np.linalg.norm(c_ref[:, None] - c_ref[None], axis=-1).max(), 1e-12))
    pos = np.linalg.norm(c_al - c_ref, axis=1) / extent
    ang = np.array([np.degrees(np.arccos(np.clip(np.sum((camera_rays(a) @ A.T) * camera_rays(b), 1), -1, 1))).max()
                    for a, b in zip(cams_est, cams_ref)])
    return {"n": int(len(pos)), "scale": s, "extent": extent,
            "position_median": float(np.median(pos)), "position_max": float(pos.max()),
            "ray_median_deg": float(np.median(ang)), "ray_max_deg": float(ang.max())}
