"""The options of a heart model, written once: the library, the pipeline and the
command all take a :class:`ModelOptions` (the command's flags fill one).

Examples
--------
>>> from modeling.options import ModelOptions
>>> opts = ModelOptions(target_faces=5000)
>>> opts.target_faces, opts.expected_fiducials
(5000, 'auto')
>>> ModelOptions.of(opts, trim_vessels=False).trim_vessels
False
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType

from hrcore.errors import UsageError
from hrcore.options import OptionsRecord

__all__ = ["AUTO", "MIN_HEART_ML", "MODEL_MEMORY_FACTOR", "ModelOptions"]

#: ``expected_fiducials`` value: take the markers found on the skin, however many (none: a warning).
AUTO = "auto"
#: an adult heart (epicardial surface) holds some 300-1000 ml; a mask below this is not one.
MIN_HEART_ML = 100.0
#: a heart model's peak memory, in multiples of the CT's bytes as int16 (the project's bound; measured 1.7-2.9x
#: from 512 x 512 x 40 to 1024 x 1024 x 300 and 512 x 512 x 900): a CT needing more than there is is refused first
MODEL_MEMORY_FACTOR = 3.0


@dataclass(frozen=True)
class ModelOptions(OptionsRecord):
    """How a heart model is built (:func:`modeling.build_heart_model`).

    Attributes
    ----------
    target_faces : int
        Faces of the decimated mesh (``--faces``).
    expected_fiducials : int, "auto" or None
        Skin fiducials expected, a different count being an error
        (``--fiducials N``); ``"auto"``: the markers found on the skin, however
        many (none: a warning); None (``--fiducials 0``): none looked for.
    fiducial_rows : int
        Rows of the fiducial grid (for their order).
    fiducial_floor_hu : float, optional
        HU above which fiducial excess density counts (``--fiducial-floor-hu``;
        default :data:`modeling.fiducials.FLOOR_HU`).
    segmentation : mapping, optional
        Keyword arguments of :func:`modeling.segment.segment_heart`.
    trim_vessels : bool, optional
        Remove the great-vessel stubs over the vessels' mouths and close the
        surface (``--trim-vessels`` / ``--keep-vessels``); default: for the
        automatic segmentation of a CT with arterial contrast only (an external
        mask is trusted as given; without contrast, or with the dim blood of a
        venous phase, the trim cannot tell a vessel's lumen, and is skipped
        with a warning).
    min_heart_ml : float, ml
        A mask smaller than this is refused: it is not a heart.
    fiducials_mm : sequence of (x, y, z), mm, optional
        The CT's fiducials given (patient LPS), used as they are instead of
        the skin search (``--fiducials FILE.mrk.json``: points picked or
        corrected in 3D Slicer, e.g. the model's own ``fiducials_ct.mrk.json``);
        at least 3, any order (registration finds the correspondence).
    """

    target_faces: int = 20000
    expected_fiducials: int | str | None = AUTO
    fiducial_rows: int = 3
    fiducial_floor_hu: float | None = None
    segmentation: MappingProxyType | None = None
    trim_vessels: bool | None = None
    min_heart_ml: float = MIN_HEART_ML
    fiducials_mm: tuple | None = None

    def __post_init__(self):
        if isinstance(self.target_faces, bool) or int(self.target_faces) != self.target_faces \
                or self.target_faces < 100:
            raise UsageError(f"target_faces (--faces) must be an integer of at least 100, got {self.target_faces!r}")
        e = self.expected_fiducials
        if not (e is None or e == AUTO or (not isinstance(e, (str, bool)) and int(e) == e and e >= 0)):
            raise UsageError(f"expected_fiducials (--fiducials) must be a count >= 0, {AUTO!r} or None, got {e!r}")
        if int(self.fiducial_rows) != self.fiducial_rows or self.fiducial_rows < 1:
            raise UsageError(f"fiducial_rows must be a positive integer, got {self.fiducial_rows!r}")
        if not self.min_heart_ml > 0:
            raise UsageError(f"min_heart_ml must be positive, got {self.min_heart_ml!r}")
        if self.fiducials_mm is not None:
            try:
                points = tuple(tuple(float(x) for x in p) for p in self.fiducials_mm)
            except (TypeError, ValueError):
                points = ((),)
            if len(points) < 3 or any(len(p) != 3 or not all(math.isfinite(x) for x in p) for p in points):
                raise UsageError("fiducials_mm (--fiducials FILE) must be at least 3 points of 3 finite coordinates "
                                 f"(patient LPS mm), got {len(points)}")
            if len(points) % int(self.fiducial_rows):
                raise UsageError(f"fiducials_mm (--fiducials FILE): {len(points)} points cannot form "
                                 f"{self.fiducial_rows} equal rows of staples (the session touches them by rows)")
            if e not in (None, AUTO) and int(e) != len(points):
                raise UsageError(f"expected_fiducials ({e}) and fiducials_mm ({len(points)} points) disagree")
            object.__setattr__(self, "fiducials_mm", points)
        self._freeze_mapping("segmentation")
