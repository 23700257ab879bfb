"""Chest fiducials: metal skin staples found in the CT (paper section 2.2.1).

A staple (about 6.5 x 4.7 x 1.6 mm) is thinner than a voxel of many scans, so
partial volume can dim it below bone HU and split it across voxels; what is
conserved is its *excess density*: the sum over voxels of (HU - floor) times the
voxel volume, ~ staple volume x (metal HU - floor).  So:

1. the *skin shell*: voxels within ``skin_reach_mm`` of the air outside the body
   (low-HU components reaching the in-plane border), where only skin, fat and
   markers are, never bone;
2. excess ``E = HU - floor_hu`` where positive, inside the shell;
3. blobs: found on a ~2 mm grid of block maxima (connected components after a
   one-voxel dilation that joins fragments of one staple; staples are
   centimetres apart), then measured at full resolution in their box;
4. a blob whose excess mass lies within [min_mass, max_mass] is a staple if it
   is *on* the skin: its connected dense voxels stay in the shell (bone and
   contrast vessels that reach the shell, e.g. where the field of view cuts a
   lung, continue beneath it) and span at most ``MAX_EXTENT_MM``; its centre is
   the E-weighted centroid, mapped through ``T_patient_from_voxel``;
5. that centre is then refined against the skin beneath the staple
   (:func:`_centre_over_skin`): a staple thinner than a voxel shares its voxels
   with air on one side and skin on the other, and HU over a fixed floor weighs
   the skin side's voxels too little (on 1.95 x 2.5 mm voxels it put the centre
   0.5-0.7 mm off, outwards and towards the sternum).  The skin's surface around
   the staple is fitted (a quadratic height field through the -500 HU crossings
   of the voxel columns clear of it), the CT's profile across that surface gives
   each voxel's background without the staple, and the centre is the centroid
   of the HU above that background over the staple's dense voxels and those
   next to them across its thickness (along the voxel axis nearest the skin's
   normal): beside a staple lies what touches it (an ECG lead, a skin fold),
   which would count as metal above the air.

Order (docs/CONTRACTS.md): a grid of ``n_rows`` rows, superior to inferior;
within a row patient right to left (increasing LPS x).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from hrcore.errors import HeartregError
from hrcore.geometry import apply_to_points, check_transform
from modeling.coarse import block_mean_max, centroid, coarse_step
from modeling.distance import distance_mm

__all__ = ["FiducialError", "Fiducials", "find_fiducials", "order_fiducials"]

#: what a model without fiducials means (the model's warnings): 'heartreg register' refuses it
NO_FIDUCIALS = ("the model has no fiducials and cannot be registered ('heartreg register' starts from the CT's skin "
                "staples, touched in surgery)")

#: A given fiducial may lie this far outside the CT's voxels (a staple on the skin at the field of view's edge).
GIVEN_MARGIN_MM = 10.0
#: Excess density is counted above this HU (above any skin or soft tissue).
FLOOR_HU = 300.0
#: A staple lies on the skin: voxels this close to the air outside are searched.
SKIN_REACH_MM = 2.5
#: Excess mass (HU x mm^3) of one staple: ~25 mm^3 x ~2500 HU = 6e4; accept
#: from a sixth to ten times that (other metal markers, dimmer reconstructions).
MIN_MASS = 1.0e4
#: Grid (mm) on which the body's outline and the candidate blobs are found.
COARSE_MM = 2.0
MAX_MASS = 6.0e5
#: A marker's dense voxels span at most this (a staple is ~6.5 mm; blur and tilt add).
MAX_EXTENT_MM = 15.0
#: How far around a candidate its dense surroundings are looked at.
MARKER_CONTEXT_MM = 8.0
#: Soft tissue (skin) is above this HU.
BODY_HU = -300.0
#: A marker's dense voxels lie this close to the skin's soft tissue (or in the next voxel).
SKIN_CONTACT_MM = 1.6
#: Fraction of a candidate's connected dense voxels allowed outside the skin shell.
MAX_BENEATH_FRACTION = 0.3
#: :func:`_centre_over_skin`: the staple's own voxels are its dense ones and those within this reach (mm; at least
#: the next voxel), where its partial volume and blur lie; the skin's background is read this far around them.
STAPLE_REACH_MM = 1.0
SKIN_RING_MM = 4.0
#: ... the skin's surface is where the CT crosses this HU (half-way from air to skin), fitted through at least
#: this many voxel columns clear of the staple.
SKIN_SURFACE_HU = -500.0
MIN_SKIN_COLUMNS = 12


class FiducialError(HeartregError, ValueError):
    """The fiducials found do not match what was expected."""


@dataclass(frozen=True)
class Fiducials:
    """Fiducial centres in the patient frame.

    Attributes
    ----------
    centres_patient_mm : (n, 3) float64
        In the documented order.
    masses_hu_mm3 : (n,) float64
        Excess density of each marker (HU above the floor x mm^3).
    notes : tuple of str
        Blobs discarded and why.
    """

    centres_patient_mm: np.ndarray
    masses_hu_mm3: np.ndarray
    notes: tuple[str, ...] = ()


def order_fiducials(centres_mm, *, n_rows: int = 3) -> np.ndarray:
    """Indices that put fiducial centres in row-major order.

    Rows are ``n_rows`` groups by height (LPS z, superior first); within a row
    the staples go from patient right to left (increasing x).

    Parameters
    ----------
    centres_mm : (n, 3) float
        Centres in the patient frame; n must be a multiple of ``n_rows``.

    Returns
    -------
    (n,) int
    """
    centres = np.asarray(centres_mm, dtype=float)
    if centres.ndim != 2 or centres.shape[1] != 3:
        raise ValueError(f"centres_mm must have shape (n, 3), got {centres.shape}")
    n = len(centres)
    if n_rows < 1 or n % n_rows:
        raise FiducialError(f"{n} fiducials cannot form {n_rows} equal rows")
    per_row = n // n_rows
    by_height = np.argsort(-centres[:, 2], kind="stable")
    order = []
    for r in range(n_rows):
        row = by_height[r * per_row : (r + 1) * per_row]
        order.extend(row[np.argsort(centres[row, 0], kind="stable")])
    return np.asarray(order, dtype=int)


def _centre_over_skin(hu, dense_kji, spacing_kji, floor_hu) -> np.ndarray:
    """Sub-voxel centre (k, j, i) of a staple from its HU above the skin's own background (module docstring, 5.);
    NaNs when the skin around it cannot be fitted.

    ``dense_kji``: the staple's voxels above ``floor_hu`` (volume indices).
    """
    spacing = np.asarray(spacing_kji, float)
    reach = np.maximum(np.ceil(STAPLE_REACH_MM / spacing), 1).astype(int)
    grow = reach + np.ceil(SKIN_RING_MM / spacing).astype(int)
    lo = np.maximum(dense_kji.min(axis=0) - grow, 0)
    hi = np.minimum(dense_kji.max(axis=0) + grow + 1, hu.shape)
    sub = np.asarray(hu[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]], dtype=np.float64)
    core = np.zeros(sub.shape, bool)
    core[tuple((dense_kji - lo).T)] = True
    # the background is read round the staple's dense voxels and their neighbours within reach
    ring = ~ndimage.binary_dilation(core, structure=np.ones(tuple(2 * reach + 1), bool)) & (sub <= floor_hu)
    air = sub < SKIN_SURFACE_HU
    if not (air & ring).any() or not (~air & ring).any():
        return np.full(3, np.nan)
    # the voxel axis closest to the skin's normal, oriented body -> air
    where = np.indices(sub.shape).reshape(3, -1).T * spacing
    normal = where[(air & ring).ravel()].mean(axis=0) - where[(~air & ring).ravel()].mean(axis=0)
    a = int(np.argmax(np.abs(normal)))
    flip = normal[a] < 0
    # the staple's partial volume lies across its thickness, along the skin's normal: its voxels are the dense
    # ones and those within reach of them along that axis (beside it lies what touches it: a lead, a fold)
    across = np.ones(3, int)
    across[a] = 2 * reach[a] + 1
    staple = ndimage.binary_dilation(core, structure=np.ones(tuple(across), bool))

    def columns(x):  # the axis ``a`` last, running from the body to the air
        x = np.moveaxis(x, a, -1)
        return x[..., ::-1] if flip else x

    values, clear = columns(sub), ~columns(staple).any(axis=-1)
    above = values > SKIN_SURFACE_HU
    step = above[..., :-1] & ~above[..., 1:]  # body -> air between t and t + 1
    one = clear & (step.sum(axis=-1) == 1)
    if one.sum() < MIN_SKIN_COLUMNS:
        return np.full(3, np.nan)
    t = np.argmax(step, axis=-1)[one]
    prof = values[one]
    rows = np.arange(len(t))
    t = t + (prof[rows, t] - SKIN_SURFACE_HU) / (prof[rows, t] - prof[rows, t + 1])
    # the skin's height (voxels along a) as a quadratic in the other two axes (mm)
    others = [x for x in range(3) if x != a]
    uv = np.argwhere(one) * spacing[others]

    def design(p):
        return np.column_stack([np.ones(len(p)), p, p**2, p[:, 0] * p[:, 1]])

    coef = np.linalg.lstsq(design(uv), t, rcond=None)[0]
    grid_uv = np.indices(values.shape[:2]).reshape(2, -1).T * spacing[others]
    height = (design(grid_uv) @ coef).reshape(values.shape[:2])
    depth = (np.arange(values.shape[-1]) - height[..., None]) * spacing[a]  # mm past the skin, towards the air
    # the background at each of the staple's depths (to a twentieth of a voxel): the ring's median within a fifth
    # of a voxel of it
    ring_c, staple_c = columns(ring), columns(staple)
    d_ring, v_ring = depth[ring_c], values[ring_c]
    order = np.argsort(d_ring)
    d_ring, v_ring = d_ring[order], v_ring[order]
    at_depth, which = np.unique(np.round(depth[staple_c] / (0.05 * spacing[a])), return_inverse=True)
    at_depth = at_depth * 0.05 * spacing[a]
    left = np.searchsorted(d_ring, at_depth - 0.2 * spacing[a])
    right = np.searchsorted(d_ring, at_depth + 0.2 * spacing[a])
    if np.any(right - left < 3):  # a depth of the staple's the ring does not reach
        return np.full(3, np.nan)
    background = np.array([np.median(v_ring[p:q]) for p, q in zip(left, right)])[which.ravel()]
    excess = np.clip(values[staple_c] - background, 0.0, None)
    if excess.sum() <= 0:
        return np.full(3, np.nan)
    at = np.argwhere(staple_c).astype(float)
    if flip:
        at[:, -1] = values.shape[-1] - 1 - at[:, -1]
    centre_c = (at * excess[:, None]).sum(axis=0) / excess.sum()
    centre = np.empty(3)
    centre[others], centre[a] = centre_c[:2], centre_c[2]
    return centre + lo


def _not_on_skin(hu, box, blob, in_shell, floor_hu, spacing_kji, plane_axes=(1, 2)) -> tuple[str, float | None]:
    """Why a dense blob found in the skin shell is not a skin marker ('' if it is one), and its size (mm) when
    it is :data:`TOO_LARGE`.

    A staple is a small piece of metal wholly on the skin.  The dense voxels
    (> ``floor_hu``) connected to the blob, looked at ``MARKER_CONTEXT_MM``
    around it, must stay within the shell (bone and contrast-filled vessels
    that reach the shell, e.g. where the field of view cuts a lung, continue
    beneath it) and span at most ``MAX_EXTENT_MM``.  ``plane_axes``: the
    array axes across the patient's height (the field of view's edges).
    """
    pad = [int(np.ceil(MARKER_CONTEXT_MM / s)) for s in spacing_kji]
    big = tuple(slice(max(b.start - p, 0), min(b.stop + p, n)) for b, p, n in zip(box, pad, hu.shape))
    dense = np.asarray(hu[big]) > floor_hu
    inner = tuple(slice(b.start - g.start, b.stop - g.start) for b, g in zip(box, big))
    labels, _ = ndimage.label(dense, structure=np.ones((3, 3, 3), bool))
    touched = np.unique(labels[inner][blob])
    touched = touched[touched > 0]
    if touched.size == 0:
        return "", None
    part = np.isin(labels, touched)
    shell = np.zeros(part.shape, bool)
    shell[inner] = in_shell
    beneath = part & ~shell
    if beneath.sum() > part.sum() * MAX_BENEATH_FRACTION:
        return "dense tissue continues beneath the skin (bone or a contrast vessel)", None
    kji = np.argwhere(part)
    extent = float(np.max((kji.max(axis=0) - kji.min(axis=0) + 1) * spacing_kji))
    if extent > MAX_EXTENT_MM:
        return TOO_LARGE, extent
    lo, hi = kji.min(axis=0) + [g.start for g in big], kji.max(axis=0) + [g.start for g in big]
    if any(lo[a] == 0 or hi[a] == hu.shape[a] - 1 for a in plane_axes):
        return "cut by the edge of the field of view", None
    # the part's own box, grown past the contact distance: nothing outside it is near
    grow = np.ceil(SKIN_CONTACT_MM / np.asarray(spacing_kji, float)).astype(int) + 1
    around = tuple(slice(max(a - g, 0), min(b + 1 + g, n))
                   for a, b, g, n in zip(kji.min(axis=0), kji.max(axis=0), grow, part.shape))
    part = part[around]
    body = (np.asarray(hu[big])[around] > BODY_HU) & ~dense[around]
    near = (distance_mm(~part, spacing_kji) <= SKIN_CONTACT_MM) | ndimage.binary_dilation(
        part, structure=np.ones((3, 3, 3), bool)
    )  # the neighbouring voxels at least, however coarse the grid
    if not (near & body).any():
        return "not touching the body (it lies in the air)", None
    return "", None


#: The reason :func:`_not_on_skin` gives a blob larger than a marker (its size apart).
TOO_LARGE = "larger than a marker"


def _by_reason(rejected, sizes_mm) -> dict[str, int]:
    """The rejected blobs counted per reason, those larger than a marker (:data:`TOO_LARGE`) with the range of
    their sizes ``sizes_mm`` (one note, not one per size: the real CT made as a pulmonary CTA gave nine)."""
    out = {why: n for why, n in rejected.items() if why != TOO_LARGE}
    if rejected.get(TOO_LARGE):
        lo, hi = round(min(sizes_mm)), round(max(sizes_mm))
        out[f"{TOO_LARGE} ({lo}{'' if lo == hi else f'-{hi}'} mm > {MAX_EXTENT_MM:.0f} mm)"] = rejected[TOO_LARGE]
    return out


def find_fiducials(
    hu,
    T_patient_from_voxel,
    *,
    expected: int | None = 9,
    n_rows: int = 3,
    floor_hu: float = FLOOR_HU,
    skin_reach_mm: float = SKIN_REACH_MM,
    min_mass: float = MIN_MASS,
    max_mass: float = MAX_MASS,
    anterior_only: bool = True,
) -> Fiducials:
    """Find metal skin fiducials in a CT volume.

    Parameters
    ----------
    hu : (n_slices, n_rows, n_cols) array
        HU volume indexed ``[k, j, i]``.
    T_patient_from_voxel : (4, 4) float64
        Maps ``(i, j, k, 1)`` to patient LPS mm.
    expected : int or None
        Number of fiducials expected; a different count is an error naming both.
        ``None`` accepts any count.
    n_rows : int
        Rows of the grid, for the ordering.
    floor_hu : float
        Excess density is counted above this HU.
    skin_reach_mm : float
        Depth of the skin shell searched.
    min_mass, max_mass : float
        Excess mass (HU x mm^3) accepted as one marker.
    anterior_only : bool
        Keep markers on the front of the chest only (in front of the body's
        centre, LPS y below it), where the paper's grid is placed.

    Raises
    ------
    FiducialError
        If the count differs from ``expected``.

    Examples
    --------
    The nine staples on the sample study's chest, ordered in rows:

    >>> from imaging import load_study
    >>> from modeling import find_fiducials
    >>> volume = load_study("sample_dicom/ct")
    >>> find_fiducials(volume.hu, volume.T_patient_from_voxel).centres_patient_mm.shape
    (9, 3)
    """
    hu = np.asarray(hu)
    if hu.ndim != 3:
        raise ValueError(f"hu must be a 3-D volume (k, j, i), got shape {hu.shape}")
    T = check_transform(T_patient_from_voxel, name="T_patient_from_voxel")
    voxel_mm3 = abs(np.linalg.det(T[:3, :3]))
    spacing_kji = np.linalg.norm(T[:3, :3], axis=0)[::-1]

    # coarse grid (~2 mm): block maxima keep every marker, block means find the air
    step = coarse_step(spacing_kji, COARSE_MM)
    cmean, cmax = block_mean_max(hu, step)
    cspacing = spacing_kji * step

    # the air outside the body: low-HU components that reach the border across the patient's height
    # (not the ends along it, where trachea and lungs leave the volume), whichever array axes those are
    height = 2 - int(np.argmax(np.abs(T[2, :3]) / spacing_kji[::-1]))
    plane_axes = tuple(a for a in range(3) if a != height)
    air_labels, _ = ndimage.label(cmean < -500)
    border = np.unique(np.concatenate([np.take(air_labels, [0, -1], axis=a).ravel() for a in plane_axes]))
    outside = np.isin(air_labels, border[border > 0])
    del air_labels
    if not outside.any():
        raise FiducialError(
            "no air around the body in the volume (the field of view cuts the skin?); "
            "skin fiducials cannot be told from bone: pass --fiducials 0 and give them otherwise"
        )
    body_kji = centroid(~outside) * step  # full-resolution voxel indices
    body_centre_y = apply_to_points(T, body_kji[::-1])[1]
    reach = skin_reach_mm + 0.5 * float(np.max(cspacing))
    shell = distance_mm(~outside, cspacing) <= reach
    candidates = shell & (cmax > floor_hu)
    labels, _ = ndimage.label(ndimage.binary_dilation(candidates), structure=np.ones((3, 3, 3), bool))

    notes = []
    rejected: Counter = Counter()
    sizes_mm: list[float] = []  # of the blobs larger than a marker
    centres, masses = [], []
    for cbox in ndimage.find_objects(labels):
        # the blob's box at full resolution, one coarse voxel wider
        box = tuple(
            slice(max((c.start - 1) * st, 0), min((c.stop + 1) * st, n))
            for c, st, n in zip(cbox, step, hu.shape)
        )
        sub = hu[box].astype(np.float32)
        # keep the skin side only: voxels whose coarse cell is in the shell
        idx = [np.arange(b.start, b.stop) // st for b, st in zip(box, step)]
        in_shell = shell[np.ix_(*idx)]
        weight = np.where(in_shell, np.clip(sub - floor_hu, 0.0, None), 0.0)
        mass = float(weight.sum()) * voxel_mm3
        if not (min_mass <= mass <= max_mass):
            if mass > 0.1 * min_mass:
                rejected[f"excess mass outside {min_mass:.3g}-{max_mass:.3g} HU.mm3"] += 1
            continue
        why, size_mm = _not_on_skin(hu, box, weight > 0, in_shell, floor_hu, spacing_kji, plane_axes)
        if why:
            rejected[why] += 1
            sizes_mm += [] if size_mm is None else [size_mm]
            continue
        kji = np.argwhere(weight > 0)
        w = weight[weight > 0]
        offset = np.array([b.start for b in box])
        kji = kji + offset
        k, j, i = _centre_over_skin(hu, kji, spacing_kji, floor_hu)
        if not np.isfinite(k):  # the skin around it could not be fitted: the dense voxels' centroid
            k, j, i = (kji * w[:, None]).sum(axis=0) / w.sum()
        centre = apply_to_points(T, [i, j, k])
        if anterior_only and centre[1] > body_centre_y:
            notes.append(f"metal on the back skin at {np.round(centre, 1).tolist()} mm ignored (anterior_only)")
            continue
        centres.append(centre)
        masses.append(mass)

    notes.extend(f"{n} dense blob(s) near the skin ignored: {why}" for why, n in sorted(_by_reason(rejected, sizes_mm).items()))
    centres = np.asarray(centres, dtype=float).reshape(-1, 3)
    masses = np.asarray(masses, dtype=float)
    if expected is not None and len(centres) != expected:
        raise FiducialError(
            f"found {len(centres)} metal marker(s) on the skin, expected {expected}; check the scan "
            "covers all skin markers, or set the expected count (--fiducials N)"
        )
    if len(centres) == 0:
        return Fiducials(centres, masses, tuple(notes))
    rows = n_rows if len(centres) % n_rows == 0 else 1
    order = order_fiducials(centres, n_rows=rows)
    return Fiducials(centres[order], masses[order], tuple(notes))


def check_given_fiducials(points_mm, shape, T_patient_from_voxel) -> np.ndarray:
    """Given fiducials (patient LPS mm) as an (n, 3) array, refused when one lies outside the CT.

    Skin markers lie in the CT (up to :data:`GIVEN_MARGIN_MM` beyond its outermost voxel centres, a staple at
    the field of view's edge): a point far outside it is in another frame (a tracker's, RAS read as LPS).
    ``shape`` is the CT's ``(k, j, i)``.
    """
    points = np.asarray(points_mm, dtype=np.float64).reshape(-1, 3)
    T = np.asarray(T_patient_from_voxel, dtype=np.float64)
    ijk = np.c_[points, np.ones(len(points))] @ np.linalg.inv(T).T
    margin = GIVEN_MARGIN_MM / np.linalg.norm(T[:3, :3], axis=0)
    extent = np.asarray(shape[::-1], float) - 1.0  # i, j, k
    outside = np.any((ijk[:, :3] < -margin) | (ijk[:, :3] > extent + margin), axis=1)
    if outside.any():
        k = int(np.argmax(outside))
        raise FiducialError(
            f"given fiducial {k + 1} ({', '.join(f'{x:.6g}' for x in points[k])} mm) lies outside the CT "
            f"({int(outside.sum())} of {len(points)} such): give the points in this CT's patient coordinates "
            "(a Slicer markups file says LPS or RAS; points placed on this CT in Slicer are)")
    return points


def fiducial_stage(hu, T_patient_from_voxel, options, fallback) -> Fiducials:
    """The model's fiducials as ``options`` (:class:`modeling.options.ModelOptions`) ask.

    Given points (``fiducials_mm``) are taken as they are; ``expected_fiducials``
    None looks for none; otherwise :func:`find_fiducials` searches the skin,
    insisting on a count (an error) or, ``"auto"``, taking what it finds: a
    search that cannot do its job then leaves the model without fiducials and
    says why through ``fallback(message)`` (a warning written into model.json).
    """
    from modeling.options import AUTO

    none = Fiducials(np.zeros((0, 3)), np.zeros(0))
    expected, rows = options.expected_fiducials, options.fiducial_rows
    if options.fiducials_mm is not None:  # checked against the CT by the build's start (check_given_fiducials)
        points = np.asarray(options.fiducials_mm, dtype=np.float64)
        return Fiducials(points, np.full(len(points), np.nan),
                         (f"fiducials: {len(points)} given (patient LPS), not searched",))
    if expected is None:
        return none
    auto = expected == AUTO
    kwargs = {} if options.fiducial_floor_hu is None else {"floor_hu": options.fiducial_floor_hu}
    try:
        found = find_fiducials(hu, T_patient_from_voxel, expected=None if auto else int(expected), n_rows=rows,
                               **kwargs)
    except FiducialError as exc:
        if not auto:
            raise
        fallback(f"fiducial search skipped: {exc}; {NO_FIDUCIALS}")
        return none
    n_found = len(found.centres_patient_mm)
    if auto and n_found == 0:
        fallback(f"no skin markers found: {NO_FIDUCIALS}; make it from a CT that shows the staples, or give "
                 "their positions (--fiducials FILE.mrk.json)")
    elif auto and n_found % rows:
        fallback(f"{n_found} skin marker(s) found, which cannot form {rows} equal rows: {NO_FIDUCIALS}; "
                 "give --fiducials N (the staples' count) to insist on it, or their positions (--fiducials "
                 "FILE.mrk.json)")
        return Fiducials(none.centres_patient_mm, none.masses_hu_mm3, found.notes)
    return found
