"""The projection M of the paper: a rotation and a translation, with known intrinsics
(perspective) or without (weak perspective).

Both models have six parameters per problem, all of order one so that the solver sees a well-scaled
problem: params = (r (3): axis-angle rotation, a, b, w).
- Perspective, intrinsics K given: X_cam = R X + depth * (a * spread / f, b * spread / f, 1) with
  depth = exp(w) * DEPTH_UNIT mm; uv = K X_cam / z. (a, b) is the root's image position in units of
  the 2D pose's spread, so that a unit of a, of b or of rotation moves the joints by a similar
  number of pixels: the solver then sees a well-conditioned problem.
- Weak perspective, no intrinsics: uv = centre + spread * (exp(w) * (R X)_xy / DEPTH_UNIT + (a, b)),
  where `centre` (px) and `spread` (px) are fixed per problem from the 2D pose being fitted. This
  is an orthographic camera with unknown scale: what a person far from the camera looks like.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

DEPTH_UNIT = 1000.0  # mm


def rotation_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula. rotvec: (..., 3) radians -> (..., 3, 3); smooth at zero.
    sin(t) / t = sinc(t / pi) and (1 - cos t) / t^2 = sinc(t / 2 pi)^2 / 2 hold at t = 0 too."""
    turns = rotvec.norm(dim=-1)[..., None, None] / torch.pi
    x, y, z = rotvec.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack([zero, -z, y, z, zero, -x, -y, x, zero], -1).unflatten(-1, (3, 3))
    eye = torch.eye(3, dtype=rotvec.dtype, device=rotvec.device)
    return eye + torch.sinc(turns) * skew + 0.5 * torch.sinc(turns / 2) ** 2 * (skew @ skew)


def quaternion(rotation: torch.Tensor) -> torch.Tensor:
    """(..., 3, 3) rotations -> (..., 4) unit quaternions (w, x, y, z), w >= 0: taken from the
    largest of its four candidate forms (Shepperd's method), which keeps every one well
    conditioned."""
    m = rotation.flatten(-2).unbind(-1)  # m[3 * row + col]
    trace_forms = torch.stack(
        [
            1 + m[0] + m[4] + m[8],
            1 + m[0] - m[4] - m[8],
            1 - m[0] + m[4] - m[8],
            1 - m[0] - m[4] + m[8],
        ],
        -1,
    )
    root = trace_forms.clamp_min(0).sqrt()  # 2 |q_i| of each quaternion component i
    forms = torch.stack(
        [
            torch.stack([root[..., 0] ** 2, m[7] - m[5], m[2] - m[6], m[3] - m[1]], -1),
            torch.stack([m[7] - m[5], root[..., 1] ** 2, m[3] + m[1], m[2] + m[6]], -1),
            torch.stack([m[2] - m[6], m[3] + m[1], root[..., 2] ** 2, m[5] + m[7]], -1),
            torch.stack([m[3] - m[1], m[6] + m[2], m[7] + m[5], root[..., 3] ** 2], -1),
        ],
        -2,
    ) / (2 * root[..., None].clamp_min(0.1))  # each row: (w, x, y, z) up to a common factor
    best = root.argmax(-1)[..., None, None].expand(*root.shape[:-1], 1, 4)
    unit = torch.gather(forms, -2, best)[..., 0, :]
    return unit * torch.where(unit[..., :1] < 0, -1.0, 1.0)  # w >= 0


def rotation_vector(rotation: torch.Tensor) -> torch.Tensor:
    """The inverse of rotation_matrix: (..., 3, 3) -> (..., 3) radians, angle in [0, pi],
    through the unit quaternion."""
    q = quaternion(rotation)
    w, v = q[..., 0], q[..., 1:]
    sin_half = v.norm(dim=-1)
    # angle / sin(angle / 2), with its limit 2 / w near zero
    factor = torch.where(
        sin_half > 1e-6, 2 * torch.atan2(sin_half, w) / sin_half.clamp_min(1e-12), 2 / w
    )
    return factor[..., None] * v


@dataclass
class CameraFrame:
    """What stays fixed while M is fitted, per problem (leading dims ...).

    intrinsics: (..., 3, 3) K, or None for weak perspective; centre (..., 2) and spread (...)
    in px define the weak-perspective image frame (unused with intrinsics).
    """

    intrinsics: torch.Tensor | None
    centre: torch.Tensor
    spread: torch.Tensor

    def unsqueeze(self, dim: int) -> CameraFrame:
        """Insert a broadcast dimension into the leading dims."""
        k = None if self.intrinsics is None else self.intrinsics.unsqueeze(dim)
        return CameraFrame(k, self.centre.unsqueeze(dim), self.spread.unsqueeze(dim))

    def take(self, rows: torch.Tensor) -> CameraFrame:
        """The problems `rows` (index into the leading dim)."""
        k = None if self.intrinsics is None else self.intrinsics[rows]
        return CameraFrame(k, self.centre[rows], self.spread[rows])


