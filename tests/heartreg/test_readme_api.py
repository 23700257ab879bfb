"""The README's Python example runs as written, on a phantom case, and its
results read back as the values written."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

README = Path(__file__).resolve().parents[2] / "README.md"


def _example() -> str:
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Python API"):]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_python_example_runs(sample_case, tmp_path, monkeypatch, capsys):
    case, truth = sample_case
    (tmp_path / "case").symlink_to(case)
    monkeypatch.chdir(tmp_path)
    scope: dict = {}
    exec(compile(_example(), str(README), "exec"), scope)  # noqa: S102 - the README's own code
    assert "phi_R* = " in capsys.readouterr().out
    build, result, model, phases, report = (scope[k] for k in ("build", "result", "model", "phases", "report"))
    np.testing.assert_allclose(model.mesh.vertices, build.model.mesh.vertices, atol=1e-4)
    assert model.cardiac_phase == build.model.cardiac_phase
    assert phases.volume_cardiac_phase == report.volume_cardiac_phase
    assert abs(result.cardiac_phase - truth["cardiac_phase"]) < 0.01
    assert (tmp_path / "out" / "registration" / "registration.json").is_file()
    again = scope["again"]
    np.testing.assert_array_equal(again.T_heart_from_probe, result.T_heart_from_probe)
    assert again.respiration_phase == result.respiration_phase and again.point_ids.tolist() == result.point_ids.tolist()
