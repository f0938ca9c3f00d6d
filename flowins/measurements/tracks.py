"""The multi-view update of sparse feature tracks over a sliding window of cloned poses.

The state keeps ``N`` cloned camera poses (:func:`flowins.state.window_layout`): at each
camera frame the filter first updates with the tracks that are complete, then shifts the
window (:func:`flowins.filter.augmentation.augment_pose_rows`), so that clone ``a - 1``
holds the pose ``a`` frames back. A track is used once, over all the frames it was seen in
the window, when it ends (it is not seen in the current frame) or when it has ``N + 1``
views (the current frame and every clone; its observations are then consumed and the
track starts afresh at the next frame). This is the MSCKF of Mourikis and Roumeliotis
(2007), as OpenVINS implements it; ``N = 1`` uses a track between two consecutive frames,
like the paper's two-view update.

For one track seen in ``m`` views ``j`` (pose ``p_j``, ``q_j``: the current pose for age 0,
clone ``a - 1`` for age ``a``) at pixels ``z_j``:

* the point ``X`` (world) is triangulated from all its views: the linear system of every
  view (:func:`flowins.geometry.triangulation.solve_dlt`, ``2m x 4`` rows in normalised
  coordinates, the origin at the newest view's centre), then Gauss-Newton steps on the
  pixel residuals;
* each view's residual is ``r_j = z_j - π(K, R_cw,j (X - c_j))`` (pixels), linearised as
  ``r ≈ H_x δx + H_f δX + n``, ``n ~ N(0, σ² I)``;
* ``X`` is projected out: with ``Π = I - H_f (H_fᵀ H_f)⁻¹ H_fᵀ`` (the projector on the left
  null space of ``H_f``, rank ``2m - 3``), the update uses ``Π r = Π H_x δx + Π n``. Its
  information ``H_xᵀ Π H_x / σ²`` and ``H_xᵀ Π r / σ²`` are those of any orthonormal
  basis ``N`` of that null space (``N Nᵀ = Π``), the MSCKF's ``Nᵀ r``. The update gets the
  rows whitened, ``Π r / σ`` and ``Π H_x / σ`` with noise ``I`` (the whitening of the noise
  ``σ² Π + (I - Π)``: ``σ²`` on the null space, 1 on the directions that carry nothing), and
  ``(2m - 3) log σ``, the ``½ log det`` of that noise on the null space, for the likelihood:
  the NIS and the likelihood are those of the ``2m - 3`` projected rows, and the χ² gate
  tests ``2m - 3`` degrees of freedom. The result equals the update with ``X`` in the
  state (no prior on it) and then marginalised; a test checks it.

A track is left out (``valid = False``) when its views do not fix the point: the
triangulation degenerate (conditioning below ``min_conditioning``), the point behind or
too close to a camera (``min_depth_m``), or the widest angle between its rays below
``min_parallax_rad``.

Batches: every function takes a leading row dimension ``r`` (runs of the batched filter),
``M`` tracks per row (padded, with a mask) and ``V = N + 1`` views per track (padded).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from flowins.config import bounded, check_fields
from flowins.constants import cached_constant, scalar_like
from flowins.filter.augmentation import augment_pose_rows
from flowins.filter.chain import BatchChain, RowBatchEvent
from flowins.filter.ekf import Gate
from flowins.filter.unobservable import transport_heading
from flowins.filter.updater import update_rows
from flowins.geometry import quaternion as quat
from flowins.geometry.triangulation import camera_matrix, solve_dlt
from flowins.measurements.flow import FlowCamera, normalise_pixels, ray_angle
from flowins.measurements.flow_update import stack_cameras
from flowins.state import pose_slices, state_dim, window_size


@dataclass(frozen=True)
class TrackUpdate:
    """How sparse tracks update the filter (config ``filter.tracks``).

    Attributes:
        window: ``N``, the cloned poses in the state; a track is used over at most ``N + 1``
            frames. 0: off (the paper's two-view update of consecutive frames instead).
        sigma_px: the 1-σ of each tracked pixel (both coordinates).
        max_tracks: at most this many tracks per frame update, the longest first (None: all).
        min_parallax_rad: leave out tracks whose rays meet at less than this angle.
        min_depth_m: leave out tracks whose point is closer than this to a camera (or behind it).
        min_conditioning: leave out tracks whose triangulation conditioning ``(σ₃ - σ₄) / σ₁`` is below this.
        refine_iterations: Gauss-Newton steps on the triangulated point.
        gate: the χ² gate of each track (``2m - 3`` degrees of freedom).
        heading_transport: after each update, carry the covariance's heading direction to the
            updated estimate (:func:`~flowins.filter.unobservable.transport_heading`, in place:
            the smoother takes the change for information), so that
            the tracks add no heading information, which no camera has; False: the plain EKF
            update, whose changes of the estimate let later tracks make some up.
    """

    window: int = bounded(10, minimum=0)
    sigma_px: float | Tensor = bounded(0.3, above=0.0)
    max_tracks: int | None = bounded(128, minimum=1)
    min_parallax_rad: float = bounded(0.005, minimum=0.0)
    min_depth_m: float = bounded(0.05, minimum=0.0)
    min_conditioning: float = bounded(1e-9, minimum=0.0)
    refine_iterations: int = bounded(2, minimum=0)
    gate: Gate = field(default_factory=Gate)
    heading_transport: bool = True

    def __post_init__(self) -> None:
        check_fields(self)

    @property
    def views(self) -> int:
        """``V = N + 1``: the most frames a track is used over."""
        return self.window + 1


# ----------------------------------------------------------------------------- the model


@cached_constant
def pose_index(dim: int, device: torch.device) -> Tensor:
    """``(N + 1, 7)``: the state indices of ``(p, q)`` of the pose of each age (0: the current
    pose, ``a``: clone ``a - 1``) in a state of size ``dim``."""
    return torch.stack([torch.cat((torch.arange(p.start, p.stop), torch.arange(q.start, q.stop)))
                        for p, q in pose_slices(dim)]).to(device)


class Projection(NamedTuple):
    """:func:`project` of a point into a camera."""

    pixel: Tensor  # (..., 2) px
    depth: Tensor  # (...,) m, along the optical axis
    H_pose: Tensor | None  # (..., 2, 7) ∂pixel/∂(p, q) of the IMU pose
    H_point: Tensor  # (..., 2, 3) ∂pixel/∂X


def project(X: Tensor, p: Tensor, q: Tensor, K: Tensor, R_ci: Tensor, centre_b: Tensor, *,
            pose_jacobian: bool = True, R_wc: Tensor | None = None) -> Projection:
    """The pixel of the world point ``X`` ``(..., 3)`` seen by the camera on the IMU pose ``p``
    ``(..., 3)``, ``q`` ``(..., 4)`` (intrinsics ``K``, IMU→camera rotation ``R_ci`` and the camera
    centre in the body ``centre_b``, each broadcast), with its Jacobians (``H_pose`` None
    without ``pose_jacobian``). ``R_wc``: the camera's rotation ``R(q) R_ciᵀ`` when the caller
    holds it already (a point projected again into the same views).

    ``X_c = R_ci R(q)ᵀ (X - c_w)`` with the camera centre ``c_w = p + R(q) c_b``,
    ``pixel = (f_x x_c / z_c + c_x, f_y y_c / z_c + c_y)``.
    """
    w = X - p
    R_cw = (quat.to_matrix(q) @ R_ci.transpose(-1, -2) if R_wc is None else R_wc).transpose(-1, -2)
    X_c = (R_cw @ w.unsqueeze(-1)).squeeze(-1) - (R_ci @ centre_b.unsqueeze(-1)).squeeze(-1)
    z = X_c[..., 2]
    z_safe = torch.where(z.abs() > torch.finfo(z.dtype).tiny ** 0.5, z, torch.ones_like(z))
    f = torch.stack((K[..., 0, 0], K[..., 1, 1]), -1)
    xy = X_c[..., :2] / z_safe.unsqueeze(-1)
    pixel = f * xy + K[..., :2, 2]
    # ∂pixel/∂X_c = [f/z I | -f xy / z]
    d_pixel = torch.cat((torch.diag_embed(f / z_safe.unsqueeze(-1)), (-f * xy / z_safe.unsqueeze(-1)).unsqueeze(-1)), -1)
    H_point = d_pixel @ R_cw
    if not pose_jacobian:
        return Projection(pixel, z, None, H_point)
    # ∂(R(q)ᵀ w)/∂q = ∂(C(q*) w)/∂q* · diag(1, -1, -1, -1)
    d_rot = quat.rotate_jacobian(quat.conjugate(q), w) * _conjugation(q.dtype, q.device)
    H_pose = torch.cat((-H_point, d_pixel @ R_ci @ d_rot), -1)
    return Projection(pixel, z, H_pose, H_point)


@cached_constant
def _conjugation(dtype: torch.dtype, device: torch.device) -> Tensor:
    return torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=dtype, device=device)


class TrackPoints(NamedTuple):
    """Triangulated points ``(..., 3)`` of tracks and whether each fixes its point."""

    point: Tensor
    conditioning: Tensor  # (...,) (σ₃ - σ₄) / σ₁ of the linear system
    in_front: Tensor  # (...,) bool: the homogeneous solution is a finite point in front of the newest view


def triangulate_views(R_wc: Tensor, c_w: Tensor, xy: Tensor, mask: Tensor) -> TrackPoints:
    """The point seen at normalised image coordinates ``xy`` ``(..., V, 2)`` by cameras
    (camera→world ``R_wc`` ``(..., V, 3, 3)``, centres ``c_w`` ``(..., V, 3)``) where ``mask``
    ``(..., V)`` holds; the first view of each track is real (the origin of the system)."""
    origin = c_w[..., 0, :]
    P = camera_matrix(R_wc, c_w - origin.unsqueeze(-2))  # (..., V, 3, 4)
    rows = xy.unsqueeze(-1) * P[..., 2:3, :] - P[..., :2, :]  # (..., V, 2, 4)
    rows = rows * mask[..., None, None].to(rows.dtype)
    solution = solve_dlt(rows.flatten(-3, -2), P[..., 0, :, :])
    h = solution.point
    w = h[..., 3]
    tiny = torch.finfo(h.dtype).tiny ** 0.5
    in_front = w > tiny * torch.linalg.vector_norm(h[..., :3], dim=-1).clamp_min(1.0) * 1e3
    point = h[..., :3] / torch.where(in_front, w, torch.ones_like(w)).unsqueeze(-1) + origin
    return TrackPoints(point, solution.conditioning, in_front)


class TrackMeasurements(NamedTuple):
    """The projected measurement of ``M`` tracks of ``V`` views (rows ``2V`` per track)."""

    residual: Tensor  # (r, M, 2V) Π r / σ, whitened (noise I)
    H: Tensor  # (r, M, 2V, D) Π H_x / σ
    noise_logdet: Tensor  # (r, M) (2m - 3) log σ: ½ log det of the noise σ² Π + (I - Π) the rows are whitened by
    dof: Tensor  # (r, M) 2m - 3
    valid: Tensor  # (r, M) bool
    n_degenerate: Tensor  # (r,) tracks left out: no finite point in front, or conditioning too low
    n_behind: Tensor  # (r,) left out: the point behind or too close to a camera
    n_low_parallax: Tensor  # (r,) left out: rays meeting at less than min_parallax_rad
    point: Tensor  # (r, M, 3) the triangulated points


def track_measurements(x: Tensor, uv_px: Tensor, ages: Tensor, mask: Tensor, camera: FlowCamera,
                       update: TrackUpdate, *, track_mask: Tensor | None = None) -> TrackMeasurements:
    """The multi-view measurements of tracks at the states ``x`` ``(r, D)`` (see the module doc).

    Args:
        uv_px ``(r, M, V, 2)``: each track's pixel in each of its views, the newest first;
        ages ``(r, M, V)``: each view's age (0: the current pose, ``a``: clone ``a - 1``);
        mask ``(r, M, V)``: the real views (each real track has at least two, first);
        camera: shared, or with a leading dimension ``r``;
        track_mask ``(r, M)``: the real tracks (default: those with two views or more).
    """
    r, M, V = ages.shape
    D = x.shape[-1]
    if V - 1 > window_size(D):
        raise ValueError(f"track_measurements: views of age up to {V - 1} need a window of {V - 1} clones; the state "
                         f"({D} entries) has {window_size(D)}")
    like = dict(dtype=x.dtype, device=x.device)
    cam = camera.to(x)
    expand = (lambda t, event: t) if not cam.batch_shape else (lambda t, event: t.reshape(r, 1, 1, *t.shape[-event:]))
    K, R_ci, centre_b = expand(cam.K, 2), expand(cam.R_ci, 2), expand(cam.centre_b, 1)
    index = pose_index(D, x.device)[ages]  # (r, M, V, 7)
    pose = x.unsqueeze(1).unsqueeze(1).expand(r, M, V, D).gather(-1, index)
    p, q = pose[..., :3], pose[..., 3:]
    R_wb = quat.to_matrix(q)
    R_wc = R_wb @ R_ci.transpose(-1, -2)
    c_w = p + (R_wb @ centre_b.unsqueeze(-1)).squeeze(-1)
    views = mask.sum(-1)
    real = (views >= 2) if track_mask is None else track_mask & (views >= 2)
    maskf = mask.to(x.dtype)
    tri = triangulate_views(R_wc, c_w, normalise_pixels(uv_px, K), mask)
    X = tri.point
    eye3 = torch.eye(3, **like)
    for _ in range(update.refine_iterations):  # Gauss-Newton on the pixel residuals
        proj = project(X.unsqueeze(-2), p, q, K, R_ci, centre_b, pose_jacobian=False, R_wc=R_wc)
        Hf = proj.H_point * maskf[..., None, None]
        res = (uv_px - proj.pixel) * maskf.unsqueeze(-1)
        normal = torch.einsum("rmvia,rmvib->rmab", Hf, Hf) + 1e-12 * eye3
        # explicit 3 x 3 inverses: batched torch.linalg.solve is ten times slower on the CPU. A
        # track without baseline has a normal matrix of rank 2, singular at rounding level
        # whatever the 1e-12: where its factorisation fails the point stays where it is, and the
        # identity stands in for it so that no infinity reaches the gradient
        invertible = torch.linalg.inv_ex(normal.detach())[1] == 0
        inverse = torch.linalg.inv(torch.where(invertible[..., None, None], normal, eye3))
        step = (inverse @ torch.einsum("rmvia,rmvi->rma", Hf, res).unsqueeze(-1)).squeeze(-1)
        ok = tri.in_front & invertible & torch.isfinite(step).all(-1)
        X = torch.where(ok.unsqueeze(-1), X + torch.where(ok.unsqueeze(-1), step, 0.0), X)
    proj = project(X.unsqueeze(-2), p, q, K, R_ci, centre_b, R_wc=R_wc)
    # validity: a finite point in front of every view, not too close, with parallax
    degenerate = ~tri.in_front | ~(tri.conditioning > update.min_conditioning) | ~torch.isfinite(X).all(-1)
    behind = ((proj.depth <= update.min_depth_m) & mask).any(-1) & ~degenerate
    rays = X.unsqueeze(-2) - c_w
    angle = ray_angle(rays[..., :1, :], rays) * maskf  # each view's ray against the newest's
    low = ~(angle.amax(-1) >= update.min_parallax_rad) & ~degenerate & ~behind
    valid = real & ~degenerate & ~behind & ~low
    rowmask = (mask & valid.unsqueeze(-1)).to(x.dtype).repeat_interleave(2, -1)  # (r, M, 2V)
    sigma = scalar_like(update.sigma_px, x)
    white = rowmask / sigma  # the real rows of valid tracks, whitened (Π below is linear)
    residual = (uv_px - proj.pixel).flatten(-2) * white
    Hf = proj.H_point.reshape(r, M, 2 * V, 3) * rowmask.unsqueeze(-1)
    H_pose = proj.H_pose * white.view(r, M, V, 2, 1)  # masked before the scatter: no (r, M, 2V, D) product
    Hx = x.new_zeros(r, M, V, 2, D).scatter(-1, index.unsqueeze(-2).expand(r, M, V, 2, 7), H_pose).view(r, M, 2 * V, D)
    # Π x = x - H_f (H_fᵀ H_f)⁻¹ (H_fᵀ x), of rank 3 (no 2V x 2V matrix; the padded rows of r,
    # H_x and H_f are zero, so Π leaves them zero)
    normal = Hf.transpose(-1, -2) @ Hf + torch.where(valid, 0.0, 1.0)[..., None, None] * eye3
    Hf_N = Hf @ torch.linalg.inv(normal)
    Hf_t = Hf.transpose(-1, -2)
    dof = (2 * views - 3).clamp_min(1) * valid
    counts = [flag.sum(-1) for flag in (degenerate & real, behind & real, low & real)]
    Pi_r = residual - (Hf_N @ (Hf_t @ residual.unsqueeze(-1))).squeeze(-1)
    Pi_Hx = Hx - Hf_N @ (Hf_t @ Hx)
    return TrackMeasurements(Pi_r, Pi_Hx, dof * torch.log(sigma), dof, valid, *counts, X)


# ----------------------------------------------------------------------------- the schedule


class TrackViews(NamedTuple):
    """The tracks one frame updates with: ``uv_px`` ``(M, V, 2)``, ``ages`` ``(M, V)`` and
    ``mask`` ``(M, V)`` (the newest view first), and how many tracks were complete there
    (``candidates``, of which the ``M`` longest are kept)."""

    uv_px: Tensor
    ages: Tensor
    mask: Tensor
    candidates: int


def schedule_tracks(t_s: Tensor, track_id: Tensor, uv_px: Tensor, frame_times_s: Tensor, *, window: int,
                    max_tracks: int | None = None) -> list[TrackViews]:
    """Which tracks each frame updates with (see the module doc), from track rows
    ``(t_s, track_id, uv_px)`` (grouped by time) and the frames ``frame_times_s`` ``(F,)``
    (sorted; rows at other times are not used).

    A track's observations in consecutive frames form a segment; a segment is used at the
    frame where it ends (the track is not seen there: its views are the clones) or where it
    reaches ``window + 1`` views (its views the current pose and every clone), and at the
    last frame; a segment of one view is not used. A frame with more complete segments than
    ``max_tracks`` keeps the longest (the others are counted in ``candidates``).
    """
    if window < 1:
        raise ValueError(f"schedule_tracks: window must be >= 1, got {window}")
    V = window + 1
    frames = frame_times_s.numpy()
    F = len(frames)
    t_all, ids_all, uv_all = t_s.numpy(), track_id.numpy(), uv_px.numpy()
    # each row's frame (rows at other times are not used)
    k_row = np.searchsorted(frames, t_all).clip(0, max(F - 1, 0))
    used = frames[k_row] == t_all if F else np.zeros(len(t_all), bool)
    rows = np.flatnonzero(used)
    k, ids = k_row[rows], ids_all[rows]
    # segments: a track's rows in consecutive frames, cut every V views
    order = np.lexsort((k, ids))
    k, ids, rows = k[order], ids[order], rows[order]
    run_start = np.ones(len(k), bool)
    run_start[1:] = (ids[1:] != ids[:-1]) | (k[1:] != k[:-1] + 1)
    run_first = np.maximum.accumulate(np.where(run_start, np.arange(len(k)), 0))
    seg_start = run_start | ((np.arange(len(k)) - run_first) % V == 0)
    first = np.flatnonzero(seg_start)  # each segment's first row (in this order)
    length = np.diff(np.append(first, len(k)))
    k0, k1 = k[first], k[first + length - 1]
    # where each is used: where it reaches V views, else where it is not seen (the frame after
    # its last view), else (seen at the last frame) the last frame; and in which order there:
    # ended ones, then those reaching V (in their frame's row order), then the last frame's rest,
    # each group in the order the segments began (the loop's order, kept by a stable sort)
    reached = length == V
    at = np.where(reached, k1, np.minimum(k1 + 1, F - 1))
    group = np.where(reached, 1, np.where(k1 + 1 <= F - 1, 0, 2))
    # reaching V: the row of the last view (rows of one frame keep their order); the others: the
    # first view's frame, then its row
    began = np.where(reached, rows[first + length - 1], k0 * (len(t_all) + 1) + rows[first])
    keep = length >= 2
    sel = np.flatnonzero(keep)
    sel = sel[np.lexsort((began[sel], group[sel], -length[sel], at[sel]))]  # by frame, then longest first
    bounds = np.searchsorted(at[sel], np.arange(F + 1))
    out = []
    j = np.arange(V)
    for f in range(F):
        chosen = sel[bounds[f]:bounds[f + 1]]
        candidates = len(chosen)
        if max_tracks is not None:
            chosen = chosen[:max_tracks]
        n = length[chosen][:, None]
        mask = j[None, :] < n
        # view j (newest first) is the segment's row L - 1 - j
        index = np.where(mask, first[chosen][:, None] + n - 1 - j[None, :], 0)
        uv = np.where(mask[..., None], uv_all[rows[index]], 0.0).astype(np.float64)
        ages = np.where(mask, f - k[index], 0)
        out.append(TrackViews(torch.from_numpy(uv), torch.from_numpy(ages.astype(np.int64)), torch.from_numpy(mask),
                              candidates))
    return out


# ----------------------------------------------------------------------------- the event


@dataclass(frozen=True)
class TrackFrame(RowBatchEvent):
    """A camera frame of the multi-view track update: the complete tracks update the filter
    (:func:`track_measurements`), then the window of cloned poses shifts."""

    time_s: float
    views: TrackViews
    camera: FlowCamera
    update: TrackUpdate
    name: str = "tracks frame"

    def batch_key(self) -> tuple:
        return (TrackFrame, id(self.update))

    @classmethod
    def place(cls, frames: list[TrackFrame], like: Tensor) -> list[TrackFrame]:
        """The frames with their views on ``like``'s device (pixels in its dtype), each kind of
        tensor of all frames moved in one copy (each frame's a view of it)."""
        views = [frame.views for frame in frames]
        shapes = {tuple(v.uv_px.shape[1:]) for v in views}
        if len(shapes) != 1 or all(v.uv_px.dtype == like.dtype and v.uv_px.device == like.device for v in views):
            return list(frames)  # frames of unequal windows move one by one, as they update
        counts = [v.uv_px.shape[0] for v in views]
        uv, ages, mask = (torch.cat([getattr(v, name) for v in views]).to(**kind).split(counts)
                          for name, kind in (("uv_px", {"dtype": like.dtype, "device": like.device}),
                                             ("ages", {"device": like.device}), ("mask", {"device": like.device})))
        return [dataclasses.replace(frame, views=v._replace(uv_px=a, ages=b, mask=c))
                for frame, v, a, b, c in zip(frames, views, uv, ages, mask)]

    @classmethod
    def apply_batch(cls, chain: BatchChain, rows: list[int], frames: list[TrackFrame]) -> None:
        u = frames[0].update
        dim = chain.mean.shape[-1]
        if dim != state_dim(u.window):
            raise ValueError(f"{frames[0].name}: filter.tracks.window={u.window} needs a state of {state_dim(u.window)} "
                             f"entries, the filter's has {dim} (start it with flowins.filter.augmentation.with_window)")
        with_tracks = [i for i, frame in enumerate(frames) if frame.views.ages.shape[0]]
        if with_tracks:
            _track_update(chain, [rows[i] for i in with_tracks], [frames[i] for i in with_tracks])
        augment_pose_rows(chain, rows, mode="limit")


def _track_update(chain: BatchChain, rows: list[int], frames: list[TrackFrame]) -> None:
    u = frames[0].update
    mean, _ = chain.newest(rows)
    M = max(frame.views.ages.shape[0] for frame in frames)
    uv = torch.stack([_pad_rows(f.views.uv_px.to(mean), M) for f in frames])
    ages = torch.stack([_pad_rows(f.views.ages.to(mean.device), M) for f in frames])
    mask = torch.stack([_pad_rows(f.views.mask.to(mean.device), M) for f in frames])
    camera = stack_cameras([f.camera for f in frames]).to(mean)  # a copy kept by the camera
    m = track_measurements(mean, uv, ages, mask, camera, u)
    infos = [dict(kind="tracks", name=frame.name, candidates=frame.views.candidates,
                  tracks=int(frame.views.ages.shape[0])) for frame in frames]
    counts = dict(zip(("valid", "degenerate", "behind", "low_parallax"),
                      (m.valid.sum(-1), m.n_degenerate, m.n_behind, m.n_low_parallax)))
    update_rows(chain, rows, H=m.H, residual=m.residual, noise_cov=None, noise_logdet=m.noise_logdet, gate=u.gate,
                valid=m.valid, dof=m.dof, infos=infos, values=counts)
    if u.heading_transport:  # in place: a step of the chain per frame would double its nodes
        after, cov = chain.newest(rows)
        chain.update_rows(rows, after, transport_heading(cov, mean, after))


def _pad_rows(t: Tensor, M: int) -> Tensor:
    """``t`` ``(m, ...)`` padded with zeros (False) to ``(M, ...)``."""
    if t.shape[0] == M:
        return t
    return torch.cat((t, t.new_zeros(M - t.shape[0], *t.shape[1:])))


def track_frames(tracks, camera: FlowCamera, update: TrackUpdate, *, t_min_s: float, t_max_s: float,
                 name: str = "tracks") -> list[TrackFrame]:
    """One :class:`TrackFrame` per camera frame of ``tracks`` (a :class:`~flowins.data.sequence.Tracks`:
    its ``frame_times_s``, or the times of its rows) inside ``[t_min_s, t_max_s]``."""
    frame_times = tracks.frame_times_s if tracks.frame_times_s is not None else tracks.frame_times
    frame_times = frame_times[(frame_times >= t_min_s) & (frame_times <= t_max_s)]
    schedule = schedule_tracks(tracks.t_s, tracks.track_id, tracks.uv_px, frame_times, window=update.window,
                               max_tracks=update.max_tracks)
    return [TrackFrame(float(t), views, camera, update, f"{name} frame at {float(t):.3f} s")
            for t, views in zip(frame_times.tolist(), schedule)]
