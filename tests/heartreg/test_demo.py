"""The demo and the pipeline command, checked on their outputs (not just that they ran)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from heartreg.cli import main
from heartreg.demo import SAMPLE_DIR, run_demo


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    run, rows = run_demo(out, progress=False)
    return out, run, rows


def test_bundled_sample_is_a_phantom_case():
    truth = json.loads((SAMPLE_DIR / "truth.json").read_text())
    assert truth["preset"] == "wood2018-trial1" and truth["seed"] == 0 and truth["size"] == "sample"
    size = sum(p.stat().st_size for p in SAMPLE_DIR.rglob("*") if p.is_file())
    assert size <= 10 * 2**20


def test_demo_recovers_the_truth_within_tolerance(demo):
    """Every row with a tolerance is within it: phi_C*, phi_R*, frame axes, mesh
    accuracy, CT fiducials, final transform, static registration worse."""
    _, _, rows = demo
    judged = [r for r in rows if isinstance(r[5], (bool, np.bool_))]
    assert len(judged) >= 9
    missed = [r for r in judged if not r[5]]
    assert not missed, missed
    by_name = {r[0]: r for r in rows}
    assert abs(by_name["respiration phase phi_R*"][3]) <= 0.05
    assert by_name["final T, translation at heart origin (mm)"][1] < by_name["fiducial seed T0, translation (mm)"][1]


def test_demo_outputs_agree_with_the_result(demo):
    out, run, rows = demo
    reg = run.registration
    payload = json.loads((out / "registration" / "registration.json").read_text())
    assert payload["respiration_phase"] == pytest.approx(reg.respiration_phase)
    np.testing.assert_allclose(payload["T_heart_from_probe"], reg.T_heart_from_probe)
    sweep = np.genfromtxt(out / "registration" / "sweep.csv", delimiter=",", names=True)
    assert len(sweep) == 101
    # eq. 10 (the sweep's smallest distance from T0) is reported beside the shape estimator
    assert sweep["respiration_phase"][np.argmin(sweep["translation_distance_mm"])] == pytest.approx(reg.phase_estimates[1].respiration_phase)
    assert payload["phase_estimates"][0]["method"] == "shape"
    phases = json.loads((out / "phases" / "phases.json").read_text())
    model = json.loads((out / "model" / "model.json").read_text())
    assert model["cardiac_phase"] == pytest.approx(phases["volume_cardiac_phase"])
    assert payload["cardiac_phase"] == pytest.approx(model["cardiac_phase"])
    html = (out / "report.html").read_text()
    assert html.count("data:image/png;base64,") >= 6
    assert "Recovered against the phantom" in html and "PHANTOM^" not in html
    table = (out / "demo_table.txt").read_text()
    assert "respiration phase phi_R*" in table and "NO" not in table


def test_cli_pipeline_on_a_users_folders(demo, tmp_path, capsys):
    out, run, _ = demo
    dest = tmp_path / "run"
    # the 3-D view is left out (--no-view): the demo above draws it and its page is checked below
    code = main(["pipeline", str(SAMPLE_DIR / "ct"), str(out / "session_case" / "session"), "-o", str(dest),
                 "-q", "--step", "0.02", "--no-view"])
    assert code == 0
    text = capsys.readouterr().out
    assert "phi_R*" in text and (dest / "report.html").exists()
    reg = json.loads((dest / "registration" / "registration.json").read_text())
    assert abs(reg["respiration_phase"] - run.registration.respiration_phase) <= 0.02
    assert len(np.genfromtxt(dest / "registration" / "sweep.csv", delimiter=",", names=True)) == 51
    assert not (dest / "registration" / "fig8_view.png").exists()


def test_cli_pipeline_bad_session(tmp_path, capsys):
    assert main(["pipeline", str(SAMPLE_DIR / "ct"), str(tmp_path / "nope"), "-o", str(tmp_path / "o"), "-q"]) == 1
    err = capsys.readouterr().err
    assert "session" in err and "Traceback" not in err
    # a bad --step is refused before anything is read (before session 17: after the phases and the model, 6-9 s)
    assert main(["pipeline", str(SAMPLE_DIR / "ct"), str(tmp_path / "nope"), "-o", str(tmp_path / "o"), "-q",
                 "--step", "0"]) == 1
    assert "step (--step) must be in" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_cli_pipeline_failure_leaves_no_partial_outputs(demo, tmp_path, capsys):
    """The model stage fails (8 staples expected, 9 found) after the phases were
    computed: nothing of the run may stay in OUT_DIR."""
    out, _, _ = demo
    dest = tmp_path / "run"
    code = main(["pipeline", str(SAMPLE_DIR / "ct"), str(out / "session_case" / "session"), "-o", str(dest),
                 "-q", "--fiducials", "8"])
    assert code == 1
    assert "expected 8" in capsys.readouterr().err
    assert not dest.exists()  # not even an empty folder


def test_report_is_one_file_and_its_3d_view_renders_in_chromium(demo, tmp_path):
    """report.html opens offline (nothing fetched) and its interactive 3-D view draws
    the model and the registered points in headless Chromium (no GPU)."""
    import re
    import shutil
    import subprocess

    out, _, _ = demo
    page = (out / "report.html").read_text()
    # one self-contained file: no external script, style, image or font
    assert not re.search(r"""(src|href)\s*=\s*["']?(https?:|//)""", page, re.IGNORECASE)
    assert "<link" not in page and "@import" not in page and "url(" not in page
    assert 'id="view3d"' in page and "<canvas" in page
    chromium = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if chromium is None:
        pytest.skip("no chromium binary (make sysdeps installs it)")
    shot = tmp_path / "report.png"
    # the view is the page's first section: a 1100 x 850 window shows it whole
    subprocess.run(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--hide-scrollbars", f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1100,850",
         f"--screenshot={shot}", (out / "report.html").as_uri()],
        check=True, capture_output=True, timeout=180,
    )
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    assert img.std() > 20, "the screenshot is blank"
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    # the model's colour #d46a6a shaded by the light: red clearly above green and blue.
    # The legend's swatch is 14 x 14 px; the drawn heart covers tens of thousands of pixels.
    model_px = int(np.count_nonzero((r > 90) & (r - g > 45) & (r - b > 45) & (abs(g - b) < 30)))
    assert model_px > 20000, model_px
    # the registered points' green #22a35a, discs of 10 px: at least a few points face the camera
    point_px = int(np.count_nonzero((g > 130) & (g - r > 80) & (g - b > 30)))
    assert point_px > 5 * 50, point_px


