"""Rotation conventions: the one module that converts between them.

Frames
------
* World: a projected CRS, metres, X east, Y north, Z up.
* OpenCV camera (the core's internal frame): x right, y down, z forward (viewing direction).
  A pose is ``cam_from_world``: ``x_cam = R @ x_world + t`` with ``t = -R @ C`` and C the projection centre.
* Photogrammetric image frame (PATB, BINGO, Pix4D, BlocksExchange, Blender's camera): x right, y up, z back
  (pointing from the scene towards the projection centre).

Omega-phi-kappa
---------------
``M = Rx(omega) @ Ry(phi) @ Rz(kappa)`` rotates photo-frame vectors into the world frame
(``world_from_photo``), with the usual right-handed active rotations
``Rx(a) = [[1, 0, 0], [0, cos a, -sin a], [0, sin a, cos a]]`` etc. This is the convention of PATB, BINGO
and Pix4D (BlocksExchange ``<Omega>/<Phi>/<Kappa>`` follow it only with ``CameraOrientation XRightYUp``; its reader
handles the other axis orders); it equals Blender's ``rotation_mode='ZYX'``
with ``rotation_euler = (omega, phi, kappa)``. The OpenCV rotation is ``R = diag(1, -1, -1) @ M.T``.

Yaw-pitch-roll (navigation)
---------------------------
Body frame x forward, y right, z down. Local level frame north-east-down (NED).
``R_ned_from_body = Rz(yaw) @ Ry(pitch) @ Rx(roll)``; yaw is the heading clockwise from grid north.
The world (east-north-up) frame is reached with ``R_enu_from_ned = [[0, 1, 0], [1, 0, 0], [0, 0, -1]]``.
A camera mounted with ``cam_from_body`` (default: a nadir camera whose image top points forward,
``x_cam = y_body``, ``y_cam = -x_body``, ``z_cam = z_body``) has ``R = cam_from_body @ R_ned_from_body.T @
R_enu_from_ned.T``. Grid convergence is ignored: yaw is taken against grid north of the projected CRS.

Yaw-pitch-roll (Metashape camera references)
--------------------------------------------
Metashape's ``camera.reference.rotation`` (and ``<reference yaw pitch roll>`` of its camera XML) turns the photo
frame into the local east-north-up frame by ``M = Rz(-yaw) @ Rx(pitch) @ Ry(roll)``: (0, 0, 0) looks down with the
image top north, yaw turns clockwise from north, pitch 90 looks horizontally towards the yaw. ``M`` is
``Metashape.Utils.ypr2mat`` read in the photo frame (in Metashape's camera frame, x right, y down, z forward, the
reference's rotation is ``M @ diag(1, -1, -1)``, and ``ypr2mat``'s rest pose looks up); the Agisoft forum prints
``ypr2mat(30, 91, 0)``, which :func:`metashape_ypr_to_photo` reproduces to the digits given.

Angles are radians unless a function takes a ``unit`` (``"deg"``, ``"gon"`` or ``"rad"``).
"""

from __future__ import annotations

import numpy as np

from ..errors import ConfigError

FLIP_YZ = np.diag([1.0, -1.0, -1.0])
"""Maps the photogrammetric image frame (x right, y up, z back) to OpenCV's (x right, y down, z forward)."""

