"""How far to trust a registration (registration.plausibility.assess_trust):
each reason, triggered for real where that is cheap, and its level."""

from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest

from heartreg.cli import main
from modeling.model import read_model
from registration.pipeline import register_session
from registration.plausibility import PlausibilityWarning, TrustLevel, assess_coverage, assess_trust
from registration.session import read_session
from tests.heartreg.small_case import small_case

#: a sweep of 3 phases: enough for every check here, seconds per registration.
FAST = {"phase_step": 0.5, "cardiac_sweep": False}


def _edit_record(path, edit):
    """Rewrite a point's CSV through ``edit(list of rows of cells) -> rows``."""
    lines = path.read_text().splitlines()
    rows = edit([line.split(",") for line in lines[1:]])
    path.write_text("\n".join([lines[0]] + [",".join(r) for r in rows]) + "\n")


@pytest.fixture(scope="module")
def case(sample_case, tmp_path_factory):
    """8 points of the sample session; point 0 with 3 tracker glitches of 25 mm,
    point 1 cut to 2 s (too few heartbeats: excluded)."""
    src, truth = sample_case
    root = tmp_path_factory.mktemp("trust")
    model_dir, session_dir = small_case(src, truth, root, grid=60, points=8)
    points = sorted((session_dir / "points").iterdir())

    def glitch(rows):
        for i in (400, 1300, 2100):
            rows[i][1] = f"{float(rows[i][1]) + 25.0:.4f}"  # robot_x_mm
        return rows

    _edit_record(points[0], glitch)
    _edit_record(points[1], lambda rows: rows[:200])
    return {"model_dir": model_dir, "session_dir": session_dir, "model": read_model(model_dir),
            "session": read_session(session_dir)}


@pytest.fixture(scope="module")
def weak(case):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PlausibilityWarning)
        return register_session(case["model"], case["session"], **FAST)


def _codes(trust) -> dict:
    return {r.code: r.level for r in trust.reasons}


def test_few_bunched_points_outliers_and_exclusions_are_reasons(weak):
    codes = _codes(weak.trust)
    assert codes["few_points"] is TrustLevel.POOR  # 7 registered points, fewer than 30
    assert codes["outlier_samples"] is TrustLevel.CAUTION
    assert codes["excluded_points"] is TrustLevel.CAUTION
    assert weak.trust.level is TrustLevel.POOR  # the worst reason decides
    fits = {f.point_id: f for f in weak.point_fits}
    assert fits[0].n_outlier_samples == 3 and all(f.n_outlier_samples == 0 for k, f in fits.items() if k)
    assert [i for i, _ in weak.exclusions] == [1]
    message = {r.code: r.message for r in weak.trust.reasons}
    assert "3 outlier sample(s)" in message["outlier_samples"] and "in 1 point(s) (0)" in message["outlier_samples"]
    assert message["few_points"].startswith("7 point(s), fewer than 30")
    # in registration.json's form, levels as words
    trust = weak.to_dict()["trust"]
    assert trust["level"] == "poor" and {"code": "excluded_points", "level": "caution",
                                         "message": message["excluded_points"]} in trust["reasons"]


def test_unconverged_icp_and_a_large_fre_are_reasons(case):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PlausibilityWarning)
        result = register_session(case["model"], case["session"], icp_options={"max_iterations": 1},
                                  max_fre_mm=0.01, **FAST)
    codes = _codes(result.trust)
    assert codes["icp_not_converged"] is TrustLevel.POOR and not result.icp.converged
    assert codes["sweep_not_converged"] is TrustLevel.CAUTION
    assert codes["fiducial_error"] is TrustLevel.CAUTION and result.fre_mm > 0.01
    assert any("final ICP did not converge within 1 iterations" in n for n in result.notes)


@pytest.fixture(scope="module")
def sound(case, weak):
    """assess_trust's arguments for a registration with nothing to say against it:
    60 points spread over the surface and a decided phi_R* (the rest as ``weak``)."""
    v = case["model"].mesh.vertices
    spread = v[np.random.default_rng(0).choice(len(v), 60, replace=False)]
    return {
        "coverage": assess_coverage(spread, v, warn=False), "outlier_samples_per_point": {0: 0, 2: 0},
        "n_excluded": 0, "phase_estimate": dataclasses.replace(weak.phase_estimates[0], decided=True),
        "icp_converged": True, "icp_degenerate": False, "sweep_unconverged": 0, "fre_mm": 0.4,
        "max_fre_mm": 3.0, "fiducials_ambiguous": False, "rms_mm": 0.3, "correction_mm": 10.0, "correction_deg": 3.0,
    }


