"""A slice of the temporal evaluation grid (``heartreg evaluate-temporal``): one
phantom case, its CT breath-hold away from 0.3, the whole chain, scored against
the truth with the grid's bounds scaled to one case."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from heartreg.cli import main
from heartreg.temporal_eval import CRITERIA, evaluate, true_phase
from heartreg.temporal_evidence import read_evidence, shape_from_evidence, transform_error
from hrcore.errors import UsageError


def test_true_phases_are_drawn_away_from_the_papers():
    phases = np.array([true_phase(f"wood2018-trial{k}", s) for k in range(1, 7) for s in range(1, 7)])
    assert np.all(np.abs((phases - 0.3 + 0.5) % 1.0 - 0.5) >= 0.1 - 1e-9)
    assert np.ptp(phases) > 0.5 and len(set(phases.round(2))) > 20  # spread over the cycle
    assert true_phase("wood2018-trial2", 3) == true_phase("wood2018-trial2", 3)  # a pure function


@pytest.fixture(scope="module")
def grid_slice(tmp_path_factory):
    # trial 4: the paper's smallest session (44 points), the fastest case; seed 3, the first the
    # 72-case grid scores within every bound (seeds 1, 2 and 4 are among its 8 uncovered cases:
    # 0.84 [0.81, 0.86] for 0.87, 0.74 [0.69, 0.79] for 0.79, 0.64 [0.60, 0.70] for 0.71)
    out = tmp_path_factory.mktemp("temporal_eval")
    result = evaluate(out, presets=("wood2018-trial4",), seeds=(3,))
    return out, result


def test_grid_slice_meets_the_bounds_scaled_to_one_case(grid_slice):
    _, result = grid_slice
    (case,) = result["cases"]
    assert case["phase_true"] == true_phase("wood2018-trial4", 3) and abs(case["phase_true"] - 0.3) >= 0.1
    shape, paper = case["estimates"]
    assert shape["estimator"] == "shape" and paper["estimator"] == "eq10"
    assert case["harmonics"] == [5, 4, 5, 2]  # register's default (RegistrationOptions)
    # grid bounds for one case: >= 90 % within +-0.05 and >= 95 % within 2 mm / 2 deg
    # mean that this case must be; 85-95 % coverage means it must be covered
    assert abs(shape["phase_error"]) <= CRITERIA["phase"]
    assert shape["transform_mm"] <= 2.0 and shape["transform_deg"] <= 2.0
    assert shape["covered"] and shape["decided"]
    # the paper's metric is scored on the same case, beside it
    assert np.isfinite(paper["phase_error"]) and np.isfinite(paper["transform_mm"])
    assert case["T0_mm"] > 3.0  # the fiducial seed is off by the skin shift, as in the paper


def test_grid_outputs_agree_with_the_cases(grid_slice, capsys):
    out, _ = grid_slice
    summary = json.loads((out / "temporal_eval.json").read_text())["summary"]
    assert summary["shape"]["cases"] == 1 and summary["shape"]["phase_within"] == 1.0
    table = (out / "temporal_eval.md").read_text()
    assert "| shape (default) | 100 % | 100 % | 100 % |" in table
    rows = (out / "temporal_eval.csv").read_text().splitlines()
    assert len(rows) == 3 and rows[0].startswith("preset,seed,phase_true")
    # re-summarised by the CLI without running anything: the same table
    assert main(["evaluate-temporal", "-o", str(out), "--trials", "4", "--seeds", "3", "--report-only"]) == 0
    assert table in capsys.readouterr().out


def test_the_saved_evidence_gives_the_shape_row_again(grid_slice):
    # issue 12: an estimator's variant is scored on the grid's own cases from their saved sweeps, without
    # new ICP runs (bench/temporal_rescore.py), which holds only if the evidence gives the stored row again
    out, result = grid_slice
    shape = result["cases"][0]["estimates"][0]
    ev = read_evidence(out, "wood2018-trial4", 3)
    est = shape_from_evidence(ev)
    assert est.respiration_phase == shape["phase"]
    assert est.interval.tolist() == [shape["interval_low"], shape["interval_high"]]
    assert est.transform_mm == shape["transform_90_mm"]
    assert transform_error(ev["T_heart_from_probe"][est.index], ev) == (shape["transform_mm"], shape["transform_deg"])
    # options go to estimate_phase: the same sweep, another bootstrap
    assert shape_from_evidence(ev, n_bootstrap=40).bootstrap_phases.shape == (40,)
    # an older grid's evidence (no registered points' means, vertices subsampled) is refused in one line
    with pytest.raises(UsageError, match="run the grid again"):
        shape_from_evidence({k: v for k, v in ev.items() if k != "mean_points_map_mm"})
    with pytest.raises(UsageError, match="no evidence"):
        read_evidence(out, "wood2018-trial4", 99)


def test_the_grid_runs_on_the_batch_machinery_and_records_a_failed_case(tmp_path):
    # a local Dask cluster (heartreg.batch): a case that cannot run is
    # recorded with its one-line error, the table is not written from nothing,
    # and nothing half-written is left for the next run to mistake for a case
    messages = []
    result = evaluate(tmp_path, presets=("no-such-preset",), seeds=(1,), workers=1, say=messages.append)
    assert list(result["failed"]) == ["no-such-preset_s1"]
    assert "unknown preset" in result["failed"]["no-such-preset_s1"]
    assert any("FAILED" in m for m in messages) and not result["cases"]
    assert list(tmp_path.iterdir()) == []  # no work folder, no empty cases/


def test_bad_harmonics_are_refused_before_any_case_runs(tmp_path, capsys):
    assert main(["evaluate-temporal", "-o", str(tmp_path / "out"), "--trials", "4", "--seeds", "1",
                 "--harmonics", "0", "4", "2", "1"]) != 0
    assert "--harmonics" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_bad_seeds_workers_and_case_records_are_one_line(tmp_path, capsys, grid_slice):
    """Session 17's sweep: --seeds 0 made OUT and said 'no case yet'; --workers -1 said 'at least 1' though 0
    runs in process; a damaged case record was a traceback; cases of another --size (or --harmonics) were labelled
    with it."""
    out = tmp_path / "out"
    with pytest.raises(SystemExit) as info:  # a usage error naming the flag and the value typed
        main(["evaluate-temporal", "-o", str(out), "--trials", "1", "--seeds", "0", "-q"])
    assert info.value.code == 2 and "argument --seeds: '0' is not a whole number of 1 or more" in capsys.readouterr().err
    assert main(["evaluate-temporal", "-o", str(out), "--trials", "1", "--seeds", "1", "--workers", "-1", "-q"]) == 1
    err = capsys.readouterr().err
    assert re.search("workers must be 0 .* or more", err) and "Traceback" not in err and not out.exists()
    (out / "cases").mkdir(parents=True)
    case = next(p for p in (grid_slice[0] / "cases").glob("*.json"))
    preset, seed = case.stem.rsplit("_s", 1)
    trial = preset.replace("wood2018-trial", "")
    (out / "cases" / case.name).write_bytes(case.read_bytes())
    argv = ["evaluate-temporal", "-o", str(out), "--trials", trial, "--seeds", seed, "--report-only", "-q"]
    assert main([*argv, "--size", "full"]) == 1
    assert "holds cases of size 'sample', not 'full'" in capsys.readouterr().err
    # ... nor cases fitted with other harmonics (an audit: the same table came back, labelled with neither)
    assert main([*argv, "--harmonics", "5", "4", "2", "1"]) == 1
    assert "holds cases fitted with harmonics [5, 4, 5, 2], not [5, 4, 2, 1] (--harmonics)" in capsys.readouterr().err
    assert main(argv) == 0 and main([*argv, "--harmonics", "5", "4", "5", "2"]) == 0
    capsys.readouterr()
    (out / "cases" / case.name).write_text("{bad")
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert f"{case.name} is not a readable case record" in err and "Traceback" not in err


def test_an_output_folder_of_other_files_or_no_cases_is_refused(tmp_path, capsys):
    """A session-19 hunt: -o pointed at a DICOM study folder made a cases/ folder inside it; a foreign folder
    took the results beside its files; --report-only on a new folder left an empty cases/ and said so on stdout;
    a memory limit that cannot be read left an empty OUT/cases."""
    foreign = tmp_path / "study"
    foreign.mkdir()
    (foreign / "IM0001.dcm").write_bytes(b"not ours")
    argv = ["evaluate-temporal", "--trials", "4", "--seeds", "1", "-q"]
    assert main([*argv, "-o", str(foreign)]) == 1
    assert "holds other files, not an evaluation (no cases/ folder)" in capsys.readouterr().err
    assert [p.name for p in foreign.iterdir()] == ["IM0001.dcm"]
    new = tmp_path / "new"
    assert main([*argv, "-o", str(new), "--report-only"]) == 1
    captured = capsys.readouterr()
    assert "no case in" in captured.err and "run without --report-only first" in captured.err and not captured.out
    assert main([*argv, "-o", str(new), "--workers", "1", "--memory-limit", "abc"]) == 1
    assert capsys.readouterr().err.count("\n") == 1
    assert not new.exists()
