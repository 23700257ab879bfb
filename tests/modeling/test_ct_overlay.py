"""modeling.ct_overlay: each panel shows the patient where its letters say (radiological orientation)."""

from __future__ import annotations

import numpy as np
import pytest

from modeling.ct_overlay import AXIAL_LEVELS, ct_panels, plane_section, render_ct_png
from modeling.surface import mask_to_mesh


@pytest.mark.parametrize("reversed_axes", [False, True])
def test_markers_land_on_the_side_their_letters_name(tmp_path, reversed_axes):
    """A box-shaped 'heart' with a bright marker on the patient's left, one in front and one on top.

    Whatever the order the CT stores its voxels in, the left marker shows on the right of the axial and
    coronal panels (letter L), the front one at the top of the axial panels (A) and on the left of the
    sagittal one (A), the top one at the top of the coronal and sagittal panels (S).
    """
    shape = (40, 50, 60)  # k, j, i at 2 mm: x 0..118, y 0..98, z 0..78 mm (LPS)
    T = np.diag([2.0, 2.0, 2.0, 1.0])
    k, j, i = np.mgrid[: shape[0], : shape[1], : shape[2]] * 2.0
    hu = np.full(shape, -100.0, np.float32)
    heart = (np.abs(i - 60) < 30) & (np.abs(j - 50) < 24) & (np.abs(k - 40) < 24)
    hu[heart] = 60.0
    hu[(np.abs(i - 84) < 5) & (np.abs(j - 50) < 5) & (np.abs(k - 40) < 20)] = 1000.0  # left (+x)
    hu[(np.abs(i - 60) < 5) & (np.abs(j - 32) < 5) & (np.abs(k - 40) < 20)] = 1000.0  # anterior (-y)
    hu[(np.abs(i - 60) < 5) & (np.abs(j - 50) < 5) & (np.abs(k - 58) < 5)] = 1000.0  # superior (+z)
    mesh = mask_to_mesh(heart, T, target_faces=2000)
    if reversed_axes:  # the same anatomy stored with every axis reversed
        flip = np.diag([-1.0, -1.0, -1.0, 1.0])
        flip[:3, 3] = np.array(shape[::-1]) - 1
        hu, T = np.ascontiguousarray(hu[::-1, ::-1, ::-1]), T @ flip
    panels = ct_panels(hu, T, mesh.vertices, mesh.faces)
    assert len(panels) == len(AXIAL_LEVELS) + 2

    def bright_side(panel):
        """Mean (a, b) of the bright pixels, relative to the panel's centre."""
        b_idx, a_idx = np.nonzero(panel.image > 500)
        a0, a1, b0, b1 = panel.extent
        a = a0 + (a_idx + 0.5) * (a1 - a0) / panel.image.shape[1]
        b = b0 + (b_idx + 0.5) * (b1 - b0) / panel.image.shape[0]
        return a, b, 0.5 * (a0 + a1), 0.5 * (b0 + b1)

    axial = panels[1]  # 40 % of the height: the left and anterior markers
    a, b, ac, bc = bright_side(axial)
    assert axial.letters == ("R", "L", "P", "A")
    assert np.any((a > ac + 15) & (np.abs(b - bc) < 8))  # left marker on the right
    assert np.any((b > bc + 10) & (np.abs(a - ac) < 8))  # anterior marker at the top
    coronal, sagittal = panels[-2], panels[-1]
    a, b, ac, bc = bright_side(coronal)
    assert coronal.letters == ("R", "L", "I", "S") and np.any(a > ac + 15) and np.any(b > bc + 10)
    a, b, ac, bc = bright_side(sagittal)
    assert sagittal.letters == ("A", "P", "I", "S") and np.any(a < ac - 10) and np.any(b > bc + 10)
    # the outline is the box's: on the axial panel it spans the box's 60 x 48 mm
    span = np.ptp(axial.outline.reshape(-1, 2), axis=0)
    np.testing.assert_allclose(span, [58.0, 46.0], atol=3.0)
    render_ct_png(panels, tmp_path / "ct.png")
    with pytest.raises(ValueError, match="must end in .png"):
        render_ct_png(panels, tmp_path / "ct.jpg")


def test_plane_section_is_trimeshs():
    """The outline's segments are trimesh's ``mesh_plane``: the same segments (either end first), also for a
    plane through a vertex, where a face touching the plane at a corner adds nothing."""
    import trimesh
    from trimesh.intersections import mesh_plane

    mesh = trimesh.creation.icosphere(subdivisions=4, radius=30.0)
    rng = np.random.default_rng(7)
    planes = [(mesh.vertices[5], np.array([0.0, 0.0, 1.0]))]
    planes += [(10.0 * rng.normal(size=3), n / np.linalg.norm(n)) for n in rng.normal(size=(10, 3))]

    def canonical(segments):  # each segment's ends in order, the segments sorted
        return sorted(tuple(sorted(tuple(end) for end in np.round(segment, 5))) for segment in segments)

    for origin, normal in planes:
        ours = plane_section(mesh.vertices, mesh.faces, origin, normal)
        theirs = mesh_plane(mesh, plane_normal=normal, plane_origin=origin)
        theirs = theirs[np.linalg.norm(theirs[:, 1] - theirs[:, 0], axis=1) > 0]
        assert ours.shape == theirs.shape and ours.shape[0] > 50
        assert canonical(ours) == canonical(theirs)


def test_the_two_pictures_drawn_at_once_are_those_drawn_alone(tmp_path):
    """render_model_pictures draws model_ct.png on a thread beside model.png: each is byte for byte what
    it is drawn alone, and a model.png that cannot be drawn raises after model_ct.png is done."""
    from modeling import make_heart_model, render_model_png
    from modeling.render import render_model_pictures

    shape = (40, 50, 60)
    T = np.diag([2.0, 2.0, 2.0, 1.0])
    k, j, i = np.mgrid[: shape[0], : shape[1], : shape[2]] * 2.0
    heart = ((i - 60) / 30) ** 2 + ((j - 50) / 22) ** 2 + ((k - 40) / 26) ** 2 < 1
    hu = np.where(heart, 60.0, -100.0).astype(np.float32)
    mesh = mask_to_mesh(heart, T, target_faces=2000)
    model = make_heart_model(mesh, cardiac_phase=0.7, cardiac_phase_source="test", base_hint=[0, 0, 1])
    panels = ct_panels(hu, T, mesh.vertices, mesh.faces)
    (tmp_path / "alone").mkdir()
    (tmp_path / "both").mkdir()
    render_model_png(model, tmp_path / "alone" / "model.png")
    render_ct_png(panels, tmp_path / "alone" / "model_ct.png")
    paths = render_model_pictures(model, panels, tmp_path / "both")
    assert [p.name for p in paths] == ["model.png", "model_ct.png"]
    for name in ("model.png", "model_ct.png"):
        assert (tmp_path / "both" / name).read_bytes() == (tmp_path / "alone" / name).read_bytes(), name
    (tmp_path / "bad").mkdir()
    with pytest.raises(TypeError, match="HeartModel"):
        render_model_pictures(object(), panels, tmp_path / "bad")
    assert (tmp_path / "bad" / "model_ct.png").is_file()  # the other picture was finished, not abandoned