def project(points: torch.Tensor, params: torch.Tensor, frame: CameraFrame) -> torch.Tensor:
    """points: (..., N, J, 3) mm; params: (..., 6); frame with leading dims (...).
    Returns (..., N, J, 2) px."""
    return project_rotated(rotate(points, rotation_matrix(params[..., :3])), params[..., 3:], frame)


def rotate(points: torch.Tensor, rotation: torch.Tensor) -> torch.Tensor:
    """points: (..., N, J, 3); rotation: (..., 3, 3). Returns R X, (..., N, J, 3)."""
    # One (N*J, 3) @ (3, 3) product per problem: far faster than N*J tiny batched products.
    return (points.flatten(-3, -2) @ rotation.transpose(-1, -2)).reshape(points.shape)


def project_rotated(
    rotated: torch.Tensor, shift: torch.Tensor, frame: CameraFrame, jacobian: bool = False
):
    """The projection of points already rotated by M's rotation.

    rotated: (..., N, J, 3) mm, R X; shift: (..., 3) M's (a, b, w). Returns uv (..., N, J, 2) px,
    and with `jacobian` also d uv / d rotated (..., N, J, 2, 3) and d uv / d (a, b, w)
    (..., N, J, 2, 3).
    """
    spread = frame.spread[..., None, None, None]  # (..., 1, 1, 1)
    if frame.intrinsics is None:
        scale = spread * torch.exp(shift[..., 2:3])[..., None, None] / DEPTH_UNIT  # px per mm
        image = scale * rotated[..., :2]  # (..., N, J, 2) px from the frame's origin
        uv = image + (frame.centre + frame.spread[..., None] * shift[..., :2])[..., None, None, :]
        if not jacobian:
            return uv
        eye = torch.eye(2, 3, dtype=uv.dtype, device=uv.device)
        d_points = (scale[..., None] * eye).expand(*uv.shape, 3)
        d_ab = (spread[..., None] * eye[:, :2]).expand(*uv.shape, 2)
        return uv, d_points, torch.cat([d_ab, image[..., None]], -1)  # d uv / d w = image
    focal, principal = _focal_principal(frame.intrinsics)
    move = camera_translation(shift, frame, frame.intrinsics)  # (..., 3) mm
    depth = move[..., 2:3]
    cam = rotated + move[..., None, None, :]
    inverse_z = 1 / cam[..., 2:3].clamp_min(1.0)  # a point behind the camera must not flip sign
    f = focal[..., None, None, :]
    image = f * cam[..., :2] * inverse_z  # (..., N, J, 2) px from the principal point
    uv = image + principal[..., None, None, :]
    if not jacobian:
        return uv
    # d uv / d cam = [f / z, 0, -image_x / z; 0, f / z, -image_y / z]
    d_points = torch.cat([torch.diag_embed(f * inverse_z), (-image * inverse_z)[..., None]], -1)
    # move = depth (a spread / f_x, b spread / f_y, 1): d uv / d a and d b are depth spread / z
    # on their own axis; d move / d w = move
    ab = (depth * frame.spread[..., None])[..., None, None, :] * inverse_z  # (..., N, J, 1)
    d_w = (f * move[..., None, None, :2] - image * move[..., None, None, 2:]) * inverse_z
    d_shift = torch.cat([torch.diag_embed(ab.expand_as(image)), d_w[..., None]], -1)
    return uv, d_points, d_shift


def camera_translation(
    shift: torch.Tensor, frame: CameraFrame, camera: torch.Tensor
) -> torch.Tensor:
    """T (..., 3) mm such that R X + T are the fitted points in the coordinates of `camera`
    (x right, y down, z away from it): where M places the person in space.

    shift: (..., 3) M's (a, b, w); camera: (..., 3, 3) the intrinsics K of the camera that took
    the image (with perspective, frame.intrinsics).
    - Perspective: T = depth (a spread / f_x, b spread / f_y, 1), depth = exp(w) DEPTH_UNIT: the
      points that M projects.
    - Weak perspective, an orthographic view at s = spread exp(w) / DEPTH_UNIT px per mm: X's
      origin, which M draws at uv0 = centre + spread (a, b), at the depth Z = f / s at which the
      camera's focal length f (the mean of f_x and f_y) draws a millimetre as s pixels:
      T = Z ((uv0 - principal) / (f_x, f_y), 1).
    """
    focal, principal = _focal_principal(camera)
    one = torch.ones_like(shift[..., :1])
    if frame.intrinsics is not None:
        depth = torch.exp(shift[..., 2:3]) * DEPTH_UNIT
        return depth * torch.cat([shift[..., :2] * frame.spread[..., None] / focal, one], -1)
    scale = frame.spread[..., None] * torch.exp(shift[..., 2:3]) / DEPTH_UNIT  # px per mm
    depth = focal.mean(-1, keepdim=True) / scale
    drawn_at = frame.centre + frame.spread[..., None] * shift[..., :2]  # uv0, px
    return depth * torch.cat([(drawn_at - principal) / focal, one], -1)


