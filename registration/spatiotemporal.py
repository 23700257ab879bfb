"""Spatiotemporal registration: sweep a phase, ICP at each, pick the empirical phase.

Paper sections 2.3.1 and 2.3.2 (Wood et al. 2018).  With the map's cardiac phase
phi_C* known from gating, the motion models predict every point at (phi_C*, phi_R)
for phi_R = 0, 0.01, ..., 1; ICP seeded by the fiducial registration ``T0``
registers each predicted point set to the surface.  The error alone has no
reliable minimum over phase (paper Fig. 2), so the respiration phase is chosen by
the empirical metric (paper eq. 10): the phase whose registration lies closest,
in translation, to ``T0``.

Translation and rotation distance from T0
-----------------------------------------
Both registrations map the source (probe) frame to the map frame.  Their
difference, expressed in the map frame, is the correction
``dT = T @ inv(T0)``.  The *translation distance* is the displacement that this
correction gives a pivot point ``c`` of the map::

    d_t = |dT c - c| = |T s - T0 s|,   s = inv(T0) c

With ``c`` at the origin of a heart-centric map frame this is ``|t(dT)|``, the
norm of the correction's translation vector, as in the paper (Fig. 7A); by
default ``c`` is the area-weighted centroid of the map's surface (the heart
centre), which makes the distance independent of where the map frame's origin
happens to be.  The *rotation distance* is the geodesic angle of ``dT``, i.e.
between the rotations of ``T`` and ``T0`` (degrees).

Static comparison (2.3.2): ``T_bar`` registers the points' mean positions (ICP
seeded by ``T0``); each point, mapped by the spatiotemporal and by the static
registration, is projected to its closest surface point; ``delta_i`` is the
distance between the two projections.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np

from hrcore.geometry import apply_to_points, check_transform
from registration.icp import IcpMethod, SurfaceIndex, icp_sweep_distances, closest_points, icp
from registration.motion_model import MotionModel, predict_positions
from registration.transforms import (
    euler_xyz_deg_from_matrix,
    invert,
    rotation_distance_deg,
)

__all__ = [
    "PhaseSweep",
    "SpatiotemporalRegistration",
    "StaticComparison",
    "surface_centroid",
    "sweep_phase",
    "register_spatiotemporal",
    "compare_static",
]

#: Sweeps seed every phase by T0, as the paper does; ``icp_options={"warm_start":
#: True}`` seeds each phase by its registered neighbour
#: (:func:`registration.icp.icp_sweep_distances`).  Not the default: from T0 a
#: phase takes about 4 steps, from its neighbour 2 to 3, and where the points lie
#: off the surface (phases far from the map's) the faceted loss is flat enough
#: along the heart's weakest direction that the seed moves the answer: on the
#: bench sweep (101 phases x 100 points, 20 000 faces) by at most 0.009 mm at
#: the mesh's centre but up to 0.13 deg in rotation (~0.1 mm at the points);
#: iterated to 1e-5 mm / 1e-5 deg (tol_loss 1e-9) both seeds still end 0.007 mm
#: / 0.09 deg apart: different local minima of the faceted loss, not a stopping
#: effect.  Nor is it faster there: the waves are many small batches.
WARM_START = False
#: The paper's sweep: 0 to 1 in steps of 0.01 (101 phases; 0 and 1 coincide).
DEFAULT_PHASES = np.linspace(0.0, 1.0, 101)


@dataclass(frozen=True)
class PhaseSweep:
    """Registrations across one phase with the other held fixed.

    Attributes
    ----------
    kind : str
        ``"respiration"`` (phi_R varies, phi_C fixed) or ``"cardiac"``.
    phases : (m,) float64
        The swept phases.
    fixed_phase : float
        The phase held constant.
    rms_mm : (m,) float64
        RMS point-to-surface distance after ICP at each phase.
    T_heart_from_probe : (m, 4, 4) float64
        ICP result at each phase.
    translation_distance_mm : (m,) float64
        ``|T s - T0 s|`` with ``s = inv(T0) pivot`` (module docstring).
    rotation_distance_deg : (m,) float64
        Geodesic angle between the rotations of ``T`` and ``T0``.
    correction_translation_mm : (m, 3) float64
        ``dT pivot - pivot``, map frame (the paper's Fig. 6A components).
    correction_euler_xyz_deg : (m, 3) float64
        Intrinsic X-Y-Z Euler angles of ``dT = T inv(T0)`` (Fig. 6B).
    euler_xyz_deg : (m, 3) float64
        Intrinsic X-Y-Z Euler angles of ``T`` itself.
    iterations : (m,) int64
    converged : (m,) bool
    pivot_mm : (3,) float64
        The map-frame pivot of the translation distance.
    distances_mm : (m, n) float64
        Point-to-surface distance of every point after ICP at each phase (the
        per-point evidence of :mod:`registration.temporal`).
    signed_distances_mm : (m, n) float64
        The same, negative inside the surface.
    """

    kind: str
    phases: np.ndarray
    fixed_phase: float
    rms_mm: np.ndarray
    T_heart_from_probe: np.ndarray
    translation_distance_mm: np.ndarray
    rotation_distance_deg: np.ndarray
    correction_translation_mm: np.ndarray
    correction_euler_xyz_deg: np.ndarray
    euler_xyz_deg: np.ndarray
    iterations: np.ndarray
    converged: np.ndarray
    pivot_mm: np.ndarray
    distances_mm: np.ndarray | None = None
    signed_distances_mm: np.ndarray | None = None

    @property
    def best_index(self) -> int:
        """Index of the smallest translation distance (paper eq. 10)."""
        return int(np.argmin(self.translation_distance_mm))

    @property
    def best_phase(self) -> float:
        """The swept phase with the smallest translation distance from T0."""
        return float(self.phases[self.best_index])


@dataclass(frozen=True)
class SpatiotemporalRegistration:
    """The empirical spatiotemporal registration.

    Attributes
    ----------
    cardiac_phase : float
        The map's cardiac phase phi_C* (given).
    respiration_phase : float
        The estimated respiration phase phi_R* (argmin translation distance).
    T_heart_from_probe : (4, 4) float64
        ICP registration at (phi_C*, phi_R*).
    T0_heart_from_probe : (4, 4) float64
        The fiducial seed.
    rms_mm, translation_distance_mm, rotation_distance_deg : float
        At phi_R*.
    points_probe_mm : (n, 3) float64
        Predicted points at (phi_C*, phi_R*), source frame.
    respiration_sweep : PhaseSweep
    cardiac_sweep : PhaseSweep or None
        Sweep over phi_C at phi_R* (paper Fig. 2A) when asked.
    """

    cardiac_phase: float
    respiration_phase: float
    T_heart_from_probe: np.ndarray
    T0_heart_from_probe: np.ndarray
    rms_mm: float
    translation_distance_mm: float
    rotation_distance_deg: float
    points_probe_mm: np.ndarray
    respiration_sweep: PhaseSweep
    cardiac_sweep: PhaseSweep | None = None


@dataclass(frozen=True)
class StaticComparison:
    """Spatiotemporal vs mean-position registration (paper 2.3.2).

    Attributes
    ----------
    T_static_heart_from_probe : (4, 4) float64
        ``T_bar``: ICP of the mean positions, seeded by T0.
    rms_static_mm : float
        RMS point-to-surface distance of the mean positions under ``T_bar``.
    projected_static_mm : (n, 3) float64
        ``S(u_bar_i)``: closest surface points of ``T_bar p_bar_i``, map frame.
    projected_spatiotemporal_mm : (n, 3) float64
        ``S(u*_i)``: closest surface points of ``T* p_i(phi*)``, map frame.
    delta_mm : (n,) float64
        ``|S(u*_i) - S(u_bar_i)|``, a Euclidean (chord) distance: it
        underestimates the geodesic distance on the surface slightly.
    mean_delta_mm : float
    """

    T_static_heart_from_probe: np.ndarray
    rms_static_mm: float
    projected_static_mm: np.ndarray
    projected_spatiotemporal_mm: np.ndarray
    delta_mm: np.ndarray
    mean_delta_mm: float


def _as_surface(surface) -> SurfaceIndex:
    if isinstance(surface, SurfaceIndex):
        return surface
    if isinstance(surface, tuple) and len(surface) == 2:
        return SurfaceIndex(*surface)
    raise ValueError("surface must be a SurfaceIndex or a (vertices, faces) tuple")


def surface_centroid(surface) -> np.ndarray:
    """Area-weighted centroid of a triangle surface, (3,) mm (the default pivot)."""
    surface = _as_surface(surface)
    tri = surface.vertices[surface.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    return (area @ tri.mean(axis=1)) / area.sum()


def _points_at(models, phase_c, phase_r) -> np.ndarray:
    """(m, n, 3) predicted points for m phase pairs."""
    phase_c, phase_r = np.broadcast_arrays(np.atleast_1d(phase_c), np.atleast_1d(phase_r))
    if isinstance(models, np.ndarray):
        raise ValueError("pass predicted points through sweep_phase(points=...), not models")
    models = list(models)
    if not models or not all(isinstance(m, MotionModel) for m in models):
        raise ValueError("models must be a non-empty sequence of MotionModel")
    return predict_positions(models, phase_c, phase_r)


def sweep_phase(
    models: Sequence[MotionModel] | None,
    surface,
    T0_heart_from_probe,
    *,
    fixed_phase: float,
    kind: str = "respiration",
    phases=None,
    points=None,
    pivot_mm=None,
    icp_options: Mapping | None = None,
) -> PhaseSweep:
    """ICP of the predicted points at each phase of a sweep, seeded by ``T0``.

    Parameters
    ----------
    models : sequence of MotionModel, or None
        Motion models of the n points (source frame); None when ``points`` are given.
    surface : SurfaceIndex or (vertices, faces)
        The map surface (map frame, mm).
    T0_heart_from_probe : (4, 4) float
        Fiducial registration (heart <- probe), the seed of every ICP.
    fixed_phase : float, cycles
        phi_C for a respiration sweep, phi_R for a cardiac sweep.
    kind : {"respiration", "cardiac"}
    phases : (m,) float, optional
        Swept phases; 0, 0.01, ..., 1 by default.
    points : (m, n, 3) float, mm, optional
        Predicted points at each swept phase, instead of ``models``.
    pivot_mm : (3,) float, optional
        Map-frame pivot of the translation distance; the surface centroid by default.
    icp_options : mapping, optional
        Keyword arguments of :func:`registration.icp.icp` (method, tolerances,
        ``max_iterations`` ...) and ``warm_start`` / ``warm_stride`` of
        :func:`registration.icp.icp_sweep_distances` (default: :data:`WARM_START`).

    Returns
    -------
    PhaseSweep
    """
    if kind not in ("respiration", "cardiac"):
        raise ValueError(f"kind must be 'respiration' or 'cardiac', got {kind!r}")
    surface = _as_surface(surface)
    T0 = check_transform(T0_heart_from_probe, name="T0_heart_from_probe")
    phases = DEFAULT_PHASES if phases is None else np.asarray(phases, dtype=float)
    if phases.ndim != 1 or phases.size == 0:
        raise ValueError(f"phases must have shape (m,), got {phases.shape}")
    if points is None:
        if models is None:
            raise ValueError("give models or points")
        if kind == "respiration":
            points = _points_at(models, fixed_phase, phases)
        else:
            points = _points_at(models, phases, fixed_phase)
    else:
        points = np.asarray(points, dtype=float)
        if points.ndim != 3 or points.shape[0] != phases.size or points.shape[2] != 3:
            raise ValueError(f"points must have shape ({phases.size}, n, 3), got {points.shape}")
    pivot = surface_centroid(surface) if pivot_mm is None else np.asarray(pivot_mm, dtype=float)
    if pivot.shape != (3,):
        raise ValueError(f"pivot_mm must have shape (3,), got {pivot.shape}")
    options = dict(icp_options or {})
    options.pop("T_init", None)

    # all phases in one batch: one closest-point query per iteration (the same ICP as ``icp``)
    options.pop("degeneracy_ratio", None)
    options.setdefault("warm_start", WARM_START)
    Ts, signed, iterations, converged = icp_sweep_distances(points, surface, T_init=T0, signed=True, **options)
    distances = np.abs(signed)
    rms = np.sqrt(np.mean(distances**2, axis=1))
    dT = Ts @ invert(T0)
    shift = dT[:, :3, :3] @ pivot + dT[:, :3, 3] - pivot
    return PhaseSweep(
        kind=kind, phases=phases.copy(), fixed_phase=float(fixed_phase), rms_mm=rms, T_heart_from_probe=Ts,
        translation_distance_mm=np.linalg.norm(shift, axis=1), rotation_distance_deg=rotation_distance_deg(Ts, T0),
        correction_translation_mm=shift, correction_euler_xyz_deg=euler_xyz_deg_from_matrix(dT),
        euler_xyz_deg=euler_xyz_deg_from_matrix(Ts), iterations=iterations, converged=converged, pivot_mm=pivot,
        distances_mm=distances, signed_distances_mm=signed,
    )


def register_spatiotemporal(
    models: Sequence[MotionModel],
    surface,
    T0_heart_from_probe,
    cardiac_phase: float,
    *,
    phases_r=None,
    pivot_mm=None,
    cardiac_sweep: bool = False,
    phases_c=None,
    icp_options: Mapping | None = None,
) -> SpatiotemporalRegistration:
    """Empirical spatiotemporal registration (paper 2.3.1, eq. 10).

    Parameters
    ----------
    models : sequence of MotionModel
        One per attachment point, source (probe) frame.
    surface : SurfaceIndex or (vertices, faces)
        Map surface, map frame.
    T0_heart_from_probe : (4, 4) float
        Fiducial registration (heart <- probe).
    cardiac_phase : float, cycles
        The map's cardiac phase phi_C*.
    phases_r : (m,) float, optional
        Respiration phases to sweep (0..1 step 0.01 by default).
    pivot_mm : (3,) float, optional
        See :func:`sweep_phase`.
    cardiac_sweep : bool
        Also sweep phi_C at the chosen phi_R* (paper Fig. 2A).
    phases_c : (m,) float, optional
        Cardiac phases of that sweep.
    icp_options : mapping, optional
        Keyword arguments of :func:`registration.icp.icp`.

    Returns
    -------
    SpatiotemporalRegistration

    Examples
    --------
    Nine points on an ellipsoidal "heart" (semi-axes 40, 30 and 50 mm) that
    breathe up to 12 mm along z and lie on the surface at phi_R = 0.3; the
    probe frame is the heart frame, so the fiducial seed is the identity.  Of
    the swept phases, 0.3 is the one whose registration stays closest to it.

    >>> import numpy as np
    >>> import trimesh
    >>> from registration import Harmonics, fit_motion_model, register_spatiotemporal
    >>> sphere = trimesh.creation.icosphere(subdivisions=3)
    >>> vertices_mm = np.asarray(sphere.vertices) * [40.0, 30.0, 50.0]
    >>> faces = np.asarray(sphere.faces)
    >>> t_s = np.arange(0.0, 30.0, 0.02)
    >>> phase_c, phase_r = (1.2 * t_s) % 1.0, (0.25 * t_s) % 1.0
    >>> models = []
    >>> for point_mm in vertices_mm[::80]:
    ...     T = np.tile(np.eye(4), (t_s.size, 1, 1))
    ...     T[:, :3, 3] = point_mm
    ...     T[:, 2, 3] += 6.0 * (np.cos(2 * np.pi * (phase_r - 0.3)) - 1.0)
    ...     models.append(fit_motion_model(phase_c, phase_r, T, harmonics=Harmonics(1, 1, 0, 0)))
    >>> len(models)
    9
    >>> reg = register_spatiotemporal(models, (vertices_mm, faces), np.eye(4), cardiac_phase=0.5,
    ...                               phases_r=np.arange(10) / 10)
    >>> print(f"phi_R* = {reg.respiration_phase:.2f}, {reg.translation_distance_mm:.3f} mm from T0, "
    ...       f"RMS {reg.rms_mm:.3f} mm")
    phi_R* = 0.30, 0.000 mm from T0, RMS 0.000 mm
    """
    surface = _as_surface(surface)
    T0 = check_transform(T0_heart_from_probe, name="T0_heart_from_probe")
    phase_c = cardiac_phase
    if not 0.0 <= phase_c <= 1.0:
        raise ValueError(f"cardiac_phase must be a phase in [0, 1], got {phase_c}")
    pivot = surface_centroid(surface) if pivot_mm is None else pivot_mm
    resp = sweep_phase(
        models,
        surface,
        T0,
        fixed_phase=phase_c,
        kind="respiration",
        phases=phases_r,
        pivot_mm=pivot,
        icp_options=icp_options,
    )
    best = resp.best_index
    phase_r = float(resp.phases[best])
    card = None
    if cardiac_sweep:
        card = sweep_phase(
            models,
            surface,
            T0,
            fixed_phase=phase_r,
            kind="cardiac",
            phases=phases_c,
            pivot_mm=pivot,
            icp_options=icp_options,
        )
    return SpatiotemporalRegistration(
        cardiac_phase=float(phase_c),
        respiration_phase=phase_r,
        T_heart_from_probe=resp.T_heart_from_probe[best].copy(),
        T0_heart_from_probe=T0.copy(),
        rms_mm=float(resp.rms_mm[best]),
        translation_distance_mm=float(resp.translation_distance_mm[best]),
        rotation_distance_deg=float(resp.rotation_distance_deg[best]),
        points_probe_mm=_points_at(models, phase_c, phase_r)[0],
        respiration_sweep=resp,
        cardiac_sweep=card,
    )


def compare_static(
    mean_points,
    surface,
    T0_heart_from_probe,
    T_spatiotemporal,
    points_spatiotemporal,
    *,
    icp_options: Mapping | None = None,
) -> StaticComparison:
    """Compare the spatiotemporal registration with the mean-position one (paper 2.3.2).

    Parameters
    ----------
    mean_points : (n, 3) float, mm, or sequence of MotionModel
        Mean position of each point, source frame (models give their
        ``mean_position_mm``).
    surface : SurfaceIndex or (vertices, faces)
    T0_heart_from_probe : (4, 4) float
        Seed of the static ICP.
    T_spatiotemporal : (4, 4) float
        The spatiotemporal registration ``T_heart_from_probe``.
    points_spatiotemporal : (n, 3) float, mm
        Predicted points at (phi_C*, phi_R*), source frame, same order.
    icp_options : mapping, optional

    Returns
    -------
    StaticComparison
    """
    surface = _as_surface(surface)
    T0 = check_transform(T0_heart_from_probe, name="T0_heart_from_probe")
    T_st = check_transform(T_spatiotemporal, name="T_spatiotemporal")
    if not isinstance(mean_points, np.ndarray) and all(
        isinstance(m, MotionModel) for m in mean_points
    ):
        mean_points = np.stack([m.mean_position_mm for m in mean_points])
    mean_points = np.asarray(mean_points, dtype=float)
    p_st = np.asarray(points_spatiotemporal, dtype=float)
    if mean_points.ndim != 2 or mean_points.shape[1] != 3:
        raise ValueError(f"mean_points must have shape (n, 3), got {mean_points.shape}")
    if p_st.shape != mean_points.shape:
        raise ValueError(
            f"points_spatiotemporal must have shape {mean_points.shape}, got {p_st.shape}"
        )
    options = dict(icp_options or {})
    options.pop("T_init", None)
    static = icp(mean_points, surface, T_init=T0, **options)
    T_bar = static.T_heart_from_probe
    proj_static = closest_points(surface, apply_to_points(T_bar, mean_points)).points
    proj_st = closest_points(surface, apply_to_points(T_st, p_st)).points
    delta = np.linalg.norm(proj_st - proj_static, axis=1)
    return StaticComparison(
        T_static_heart_from_probe=T_bar,
        rms_static_mm=static.rms_mm,
        projected_static_mm=proj_static,
        projected_spatiotemporal_mm=proj_st,
        delta_mm=delta,
        mean_delta_mm=float(delta.mean()),
    )