def test_a_sample_or_output_in_the_way_is_refused_before_anything_is_written(tmp_path, capsys):
    """Session 17's sweep: `demo -o SAMPLE/ct/x --sample SAMPLE` wrote 56 MB of session into the input, then
    refused; a damaged truth.json was a traceback (status 70) that left an empty output folder."""
    import shutil

    sample = tmp_path / "sample"
    shutil.copytree(SAMPLE_DIR, sample)
    before = sorted(p.relative_to(sample).as_posix() for p in sample.rglob("*"))
    for out in (sample / "ct" / "x", sample / "x"):
        assert main(["demo", "-o", str(out), "--sample", str(sample), "-q"]) == 1
        assert "lies inside the input" in capsys.readouterr().err
    assert sorted(p.relative_to(sample).as_posix() for p in sample.rglob("*")) == before
    (sample / "truth.json").write_text("{}")
    assert main(["demo", "-o", str(tmp_path / "d"), "--sample", str(sample), "-q"]) == 1
    err = capsys.readouterr().err
    assert "truth.json lacks 'preset', 'seed', 'config': not a phantom truth" in err and "Traceback" not in err
    assert not (tmp_path / "d").exists()


class _Stop(Exception):
    pass


def test_demo_scores_the_experiment_of_the_case_it_is_given(sample_case, tmp_path, monkeypatch):
    """An audit's `demo --sample` of a case made with --resp-phase 0.6 (or --points 8) registered a session
    regenerated from preset and seed alone (phi_R* 0.33 against 0.6, 100 points): the demo takes the case's own
    session, and without one writes the session the case would have had (truth.json's configuration)."""
    import shutil

    import heartreg.pipeline
    from tests.heartreg.small_case import digest

    case, truth = sample_case  # trial 1 with 30 points (the preset has 101)
    used = []

    def pipeline(study, session, out, **kwargs):  # the registration itself is tested above
        used.append(session)
        raise _Stop

    monkeypatch.setattr(heartreg.pipeline, "run_pipeline", pipeline)
    with pytest.raises(_Stop):
        run_demo(tmp_path / "own", sample_dir=case, progress=False)
    assert used[-1] == case / "session" and not (tmp_path / "own" / "session_case").exists()

    bare = tmp_path / "bare"  # the case without its session
    shutil.copytree(case / "ct", bare / "ct")
    shutil.copyfile(case / "truth.json", bare / "truth.json")
    with pytest.raises(_Stop):
        run_demo(tmp_path / "again", sample_dir=bare, progress=False)
    assert used[-1] == tmp_path / "again" / "session_case" / "session"
    assert len(json.loads((used[-1] / "session.json").read_text())["points"]) == 30
    assert digest(used[-1]) == digest(case / "session")  # byte for byte the case's own


def test_demo_fails_when_a_row_is_outside_its_tolerance(tmp_path, monkeypatch, capsys):
    """The audit's demo printed phi_R* 0.33 against 0.6, 'NO', and exited 0."""
    import types

    import heartreg.demo

    rows = [("cardiac phase phi_C*", 0.5, 0.5, 0.0, 0.005, True),
            ("respiration phase phi_R*", 0.33, 0.6, -0.27, 0.05, False),
            ("fiducial FRE (mm)", 1.8, "", "", "", ""),
            ("final T, rotation (deg)", 3.0, 0.0, 3.0, 2.0, False)]
    run = types.SimpleNamespace(out_dir=tmp_path, paths={"report": tmp_path / "report.html"}, timings_s={})
    monkeypatch.setattr(heartreg.demo, "run_demo", lambda *a, **k: (run, rows))
    assert main(["demo", "-o", str(tmp_path), "-q"]) == 1
    captured = capsys.readouterr()
    assert "NO" in captured.out
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "outside tolerance: respiration phase phi_R*; final T, rotation (deg)" in lines[0]
    monkeypatch.setattr(heartreg.demo, "run_demo", lambda *a, **k: (run, rows[:1] + rows[2:3]))
    assert main(["demo", "-o", str(tmp_path), "-q"]) == 0 and capsys.readouterr().err == ""
