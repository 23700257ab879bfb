"""``heartreg batch``: four sample cases on a two-worker local cluster, stopped and resumed.

The cases share the session-wide sample phantom (``sample_case``): one runs the
whole chain (phases, model, register with the sample session's first 8 points),
two only phases and model with different options, and one is broken (a study
folder without DICOM).  The batch is started in a child process on its own
local cluster and killed after two cases finish; the restart runs on a
scheduler started separately with one worker (the module's one other cluster) and must run
only the rest, and every output must be the bytes the single commands write
(the commands are deterministic: same inputs, same bytes).
"""

from __future__ import annotations

import contextlib
import csv
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from heartreg.batch import CohortError, read_cohort, run_batch
from heartreg.batch.cohort import default_name, select_part
from heartreg.cli import main
from tests.heartreg.small_case import first_points

REPO = Path(__file__).resolve().parents[2]
#: bounded waits (s): a loaded 2-core machine runs a sample case in 5-60 s
KILL_WAIT_S = 600
SCHEDULER_WAIT_S = 120

ROWS = [
    # case, study, session, options
    ("whole", "case/ct", "short", "--step 0.1 --no-view"),
    ("faces8k", "case/ct", "", "--faces 8000 --fiducials 0"),
    ("broken", "broken", "", ""),
    ("vessels", "case/ct", "", "--keep-vessels --faces 8000 --fiducials 0"),
]
BROKEN_MESSAGE = r"^phases: no DICOM images found under '<study>'"
#: points of the session the whole case registers (the shape estimator's least)
SHORT_POINTS = 8


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")])
    return env


def _write_cohort(folder: Path, case_dir: Path, rows) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "case").symlink_to(case_dir)
    if any(r[2] == "short" for r in rows):
        first_points(case_dir / "session", folder / "short", SHORT_POINTS)
    (folder / "broken").mkdir()
    (folder / "broken" / "IM0001.dcm").write_bytes(b"not a DICOM file")
    path = folder / "cohort.csv"
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["case", "study", "session", "options"])
        writer.writerows(rows)
    return path


def _finished(out: Path) -> dict:
    """Finished cases: name -> mtime of case.json (ns)."""
    return {p.parent.name: p.stat().st_mtime_ns for p in out.glob("*/case.json")}


def _files(folder: Path) -> dict:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def scheduler():
    """A scheduler and one worker in their own process (127.0.0.1, ephemeral port): its address.

    One worker is enough to be another cluster (the restart's two or so cases run one
    after the other); each worker process more costs seconds of imports."""
    script = (
        "import sys\n"
        "from distributed import LocalCluster\n"
        "if __name__ == '__main__':\n"
        "    c = LocalCluster(n_workers=1, threads_per_worker=1, host='127.0.0.1', scheduler_port=0,\n"
        "                     dashboard_address=None)\n"
        "    print(c.scheduler_address, flush=True)\n"
        "    sys.stdin.read()\n"  # until the fixture closes stdin
        "    c.close()\n"
    )
    cluster = subprocess.Popen([sys.executable, "-c", script], env=_env(), stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, start_new_session=True)
    try:
        address = cluster.stdout.readline().strip()
        assert address.startswith("tcp://127.0.0.1:"), address  # else the batch would start a local cluster
        yield address
    finally:
        cluster.stdin.close()
        try:
            cluster.wait(timeout=SCHEDULER_WAIT_S)
        except subprocess.TimeoutExpired:
            os.killpg(cluster.pid, signal.SIGKILL)


@pytest.fixture(scope="module")
def batch(sample_case, request, tmp_path_factory):
    """The batch killed after two cases, then run again to the end on the separate scheduler.

    The separate scheduler starts once the killed batch is gone: its processes would
    only compete with the batch's own local cluster for the cores."""
    case_dir, _ = sample_case
    root = tmp_path_factory.mktemp("batch")
    cohort = _write_cohort(root / "in", case_dir, ROWS)
    out = root / "out"
    child = subprocess.Popen(
        [sys.executable, "-m", "heartreg.cli", "batch", str(cohort), "-o", str(out), "--workers", "2", "-q"],
        env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )
    try:
        deadline = time.monotonic() + KILL_WAIT_S
        while len(_finished(out)) < 2 and child.poll() is None and time.monotonic() < deadline:
            time.sleep(0.2)
        child.kill()  # the client only: its local workers must notice and stop by themselves
        child.wait(timeout=30)
        before = _finished(out)
        folders = sorted(p.name for p in out.iterdir() if p.is_dir() and not p.name.startswith((".", "_")))
    finally:
        time.sleep(1)
        try:
            os.killpg(child.pid, signal.SIGKILL)  # any worker left behind (cleanup, not part of the test)
        except ProcessLookupError:
            pass
    result = run_batch(cohort, out, scheduler=request.getfixturevalue("scheduler"), progress=False)
    return root, cohort, out, before, folders, result