# The field of view, across the image's longer side, assumed for a photo whose camera is not
# known: about a phone's or a compact camera's standard lens. A guess, not a fit: a person's
# depth scales with the focal length, so callers who know theirs should pass it.
ASSUMED_FOV_DEG = 55.0


def pinhole(width: float, height: float, focal_px: float | None = None) -> torch.Tensor:
    """(3, 3) intrinsics of a camera with square pixels and its principal point at the centre
    of a width x height px image; focal_px None: the focal length of ASSUMED_FOV_DEG."""
    if focal_px is None:
        focal_px = max(width, height) / 2 / math.tan(math.radians(ASSUMED_FOV_DEG) / 2)
    return torch.tensor([[focal_px, 0.0, width / 2], [0.0, focal_px, height / 2], [0.0, 0.0, 1.0]])


def _focal_principal(k: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(..., 3, 3) intrinsics -> focal lengths (..., 2) and principal point (..., 2), px."""
    focal = torch.stack([k[..., 0, 0], k[..., 1, 1]], -1)
    return focal, torch.stack([k[..., 0, 2], k[..., 1, 2]], -1)


def initial_params(
    candidates: torch.Tensor, joints_2d: torch.Tensor, mask: torch.Tensor, frame: CameraFrame
) -> torch.Tensor:
    """Start M at the virtual camera of the candidates (identity rotation: they are already
    camera-oriented) with the scale and position that best match the 2D pose.

    candidates: (..., N, 14, 3) mm; joints_2d: (..., 14, 2) px; mask: (..., 14) float, the joints
    used. Returns params (..., 6).
    """
    mean_pose = candidates.mean(-3)  # (..., 14, 3)
    m = mask[..., None]
    count = m.sum(-2).clamp_min(1)
    c2 = (joints_2d * m).sum(-2) / count  # (..., 2) px
    c3 = (mean_pose * m).sum(-2) / count  # (..., 3) mm
    spread_2d = (((joints_2d - c2[..., None, :]) ** 2 * m).sum((-1, -2)) / count[..., 0]).sqrt()
    spread_3d = ((mean_pose[..., :2] - c3[..., None, :2]) ** 2 * m).sum((-1, -2)) / count[..., 0]
    spread_3d = spread_3d.sqrt().clamp_min(1.0)
    zeros = torch.zeros_like(c2[..., :1])
    if frame.intrinsics is None:
        scale = spread_2d / frame.spread * DEPTH_UNIT / spread_3d  # exp(w)
        ab = (c2 - frame.centre) / frame.spread[..., None]
        ab = ab - scale[..., None] * c3[..., :2] / DEPTH_UNIT
        return torch.cat([zeros, zeros, zeros, ab, scale.clamp_min(1e-6).log()[..., None]], -1)
    focal, principal = _focal_principal(frame.intrinsics)
    depth = focal.mean(-1) * spread_3d / spread_2d.clamp_min(1e-3)  # mm
    ab = (c2 - principal) / focal - c3[..., :2] / depth[..., None]
    ab = ab * focal / frame.spread[..., None]
    return torch.cat([zeros, zeros, zeros, ab, (depth / DEPTH_UNIT).log()[..., None]], -1)


def image_frame(
    joints_2d: torch.Tensor, visible: torch.Tensor, intrinsics: torch.Tensor | None
) -> CameraFrame:
    """The fixed per-pose frame of the projection model: the visible joints' centroid and RMS
    spread (px) for weak perspective; intrinsics when given. joints_2d: (B, 14, 2) px;
    visible: (B, 14) bool; intrinsics: None or (B, 3, 3)."""
    m = visible.float()[..., None]
    centre = (joints_2d * m).sum(-2) / m.sum(-2)
    spread = (((joints_2d - centre[:, None]) ** 2 * m).sum((-1, -2)) / m.sum((-1, -2))).sqrt()
    return CameraFrame(intrinsics, centre, spread.clamp_min(1.0))
