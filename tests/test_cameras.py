import math

import numpy as np
import torch

from stdr.cameras import Camera, focal_from_fov, opengl_c2w_to_opencv_w2c


def test_opengl_to_opencv_hand_computed_projection():
    # A Blender camera at (1, -4, 2) looking along +y (world), up = +z, i.e. rotated 90 deg about x
    # from the default (which looks down -z). Camera axes in world: right=+x, up=+z, back=-y.
    c2w = np.eye(4)
    c2w[:3, 0] = [1, 0, 0]
    c2w[:3, 1] = [0, 0, 1]
    c2w[:3, 2] = [0, -1, 0]
    c2w[:3, 3] = [1, -4, 2]
    R, t = opengl_c2w_to_opencv_w2c(c2w)
    cam = Camera(R=torch.tensor(R), t=torch.tensor(t), fx=100.0, fy=80.0, cx=50.0, cy=40.0,
                 width=100, height=80)
    # A point 5 units in front of the camera, 1 to its right and 0.5 above it.
    X = torch.tensor([[2.0, 1.0, 2.5]], dtype=torch.float64)
    uv, z = cam.project(X)
    # by hand: x_cam = 1 (right), y_cam = -0.5 (OpenCV y is down), z_cam = 5
    assert math.isclose(float(z), 5.0, abs_tol=1e-12)
    assert np.allclose(uv.numpy(), [[50 + 100 * 1 / 5, 40 + 80 * (-0.5) / 5]], atol=1e-10)
    # translation keeps its sign (the peers' conversion flips t_x, t_y)
    assert np.allclose(cam.center.numpy(), [1, -4, 2])


def test_camera_not_looking_at_origin_keeps_translation():
    rng = np.random.default_rng(0)
    for _ in range(5):
        A = rng.normal(size=(3, 3))
        Q, _ = np.linalg.qr(A)
        Q *= np.sign(np.linalg.det(Q))
        c2w = np.eye(4)
        c2w[:3, :3] = Q
        c2w[:3, 3] = rng.normal(size=3) * 3
        R, t = opengl_c2w_to_opencv_w2c(c2w)
        # the camera centre maps to the origin, and a point on the OpenGL -z axis has positive depth
        assert np.allclose(R @ c2w[:3, 3] + t, 0, atol=1e-12)
        p = c2w[:3, 3] - 2.0 * c2w[:3, 2]
        assert np.isclose((R @ p + t)[2], 2.0)
        assert np.isclose(np.linalg.det(R), 1.0)


def test_scaled_intrinsics_and_fov():
    f = focal_from_fov(0.6911112070083618, 800)
    assert math.isclose(f, 1111.1110311937682, rel_tol=1e-9)
    cam = Camera(R=torch.eye(3), t=torch.zeros(3), fx=f, fy=f, cx=400, cy=400, width=800, height=800)
    s = cam.scaled(0.25)
    assert (s.width, s.height) == (200, 200)
    assert math.isclose(s.fx, f / 4) and math.isclose(s.cx, 100.0)
    # a point projects to the same relative image position at both scales
    X = torch.tensor([[0.3, -0.2, 4.0]])
    a, _ = cam.project(X)
    b, _ = s.project(X)
    assert torch.allclose(a / 800, b / 200, atol=1e-6)