def test_a_killed_batch_leaves_only_whole_cases_and_the_restart_runs_only_the_rest(batch):
    _, _, out, before, folders, result = batch
    assert len(before) >= 2
    # no half-written case: every case folder the killed batch left holds its record
    assert folders == sorted(before)
    names = {r[0] for r in ROWS}
    assert set(result.ran) == names - set(before)
    # the cases done before the kill were judged done by their key, not rewritten
    assert {n: t for n, t in _finished(out).items() if n in before} == before
    by_name = {r.case: r for r in result.records}
    assert all(by_name[n].reused for n in before)
    # the staging folders of the cases the kill interrupted are gone
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")]


@pytest.mark.parametrize("to_group", [True, False], ids=["terminal", "process"])
def test_ctrl_c_in_a_terminal_is_one_line(sample_case, tmp_path, to_group):
    """A terminal's Ctrl-C reaches the whole process group: each local worker printed its own KeyboardInterrupt
    and lost heartbeats (70 lines, 3 tracebacks), and the resource tracker two lines of leaked semaphores.  The
    workers now ignore SIGINT (the command stops them) and the tracker's warning is off.  A SIGINT to the command
    alone (``timeout -s INT``) left the case under way's staging folder (an audit: 3.9 MB until the next run)."""
    case_dir, _ = sample_case
    cohort = _write_cohort(tmp_path / "in", case_dir, [("faces8k", "case/ct", "", "--faces 8000 --fiducials 0")])
    out = tmp_path / "out"
    child = subprocess.Popen(
        [sys.executable, "-m", "heartreg.cli", "batch", str(cohort), "-o", str(out), "--workers", "1", "-q"],
        env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        deadline = time.monotonic() + KILL_WAIT_S
        while child.poll() is None and time.monotonic() < deadline and not (
                out.is_dir() and any(p.name.startswith(".") for p in out.iterdir())):  # a case under way
            time.sleep(0.05)
        os.killpg(child.pid, signal.SIGINT) if to_group else child.send_signal(signal.SIGINT)
        _, err = child.communicate(timeout=120)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(child.pid, signal.SIGKILL)
    assert child.returncode == 130, err
    assert err.splitlines() == ["heartreg batch: interrupted; the cases finished are kept in the output folder and "
                                "its summary.csv: run the same command again to go on"], err
    # ... and the case under way leaves no staging folder
    assert not [p.name for p in out.iterdir() if p.name.startswith(".")], list(out.iterdir())


def test_three_done_one_failed_with_its_message(batch):
    _, _, out, _, _, result = batch
    statuses = {r.case: r.status for r in result.records}
    assert statuses == {"whole": "done", "faces8k": "done", "broken": "failed", "vessels": "done"}
    (failed,) = [r for r in result.records if r.status == "failed"]
    assert failed.error == json.loads((out / "_failed" / "broken.json").read_text())["error"]
    assert re.match(BROKEN_MESSAGE, failed.error), failed.error
    assert not (out / "broken").exists()


def test_outputs_are_the_single_commands_bytes(batch, sample_outputs, tmp_path):
    root, _, out, _, _, _ = batch
    # ``heartreg phases`` and ``heartreg model`` of the case's CT (default options, run once
    # for the suite), then ``heartreg register`` with the case's session and options
    session = str(root / "in" / "short")
    assert main(["register", str(sample_outputs / "model"), session, "-o", str(tmp_path / "registration"), "-q",
                 "--step", "0.1", "--no-view"]) == 0
    single = {"phases": sample_outputs / "phases", "model": sample_outputs / "model",
              "registration": tmp_path / "registration"}
    for part in ("phases", "model", "registration"):
        mine, theirs = _files(out / "whole" / part), _files(single[part])
        assert sorted(mine) == sorted(theirs) and len(mine) >= 3, part
        assert [n for n in mine if mine[n] != theirs[n]] == [], part


def test_summary_and_index_hold_the_outputs_numbers_and_no_input_path(batch):
    root, _, out, _, _, _ = batch
    rows = {r["case"]: r for r in csv.DictReader((out / "summary.csv").open())}
    assert list(rows) == [r[0] for r in ROWS]
    for name in ("whole", "faces8k", "vessels"):
        phases = json.loads((out / name / "phases" / "phases.json").read_text())
        model = json.loads((out / name / "model" / "model.json").read_text())
        row = rows[name]
        assert row["status"] == "done" and row["error"] == ""
        # summary.csv writes 10 significant digits
        assert float(row["phi_c"]) == pytest.approx(phases["volume_cardiac_phase"], rel=1e-9)
        assert float(row["heart_volume_ml"]) == pytest.approx(model["volume_mm3"] / 1000, rel=1e-9)
        assert [float(row[f"euler_{a}_deg"]) for a in "xyz"] == pytest.approx(model["euler_xyz_deg"], rel=1e-9)
        assert int(row["n_faces"]) == model["n_faces"]
    assert int(rows["faces8k"]["n_faces"]) <= 8000 < int(rows["whole"]["n_faces"])
    reg = json.loads((out / "whole" / "registration" / "registration.json").read_text())
    assert float(rows["whole"]["phi_r"]) == pytest.approx(reg["respiration_phase"], abs=1e-12)
    assert float(rows["whole"]["rms_mm"]) == pytest.approx(reg["rms_mm"], rel=1e-9)
    # the registration's trust is in the summary (it was only inside each case's folder)
    assert rows["whole"]["trust"] == reg["trust"]["level"]
    assert rows["whole"]["trust_reasons"] == "; ".join(r["code"] for r in reg["trust"]["reasons"])
    assert rows["faces8k"]["phi_r"] == "" and rows["broken"]["status"] == "failed"
    page = (out / "index.html").read_text()
    assert page.count("data:image/png;base64,") == 3  # one picture per done case
    for name in ("whole", "faces8k", "vessels"):
        assert f'<a href="{name}/">{name}</a>' in page
    assert "no DICOM images found" in page
    for text in (page, (out / "summary.csv").read_text(), *(p.read_text() for p in out.glob("*/case.json"))):
        assert str(root) not in text and "PHANTOM^" not in text


def test_the_key_follows_inputs_and_options_not_where_the_cohort_is(batch, sample_case, tmp_path):
    case_dir, _ = sample_case
    _, cohort, _, _, _, _ = batch
    # the same cohort in another folder, with one option changed
    rows = [r if r[0] != "vessels" else ("vessels", "case/ct", "", "--keep-vessels --faces 6000 --fiducials 0")
            for r in ROWS]
    changed = _write_cohort(tmp_path / "in", case_dir, rows)
    cases = {c.name: c for c in read_cohort(changed)}
    from heartreg.batch import case_key

    old = {c.name: c for c in read_cohort(cohort)}
    assert case_key(cases["faces8k"]) == case_key(old["faces8k"])  # moved cohort, same inputs: same key
    assert case_key(cases["vessels"]) != case_key(old["vessels"])


def test_scheduler_started_separately_on_loopback(batch, scheduler, sample_case, tmp_path):
    """The batch connects to a scheduler and workers in their own process (127.0.0.1, ephemeral
    port); a case the killed batch's local cluster finished comes out the same bytes there."""
    case_dir, _ = sample_case
    _, _, out, before, _, _ = batch
    # a case without a session that the local cluster finished before the kill (two finished: one is)
    local = next(r for r in ROWS if r[0] in before and not r[2])
    cohort = _write_cohort(tmp_path / "in", case_dir, [local, next(r for r in ROWS if r[0] == "broken")])
    remote = tmp_path / "out"
    code = main(["batch", str(cohort), "-o", str(remote), "--scheduler", scheduler, "-q"])
    assert code == 1  # one case failed
    statuses = {r["case"]: r["status"] for r in csv.DictReader((remote / "summary.csv").open())}
    assert statuses == {local[0]: "done", "broken": "failed"}
    # the worker of the other cluster wrote the same bytes as the local batch
    for part in ("phases", "model"):
        assert _files(remote / local[0] / part) == _files(out / local[0] / part)


def test_workers_import_the_compiled_modules_before_any_task():
    """A new local worker has imported PRELOAD by the time the client is handed out, before any task
    (a task's thread loading them left heaps corrupt at exit)."""
    from heartreg.batch.cluster import PRELOAD, open_client

    def loaded():
        return [m for m in PRELOAD if m in sys.modules]

    with open_client(workers=1) as client:
        assert list(client.run(loaded).values()) == [list(PRELOAD)]


def test_an_unreachable_scheduler_is_one_line(tmp_path, sample_case, capsys, monkeypatch):
    case_dir, _ = sample_case
    monkeypatch.setattr("heartreg.batch.cluster.CONNECT_TIMEOUT_S", 2)  # Dask retries until then
    cohort = _write_cohort(tmp_path / "in", case_dir, ROWS[1:2])
    # port 9 (discard) on loopback: nothing listens, the connection is refused at once
    assert main(["batch", str(cohort), "-o", str(tmp_path / "out"), "--scheduler", "tcp://127.0.0.1:9", "-q"]) == 1
    err = capsys.readouterr().err
    assert "cannot reach the Dask scheduler at tcp://127.0.0.1:9" in err and "Traceback" not in err
    assert not (tmp_path / "out").exists()  # a refusal at start writes nothing (it wrote summary.csv before)


def test_a_service_that_is_no_scheduler_is_one_line_not_a_hang(tmp_path, sample_case, capsys, monkeypatch):
    """An HTTP server (a dashboard's port given for the scheduler's) accepts and waits for a request: Dask's
    client waited forever, past its own timeout; a malformed address gave a traceback (session 16's sweep)."""
    import socket
    import threading

    monkeypatch.setattr("heartreg.batch.cluster.CONNECT_TIMEOUT_S", 2)  # the handshake awaited 2 s, not 10
    case_dir, _ = sample_case
    cohort = _write_cohort(tmp_path / "in", case_dir, ROWS[1:2])
    quiet = socket.create_server(("127.0.0.1", 0))
    accepted = []
    thread = threading.Thread(target=lambda: accepted.append(quiet.accept()), daemon=True)
    thread.start()
    try:
        t0 = time.monotonic()
        address = f"tcp://127.0.0.1:{quiet.getsockname()[1]}"
        assert main(["batch", str(cohort), "-o", str(tmp_path / "out"), "--scheduler", address, "-q"]) == 1
        assert time.monotonic() - t0 < 30
        err = capsys.readouterr().err
        assert "answers, but not as a Dask scheduler (no handshake within 2 s)" in err and "Traceback" not in err
    finally:
        quiet.close()
    for address in ("not-an-address", "tcp://127.0.0.1"):
        assert main(["batch", str(cohort), "-o", str(tmp_path / "out"), "--scheduler", address, "-q"]) == 1
        err = capsys.readouterr().err
        assert "give tcp://HOST:PORT" in err and "Traceback" not in err
    assert main(["batch", str(cohort), "-o", str(tmp_path / "out"), "--workers", "1000", "-q"]) == 1
    assert "at most 4 per core" in capsys.readouterr().err
    assert main(["batch", str(cohort), "-o", str(tmp_path / "out"), "--workers", "1", "--memory-limit", "1MB",
                 "-q"]) == 1
    assert "less than a case needs" in capsys.readouterr().err
    # dask reads '-1GB' as minus a gigabyte, and its nanny failed to start with a traceback (a review)
    assert main(["batch", str(cohort), "-o", str(tmp_path / "out"), "--workers", "1", "--memory-limit=-1GB",
                 "-q"]) == 1
    assert "--memory-limit '-1GB' is not an amount of memory" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


# ------------------------------------------------------------------ cohort (no cluster)
def test_options_go_to_the_commands_that_have_them(tmp_path, sample_case):
    case_dir, _ = sample_case
    (tmp_path / "qrs.csv").write_text("time_s\n1.0\n")
    cohort = _write_cohort(tmp_path / "in", case_dir, [
        ("a", "case/ct", "case/session", "--qrs ../qrs.csv --faces 9000 --step 0.05 --harmonics 3 2 1 1"),
    ])
    (case,) = read_cohort(cohort)
    qrs = str((tmp_path / "qrs.csv").resolve())
    assert case.argv["phases"] == ("--qrs", qrs)
    assert case.argv["model"] == ("--qrs", qrs, "--faces", "9000")
    assert case.argv["register"] == ("--step", "0.05", "--harmonics", "3", "2", "1", "1")
    assert case.inputs["phases --qrs"] == qrs and case.session == str((case_dir / "session").resolve())


def test_a_seed_file_is_an_input_like_the_others(tmp_path, sample_case):
    """``--seed POINT.mrk.json`` (a value that may be a point or a file) was kept verbatim: not resolved against
    the cohort's folder, not in the case's key (a moved point reused the old case), and its absolute path, with
    whatever folder names it held, written into case.json.  Points stay as they are."""
    from heartreg.batch.case import _placeholders, _redact

    case_dir, _ = sample_case
    cohort = _write_cohort(tmp_path / "in", case_dir, [
        ("a", "case/ct", "", "--seed seed.mrk.json"), ("b", "case/ct", "", "--seed=-12.5,40,-100"),
    ])
    a, b = read_cohort(cohort)
    seed = str((tmp_path / "in" / "seed.mrk.json").resolve())
    assert a.argv["model"] == ("--seed", seed) and a.inputs["model --seed"] == seed
    assert [_redact(x, _placeholders(a)) for x in a.argv["model"]] == ["--seed", "<model --seed>"]
    assert b.argv["model"] == ("--seed=-12.5,40,-100",) and "model --seed" not in b.inputs


@pytest.mark.parametrize(("options", "match"), [
    ("--facs 9000", r"line 2: '--facs' is not an option of heartreg phases, model, register"),
    ("-o elsewhere", r"line 2: option -o is set by the batch itself"),
    ("--faces many", r"line 2: heartreg model: argument --faces: invalid int value: 'many'"),
    ("--step 0.05", r"line 2: --step is an option of register, but the case has no session"),
    ("--harmonics 5 4", r"line 2: option --harmonics needs 4 value\(s\)"),
    # values the parser takes and the options refuse: refused here too, not once the case runs (an audit)
    ("--faces -5", r"line 2: heartreg model: target_faces \(--faces\) must be an integer of at least 100, got -5"),
    ("--keep-vessels --trim-vessels", r"line 2: heartreg model: --keep-vessels and --trim-vessels contradict"),
])
def test_bad_options_are_refused_before_any_work(tmp_path, sample_case, options, match):
    case_dir, _ = sample_case
    cohort = _write_cohort(tmp_path / "in", case_dir, [("a", "case/ct", "", options)])
    with pytest.raises(CohortError, match=match):
        read_cohort(cohort)


def test_cohort_names_and_parts(tmp_path, sample_case):
    case_dir, _ = sample_case
    twice = _write_cohort(tmp_path / "twice", case_dir, [("a", "case/ct", "", ""), ("A", "broken", "", "")])
    with pytest.raises(CohortError, match="case name 'A' is used twice"):
        read_cohort(twice)
    bad = _write_cohort(tmp_path / "bad", case_dir, [("../up", "case/ct", "", "")])
    with pytest.raises(CohortError, match=r"case name '../up' must start with a letter or digit"):
        read_cohort(bad)
    # a folder of study folders: one case per subfolder, in the folders' order, named by a hash of the folder's
    # name, never by it (an audit: 'JaneDoe_MRN12345' named the output folder, the summary's rows and the page)
    folder = tmp_path / "folder"
    for name in ("s2", "s1"):
        (folder / name).mkdir(parents=True)
    cases = read_cohort(folder)
    assert [c.name for c in cases] == [default_name("s1"), default_name("s2")] and not any(c.has_session for c in cases)
    assert [c.unnamed_study for c in cases] == ["s1", "s2"] and re.fullmatch(r"case-[0-9a-f]{10}", cases[0].name)
    # a broken link to a study is a case (that will fail), not one that vanishes without a line
    (folder / "s3").symlink_to(tmp_path / "moved_away")
    assert [c.unnamed_study for c in read_cohort(folder)] == ["s1", "s2", "s3"]
    (folder / "s3").unlink()
    # any folder name will do now (before, names that could not name an output folder were refused)
    for name in ("case two", "J\u00f6rg"):
        (folder / name).mkdir()
    assert [c.unnamed_study for c in read_cohort(folder)] == ["J\u00f6rg", "case two", "s1", "s2"]
    # a CSV row without a case name: the hash of its study cell, as given
    unnamed = _write_cohort(tmp_path / "unnamed", case_dir, [("", "case/ct", "", "")])
    assert [c.name for c in read_cohort(unnamed)] == [default_name("case/ct")]
    parts = [select_part(list("abcde"), 2, i) for i in (0, 1)]
    assert parts == [("a", "c", "e"), ("b", "d")]
    with pytest.raises(CohortError, match=r"--part-id must be in 0..1 for --num-parts 2, got 2"):
        select_part(list("abc"), 2, 2)


def test_notes_written_name_no_file_and_no_uid(tmp_path):
    """A case's notes go into case.json, summary.csv and index.html: no file name of its study (a file can be
    named after the patient) and no series UID (header data)."""
    from heartreg.batch.case import _without_file_names
    from heartreg.batch.cohort import Case

    study = tmp_path / "study"
    study.mkdir()
    (study / "SMITHERS_WAYLON.CT.0005.dcm").write_text("x")
    case = Case(name="a", study=str(study), session="", argv={c: () for c in ("phases", "model", "register")},
                inputs={"study": str(study)})
    clean = _without_file_names(case)
    assert clean("series [0] 1.2.826.0.1.3680043.8.498.1: skipped <study>/SMITHERS_WAYLON.CT.0005.dcm") == \
        "series [0] <uid>: skipped <study>/a file"
    # nor its pseudonym, which the refusals now print in the UID's place
    assert clean("used [0] 2.25.203301141038854865093112567078745046446: choose") == "used [0] <uid>: choose"


def test_a_folder_of_other_files_is_no_output_folder(tmp_path, sample_case):
    """A user's own summary.csv and index.html were replaced by a batch's (session 16's sweep): a non-empty
    output folder must be an earlier batch's."""
    case_dir, _ = sample_case
    cohort = _write_cohort(tmp_path / "in", case_dir, [("a", "broken", "", "")])
    out = tmp_path / "mine"
    out.mkdir()
    (out / "summary.csv").write_text("my,data\n")
    (out / "index.html").write_text("<p>mine\n")
    with pytest.raises(CohortError, match="holds files that are not an earlier batch's"):
        run_batch(cohort, out, workers=1, progress=False)
    assert (out / "summary.csv").read_text() == "my,data\n" and (out / "index.html").read_text() == "<p>mine\n"


def test_an_output_folder_inside_a_cohort_folder_is_not_a_case(tmp_path, batch):
    """``heartreg batch COHORT_DIR -o COHORT_DIR/out`` ran once, then its output folder was read as a study."""
    from heartreg.batch.cohort import is_batch_output

    _, _, out, _, _, _ = batch
    assert is_batch_output(out)
    folder = tmp_path / "cohort"
    (folder / "study1").mkdir(parents=True)
    (folder / "out").mkdir()
    (folder / "out" / "summary.csv").write_text((out / "summary.csv").read_text())
    assert [c.unnamed_study for c in read_cohort(folder)] == ["study1"]


def test_an_output_folder_inside_an_input_is_refused(tmp_path, sample_case):
    case_dir, _ = sample_case
    cohort = _write_cohort(tmp_path / "in", case_dir, [("a", "broken", "", "")])
    with pytest.raises(CohortError, match="is inside case a's study"):
        run_batch(cohort, tmp_path / "in" / "broken" / "out", workers=1, progress=False)


def test_index_marks_untrusted_registrations_and_counts_them(tmp_path):
    """A poor registration stood in index.html as the plain word 'poor' among ok cases (a page audit): its cell
    is now marked by level, and a line above the table names the cases not trusted."""
    import html as html_lib

    from heartreg.batch.case import CaseRecord
    from heartreg.batch.report import index_html

    records = [CaseRecord(case="good", status="done", values={"trust": "ok", "phi_r": 0.29}),
               CaseRecord(case="few", status="done",
                          values={"trust": "poor", "trust_reasons": "few_points; icp_degenerate", "phi_r": 0.72}),
               CaseRecord(case="odd", status="done", values={"trust": "caution", "trust_reasons": "phase_undecided"})]
    page = index_html(records, tmp_path / "index.html", out_dir=tmp_path).read_text()
    banner = re.search(r'<p class="untrusted">(.*?)</p>', page)
    assert banner and html_lib.unescape(re.sub("<.*?>", "", banner.group(1))) == \
        "Registrations not trusted: 1 poor (few); 1 caution (odd); see each case's trust reasons."
    cells = re.findall(r'<td class="trust-(\w+)">(\w+)', page)
    assert cells == [("ok", "ok"), ("poor", "poor"), ("caution", "caution")]
    ok_only = index_html(records[:1], tmp_path / "ok.html", out_dir=tmp_path).read_text()
    assert 'class="untrusted"' not in ok_only