def test_nothing_against_it_is_ok(sound):
    trust = assess_trust(**sound)
    assert trust.level is TrustLevel.OK and trust.reasons == () and trust.summary() == "ok"
    assert trust.to_dict() == {"level": "ok", "reasons": []}


@pytest.mark.parametrize("change, code, level", [
    ({"icp_degenerate": True}, "icp_degenerate", TrustLevel.POOR),
    ({"fiducials_ambiguous": True}, "fiducials_ambiguous", TrustLevel.CAUTION),
    ({"phase_estimate": "undecided"}, "phase_undecided", TrustLevel.CAUTION),
    ({"coverage": "bunched"}, "narrow_coverage", TrustLevel.CAUTION),
    # a model of another heart (the adversarial review's case: 5.1 mm RMS, 48 deg from T0)
    ({"rms_mm": 5.1}, "surface_misfit", TrustLevel.CAUTION),
    ({"correction_deg": 48.0, "correction_mm": 12.0}, "seed_contradicted", TrustLevel.POOR),
    ({"correction_deg": 5.0, "correction_mm": 41.0}, "seed_contradicted", TrustLevel.POOR),
    ({"rms_mm": 2.0, "correction_deg": 8.2, "correction_mm": 9.9}, None, TrustLevel.OK),  # the paper's in vivo means
    # a tracker that lost half of a point's poses (an audit's PLUS session: the trust was "ok"); a few are normal
    ({"invalid_samples_per_point": {0: (750, 1500), 2: (3, 1500)}}, "invalid_poses", TrustLevel.CAUTION),
    ({"invalid_samples_per_point": {0: (150, 1500), 2: (0, 1500)}}, None, TrustLevel.OK),
])
def test_each_other_reason_alone_sets_its_level(case, weak, sound, change, code, level):
    args = dict(sound, **change)
    if change.get("phase_estimate") == "undecided":
        args["phase_estimate"] = dataclasses.replace(weak.phase_estimates[0], decided=False)
    if change.get("coverage") == "bunched":  # 40 points on one side of the heart
        v = case["model"].mesh.vertices
        side = v[(v[:, 0] > 0.5 * v[:, 0].max()) & (np.abs(v[:, 2] - v[:, 2].mean()) < 10)]
        args["coverage"] = assess_coverage(side[np.random.default_rng(1).choice(len(side), 40)], v, warn=False)
    trust = assess_trust(**args)
    if code is None:
        assert trust.reasons == () and trust.level is level
        return
    assert [(r.code, r.level) for r in trust.reasons] == [(code, level)] and trust.level is level
    assert trust.summary() == f"{level.value} ({code})"
    if code == "invalid_poses":
        assert trust.reasons[0].message.startswith("the tracker marked up to 50% of the poses of 1 point(s) (0) invalid")


def test_register_writes_and_prints_the_trust(case, tmp_path, capsys):
    out = tmp_path / "reg"
    assert main(["register", str(case["model_dir"]), str(case["session_dir"]), "-o", str(out), "-q",
                 "--step", "0.5", "--no-view"]) == 0
    trust = json.loads((out / "registration.json").read_text())["trust"]
    assert trust["level"] == "poor"
    codes = [r["code"] for r in trust["reasons"]]
    assert {"few_points", "outlier_samples", "excluded_points"} <= set(codes)
    printed = [line for line in capsys.readouterr().out.splitlines() if line.strip().startswith("trust")]
    assert printed == [f"  trust             poor ({', '.join(codes)}); see the notes"]


def test_the_report_page_shows_the_trust_and_its_reasons(weak, sound):
    from heartreg.report_html import trust_html

    page = trust_html(weak.trust)
    assert 'class="trust trust-poor"' in page and "POOR" in page
    assert all(r.message.replace("'", "&#x27;") in page for r in weak.trust.reasons)
    assert "<ul>" not in trust_html(assess_trust(**sound))  # ok: no reasons listed