ENU_FROM_NED = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
CAM_FROM_BODY_NADIR = np.array([[0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])

ANGLE_UNITS = {"rad": 1.0, "deg": np.pi / 180.0, "gon": np.pi / 200.0, "grad": np.pi / 200.0}


def to_radians(value: float | np.ndarray, unit: str) -> float | np.ndarray:
    """Convert angles in ``unit`` (``deg``, ``gon``/``grad`` or ``rad``) to radians."""
    try:
        return value * ANGLE_UNITS[unit]
    except KeyError:
        raise ConfigError(f"unknown angle unit '{unit}' (use one of deg, gon, rad)") from None


def from_radians(value: float | np.ndarray, unit: str) -> float | np.ndarray:
    """Convert radians to ``unit`` (``deg``, ``gon``/``grad`` or ``rad``)."""
    try:
        return value / ANGLE_UNITS[unit]
    except KeyError:
        raise ConfigError(f"unknown angle unit '{unit}' (use one of deg, gon, rad)") from None


def rot_x(a: float) -> np.ndarray:
    """Active right-handed rotation about x by ``a`` radians, (3, 3)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(a: float) -> np.ndarray:
    """Active right-handed rotation about y by ``a`` radians, (3, 3)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(a: float) -> np.ndarray:
    """Active right-handed rotation about z by ``a`` radians, (3, 3)."""
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def opk_to_world_from_photo(omega: float, phi: float, kappa: float) -> np.ndarray:
    """``M = Rx(omega) Ry(phi) Rz(kappa)``: photo frame (x right, y up, z back) to world, (3, 3)."""
    return rot_x(omega) @ rot_y(phi) @ rot_z(kappa)


def world_from_photo_to_opk(m: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`opk_to_world_from_photo`; phi in [-pi/2, pi/2].

    At the singularity ``|phi| = pi/2`` omega is set to 0 and kappa carries the whole rotation about z.
    """
    m = np.asarray(m, dtype=np.float64)
    # M = Rx(w) Ry(p) Rz(k): m[0,2] = sin p, m[1,2] = -sin w cos p, m[2,2] = cos w cos p,
    # m[0,0] = cos p cos k, m[0,1] = -cos p sin k
    sp = float(np.clip(m[0, 2], -1.0, 1.0))
    phi = float(np.arcsin(sp))
    if abs(sp) < 1.0 - 1e-12:
        omega = float(np.arctan2(-m[1, 2], m[2, 2]))
        kappa = float(np.arctan2(-m[0, 1], m[0, 0]))
    else:
        omega = 0.0
        kappa = float(np.arctan2(m[1, 0], m[1, 1]))
    return omega, phi, kappa


def opk_to_cam_from_world(omega: float, phi: float, kappa: float) -> np.ndarray:
    """OpenCV rotation ``R`` (world to camera, x right, y down, z forward) from omega-phi-kappa radians."""
    return FLIP_YZ @ opk_to_world_from_photo(omega, phi, kappa).T


def cam_from_world_to_opk(r_cam_from_world: np.ndarray) -> tuple[float, float, float]:
    """Omega-phi-kappa radians from an OpenCV ``cam_from_world`` rotation."""
    m = (FLIP_YZ @ np.asarray(r_cam_from_world, dtype=np.float64)).T
    return world_from_photo_to_opk(m)


def world_from_body(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """(3, 3) rotation of body vectors (x forward, y right, z down) into the world (east, north, up) for navigation
    angles in radians (``yaw`` the heading against grid north)."""
    return ENU_FROM_NED @ rot_z(yaw) @ rot_y(pitch) @ rot_x(roll)


def ypr_axes(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """The world axes ``(3, 3)`` (columns, east-north-up) about which small changes of roll, pitch and yaw (in that
    order) turn the body of :func:`world_from_body`: a change ``d (3,)`` of the angles is the small world rotation
    ``axes @ d``. Roll turns about the body's x axis, pitch about the y axis the heading alone turns, yaw about the
    vertical (``R_ned_from_body = Rz(yaw) Ry(pitch) Rx(roll)``, each angle's rotation applied in the frame of the
    ones before it)."""
    rz = ENU_FROM_NED @ rot_z(yaw)
    return np.stack([(rz @ rot_y(pitch))[:, 0], rz[:, 1], ENU_FROM_NED[:, 2]], 1)


def opk_axes(omega: float, phi: float, kappa: float) -> np.ndarray:
    """The world axes ``(3, 3)`` (columns) about which small changes of omega, phi and kappa turn the image of
    :func:`opk_to_world_from_photo`: a change ``d (3,)`` of the angles is the small world rotation ``axes @ d``.
    Omega turns about the world's X axis, phi about the Y axis omega turns, kappa about the image's own z axis (its
    viewing axis: the world's Z for a nadir image, 45 degrees from it for an oblique one)."""
    rx = rot_x(omega)
    return np.stack([np.array([1.0, 0.0, 0.0]), rx[:, 1], (rx @ rot_y(phi))[:, 2]], 1)


def world_axis_sigmas(axes: np.ndarray, sigmas: np.ndarray) -> np.ndarray:
    """Standard deviations ``(3,)`` of small rotations about the world's X, Y, Z axes for independent angles with
    standard deviations ``sigmas (3,)`` turning about ``axes (3, 3)`` (columns, from :func:`opk_axes` or
    :func:`ypr_axes`): the square roots of the diagonal of ``axes diag(sigmas^2) axes^T`` (the correlations are
    dropped, as the adjustment's attitude priors take none)."""
    return np.sqrt((np.asarray(axes, np.float64) ** 2) @ (np.asarray(sigmas, np.float64) ** 2))


ANGLE_SIGMA_RCOND = 0.1
"""Singular values of the squared axes under this share of the largest are dropped by :func:`angle_sigmas`."""


def angle_sigmas(axes: np.ndarray, world: np.ndarray) -> np.ndarray:
    """The angles' standard deviations ``(3,)`` for sigmas ``world (3,)`` about the world's axes: the inverse of
    :func:`world_axis_sigmas` in the least-squares sense where that gives every angle a variance, which is exact
    for world sigmas the angles can give (a nadir image, a flight along a grid axis, an OPK list's own sigmas read
    back).

    Two angles turning about nearly the same pair of world axes (phi and kappa of an image tilted 45 degrees about
    X both turn about Y and Z by halves) cannot be told apart by the world's variances: below
    :data:`ANGLE_SIGMA_RCOND` the smallest singular value is dropped and they share the variance evenly. World sigmas
    that no independent angles give (least-squares variances below zero: nearly equal ones on an image tilted about
    Y, whose omega and kappa turn about axes 45 degrees apart) get each angle's marginal standard deviation under
    them, the square roots of the diagonal of ``axes^-1 diag(world^2) axes^-T``: larger than the world's, as the
    angles' errors would be correlated."""
    a = np.asarray(axes, np.float64)
    w2 = np.asarray(world, np.float64) ** 2
    var = np.linalg.lstsq(a**2, w2, rcond=ANGLE_SIGMA_RCOND)[0]
    if var.min() < 0.0:
        inv = np.linalg.pinv(a)
        var = (inv**2) @ w2
    return np.sqrt(var)


def metashape_ypr_to_photo(yaw: float, pitch: float, roll: float) -> np.ndarray:
    """``world_from_photo`` ``(3, 3)`` (east-north-up from x right, y up, z back) of a Metashape camera reference's
    yaw, pitch and roll (radians; see the module docstring): ``Rz(-yaw) @ Rx(pitch) @ Ry(roll)``."""
    return rot_z(-yaw) @ rot_x(pitch) @ rot_y(roll)


def photo_to_metashape_ypr(m: np.ndarray) -> tuple[float, float, float]:
    """Inverse of :func:`metashape_ypr_to_photo`: yaw, pitch, roll radians of ``world_from_photo m (3, 3)``, pitch in
    [-pi/2, pi/2]. A horizontal view (pitch 90 degrees, where yaw and roll turn about the same axis) gets roll 0."""
    m = np.asarray(m, np.float64)
    pitch = float(np.arcsin(np.clip(m[2, 1], -1.0, 1.0)))
    if np.hypot(m[0, 1], m[1, 1]) > 1e-12:
        return float(np.arctan2(m[0, 1], m[1, 1])), pitch, float(np.arctan2(-m[2, 0], m[2, 2]))
    return float(np.arctan2(-m[1, 0], m[0, 0])), pitch, 0.0


def ypr_to_cam_from_world(
    yaw: float,
    pitch: float,
    roll: float,
    cam_from_body: np.ndarray = CAM_FROM_BODY_NADIR,
) -> np.ndarray:
    """OpenCV ``cam_from_world`` from navigation yaw, pitch, roll (radians) and the camera mount, (3, 3)."""
    return np.asarray(cam_from_body) @ world_from_body(yaw, pitch, roll).T


def cam_from_world_to_ypr(
    r_cam_from_world: np.ndarray,
    cam_from_body: np.ndarray = CAM_FROM_BODY_NADIR,
) -> tuple[float, float, float]:
    """Yaw, pitch, roll radians (pitch in [-pi/2, pi/2]) from an OpenCV rotation and the camera mount."""
    world_from_body = (np.asarray(cam_from_body).T @ np.asarray(r_cam_from_world)).T
    n = ENU_FROM_NED.T @ world_from_body  # ned_from_body = Rz(y) Ry(p) Rx(r)
    sp = float(np.clip(-n[2, 0], -1.0, 1.0))
    pitch = float(np.arcsin(sp))
    if abs(sp) < 1.0 - 1e-12:
        yaw = float(np.arctan2(n[1, 0], n[0, 0]))
        roll = float(np.arctan2(n[2, 1], n[2, 2]))
    else:
        roll = 0.0
        yaw = float(np.arctan2(-n[0, 1], n[1, 1]))
    return yaw, pitch, roll


def mount_rotation(tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    """``cam_from_body`` (3, 3) of a camera tilted ``tilt_deg`` from the body's down axis (z) towards azimuth
    ``azimuth_deg`` (clockwise from the body's forward axis x, towards its right axis y), its image's top turned
    away from that azimuth (a forward-looking camera's image top points up, a nadir camera's forward)."""
    t, a = np.radians(tilt_deg), np.radians(azimuth_deg)
    x, y, z = np.eye(3)
    h = np.cos(a) * x + np.sin(a) * y
    z_cam = np.cos(t) * z + np.sin(t) * h
    y_cam = np.sin(t) * z - np.cos(t) * h
    x_cam = np.cross(y_cam, z_cam)
    return np.stack([x_cam, y_cam, z_cam])


def rotation_angle(r_a: np.ndarray, r_b: np.ndarray) -> float | np.ndarray:
    """Angle in radians of the relative rotation ``r_a @ r_b.T``: ``r_a``, ``r_b`` (3, 3) -> float, or stacks
    ``(k, 3, 3)`` (either may be one rotation) -> ``(k,)``. From the sine and the cosine, so that it is exact near
    zero, where the cosine alone loses half the digits."""
    d = np.asarray(r_a, np.float64) @ np.swapaxes(np.asarray(r_b, np.float64), -1, -2)
    sin = 0.5 * np.linalg.norm(np.stack([d[..., 2, 1] - d[..., 1, 2], d[..., 0, 2] - d[..., 2, 0],
                                         d[..., 1, 0] - d[..., 0, 1]], -1), axis=-1)
    angle = np.arctan2(sin, 0.5 * (np.trace(d, axis1=-2, axis2=-1) - 1.0))
    return float(angle) if angle.ndim == 0 else angle


def skew(v: np.ndarray) -> np.ndarray:
    """The cross-product matrix ``[v]x`` (3, 3) of a vector ``v`` (3,): ``skew(v) @ w == np.cross(v, w)``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def rotvec_to_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues: axis-angle vector (3,) to rotation matrix (3, 3)."""
    v = np.asarray(rotvec, dtype=np.float64)
    a = float(np.linalg.norm(v))
    if a < 1e-15:
        return np.eye(3)
    k = v / a
    kx = skew(k)
    return np.eye(3) + np.sin(a) * kx + (1.0 - np.cos(a)) * (kx @ kx)


def matrix_to_rotvec(r: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) to axis-angle vector (3,)."""
    r = np.asarray(r, dtype=np.float64)
    a = rotation_angle(r, np.eye(3))
    if a < 1e-12:
        return np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]]) / 2.0
    if np.pi - a < 1e-6:
        # axis from the symmetric part: R = 2 k k^T - I at a = pi
        b = (r + np.eye(3)) / 2.0
        i = int(np.argmax(np.diag(b)))
        k = b[:, i] / np.sqrt(max(b[i, i], 1e-300))
        return k * a
    w = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    return w * (a / (2.0 * np.sin(a)))


def orthonormalize(r: np.ndarray) -> np.ndarray:
    """Nearest rotation matrix (SVD), for matrices read from files with limited precision."""
    u, _, vt = np.linalg.svd(np.asarray(r, dtype=np.float64))
    d = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, d]) @ vt
