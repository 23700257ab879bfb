"""Registration: the motion-model fit, the respiration sweep vs Open3D ICP, and ``heartreg register``.

Inputs (built once, untimed, into ``bench/out/data/registration_inputs.npz``)
the way ``tests/registration/conftest.py`` builds them: the trial-1 phantom
heart at (phi_C* = 0.65, phi_R* = its image phase) triangulated on a 100 x 100
(u, v) grid (20 000 faces, patient frame), 100 attachment points spread over it
(``spread_uv``) with 30 s x 100 Hz = 3000 robot poses each (``simulate_traces``:
own R-peaks and breaths per point, 0.3 mm / 0.2 deg tracker noise), and the
fiducial seed ``T0 = inv(T_fiducial_shift) @ T_patient_from_probe``.  The 101 x
100 predicted point sets of the sweep (phi_C* fixed, phi_R = 0, 0.01, ..., 1)
come from our motion models and are stored too, so both ICPs register the very
same points.

Steps, each in a fresh child process (see ``common.py``):

- motion-model fit: ``registration.motion_model.fit_motion_model`` on the 100
  traces of 3000 samples (harmonics 5 4 2 1).
- sweep: ``registration.spatiotemporal.sweep_phase`` (point-to-plane ICP seeded
  by T0 at each of the 101 phases, all phases batched, exact closest points on
  the triangles, max 50 iterations) with a prebuilt ``SurfaceIndex`` (its build,
  and the process's first closest-point query, which imports numba and loads
  the compiled search from its cache, are timed apart and reported in the
  notes); the warm start (``icp_options={"warm_start":
  True}``) runs beside it and the notes give its time and agreement.  Target
  (issue 12): <= 0.3 s on 2 cores, the same answer within 0.01 mm.
- reference: Open3D ``registration_icp`` with ``TransformationEstimationPointToPlane``,
  101 runs each seeded by T0, ``max_iteration`` 50, a max correspondence
  distance of 100 mm (all points, like ours) on a target cloud sampled densely
  from the same mesh (``sample_points_uniformly``, ~4 points per mm^2, triangle
  normals); the sampling and the KD-tree Open3D builds per call are timed, the
  sampling separately (notes).  Ours and Open3D run alternately.
- ``heartreg register`` end to end (CLI, start-up included) on a sample phantom
  case (``heartreg phantom --seed 1``: 100 points x 30 s x 100 Hz session) and
  its model (``heartreg model``, built once, untimed).
"""

from __future__ import annotations

import shutil
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

TARGET_SWEEP_S = 0.3
PHASE_C = 0.65
N_POINTS = 100
DURATION_S = 30.0
RATE_HZ = 100.0
MAX_ITERATIONS = 50
O3D_MAX_DISTANCE_MM = 100.0
O3D_POINTS_PER_MM2 = 4.0
INPUTS = common.DATA_DIR / "registration_inputs.npz"
ME = "bench_registration"


# ---------------------------------------------------------------- inputs (untimed, once)


def make_inputs(path: str = str(INPUTS)) -> dict:
    """Step (once, untimed): build the phantom inputs as tests/registration/conftest.py
    does and save them to ``path``."""
    path = Path(path)
    if path.exists():
        return {}
    import numpy as np

    sys.path.insert(0, str(common.REPO_DIR))
    from heartreg.phantom import config as phantom_config
    from heartreg.phantom import layout
    from registration.motion_model import fit_motion_model, predict_positions
    from registration.transforms import invert
    from tests.registration.conftest import heart_grid_mesh, simulate_traces, spread_uv

    print(f"bench: building registration inputs (once) into {path}", file=sys.stderr)
    cfg = phantom_config.PRESETS["wood2018-trial1"]
    heart = layout.make_heart(cfg)
    vertices, faces = heart_grid_mesh(heart, PHASE_C, cfg.image_resp_phase)
    traces, _ = simulate_traces(heart, cfg, spread_uv(N_POINTS), rng=np.random.default_rng(21),
                                duration_s=DURATION_S, rate_hz=RATE_HZ)
    models = [fit_motion_model(*trace) for trace in traces]
    phases = np.linspace(0.0, 1.0, 101)
    points = predict_positions(models, PHASE_C, phases)  # (101, n, 3)
    T0 = invert(layout.T_fiducial_shift(cfg)) @ layout.T_patient_from_probe()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, vertices=vertices, faces=faces, T0=T0, phases=phases, points=points,
             phase_c=np.stack([t[0] for t in traces]), phase_r=np.stack([t[1] for t in traces]),
             T_probe_from_robot=np.stack([t[2] for t in traces]))
    tmp.replace(path)
    return {}


def _load(path):
    import numpy as np

    with np.load(path) as z:
        return {k: z[k] for k in z.files}


# ---------------------------------------------------------------- steps (run in a child)


def fit_models(inputs: str) -> dict:
    from registration.motion_model import fit_motion_model

    d = _load(inputs)
    t0 = time.perf_counter()
    models = [fit_motion_model(pc, pr, T) for pc, pr, T in zip(d["phase_c"], d["phase_r"], d["T_probe_from_robot"])]
    elapsed = time.perf_counter() - t0
    return {"time_s": elapsed, "n_points": len(models), "n_samples": int(d["phase_c"].shape[1]),
            "residual_rms_3d_mm_median": float(sorted(m.residual_rms_3d_mm for m in models)[len(models) // 2])}


def sweep_ours_warm(inputs: str) -> dict:
    """The sweep with each phase seeded by its registered neighbour (``warm_start``)."""
    return sweep_ours(inputs, warm=True)


def sweep_ours(inputs: str, warm: bool = False) -> dict:
    from registration.icp import SurfaceIndex, closest_points
    from registration.spatiotemporal import sweep_phase

    d = _load(inputs)
    t0 = time.perf_counter()
    index = SurfaceIndex(d["vertices"], d["faces"])
    index_s = time.perf_counter() - t0
    # the process's first search imports numba and loads the compiled search from its cache:
    # once per process, like an import; timed apart from the sweep
    t0 = time.perf_counter()
    closest_points(index, d["points"][0, :1])
    first_query_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    sweep = sweep_phase(None, index, d["T0"], fixed_phase=PHASE_C, kind="respiration", phases=d["phases"],
                        points=d["points"], icp_options={"max_iterations": MAX_ITERATIONS, "warm_start": warm})
    elapsed = time.perf_counter() - t0
    return {"time_s": elapsed, "index_s": index_s, "first_query_s": first_query_s, "n_faces": int(d["faces"].shape[0]),
            "shape": list(d["points"].shape), "T": sweep.T_heart_from_probe.tolist(),
            "iterations_mean": float(sweep.iterations.mean()), "iterations_max": int(sweep.iterations.max()),
            "converged": int(sweep.converged.sum()), "rms_median_mm": float(sorted(sweep.rms_mm)[50]),
            "best_phase": sweep.best_phase}


def import_open3d():
    """``import open3d``; its Linux wheel links libusb-1.0, which minimal systems
    lack: then preload the copy the ``libusb-package`` wheel ships and retry."""
    try:
        import open3d
    except ImportError as exc:
        if "libusb" not in str(exc):
            raise
        import ctypes

        import libusb_package

        lib = next(Path(libusb_package.__file__).parent.glob("libusb-1.0.so*"))
        ctypes.CDLL(str(lib), mode=ctypes.RTLD_GLOBAL)
        import open3d
    return open3d


def sweep_open3d(inputs: str) -> dict:
    import numpy as np

    o3d = import_open3d()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    d = _load(inputs)
    t0 = time.perf_counter()
    mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(d["vertices"]),
                                     o3d.utility.Vector3iVector(d["faces"].astype(np.int32)))
    mesh.compute_triangle_normals()
    n_target = int(round(mesh.get_surface_area() * O3D_POINTS_PER_MM2))
    target = mesh.sample_points_uniformly(number_of_points=n_target, use_triangle_normal=True)
    sample_s = time.perf_counter() - t0
    reg = o3d.pipelines.registration
    estimation = reg.TransformationEstimationPointToPlane()
    criteria = reg.ICPConvergenceCriteria(max_iteration=MAX_ITERATIONS)
    sources = [o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p)) for p in d["points"]]
    Ts, rmse = [], []
    t0 = time.perf_counter()
    for source in sources:
        result = reg.registration_icp(source, target, O3D_MAX_DISTANCE_MM, d["T0"], estimation, criteria)
        Ts.append(np.asarray(result.transformation).tolist())
        rmse.append(result.inlier_rmse)
    elapsed = time.perf_counter() - t0
    return {"time_s": elapsed, "sample_s": sample_s, "n_target": n_target, "T": Ts,
            "rmse_median_mm": float(sorted(rmse)[50]), "open3d": o3d.__version__}


# ---------------------------------------------------------------- the bench


def _agreement(T_ours, T_ref, inputs) -> tuple[float, float]:
    """Max over the phases of |T_ours s - T_ref s| at the mesh's vertex centroid
    (mm; ``s`` its source-frame point under ``T_ours``) and of the rotation angle
    between them (deg).  numpy only: the parent stays small (see ``peak_note``)."""
    import numpy as np

    A, B = np.asarray(T_ours), np.asarray(T_ref)
    with np.load(inputs) as z:
        c = z["vertices"].mean(axis=0)
    s = np.einsum("aji,aj->ai", A[:, :3, :3], c - A[:, :3, 3])  # inv(A) c
    pa = np.einsum("aij,aj->ai", A[:, :3, :3], s) + A[:, :3, 3]
    pb = np.einsum("aij,aj->ai", B[:, :3, :3], s) + B[:, :3, 3]
    R = np.einsum("aji,ajk->aik", A[:, :3, :3], B[:, :3, :3])
    cos = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(pa - pb, axis=1).max()), float(np.degrees(np.arccos(cos)).max())


def open3d_version() -> dict:
    """Step: Open3D's version, or an import error (then the reference is skipped)."""
    return {"open3d": import_open3d().__version__}


def _open3d_status() -> str:
    """'' when Open3D imports (checked in a child), else why not."""
    try:
        common.run_step(f"{ME}:open3d_version", repeats=1)
    except common.BenchError as exc:
        tail = [line for line in str(exc).splitlines() if line.strip()]
        return tail[-1][:200] if tail else "open3d failed to import"
    return ""


def _sample_model(case: Path) -> Path:
    """The sample case's heart model (``heartreg model``, once, untimed)."""
    model = common.DATA_DIR / "sample_case_model"
    if (model / "model.json").exists():
        return model
    shutil.rmtree(model, ignore_errors=True)
    argv = [*common.heartreg_cli(), "model", case / "ct", "-o", model, "-q"]
    print(f"bench: building {model} (once)", file=sys.stderr)
    common.run_command(argv, repeats=1)
    return model


def main(argv=None) -> int:
    parser = common.bench_argparser(__doc__.splitlines()[0])
    parser.add_argument("--only", action="append", choices=("fit", "sweep", "register"),
                        help="run only this step (repeatable); all by default")
    args = parser.parse_args(argv)
    steps = set(args.only or ("fit", "sweep", "register"))
    common.ensure_requirements()
    n = args.repeats
    me = ME
    # Keep this parent process small: a child's peak RSS (ru_maxrss) is never
    # below its parent's RSS at the fork, so inputs are built and Open3D is
    # imported in children only.
    inputs = str(INPUTS)
    if not INPUTS.exists():
        common.run_step(f"{me}:make_inputs", {"path": inputs}, repeats=1)
    imports = ("numpy", "scipy.spatial", "registration")
    rows = []

    if "fit" in steps:
        _fit_row(rows, me, inputs, imports, n)
    if "sweep" in steps:
        _sweep_row(rows, me, inputs, imports, n)
    if "register" in steps:
        _register_row(rows, n)
    common.write_results(me, rows, command=common.command_line(), repeats=n)
    return 0


def _fit_row(rows, me, inputs, imports, n):
    fit = common.run_step(f"{me}:fit_models", {"inputs": inputs}, repeats=n, imports=imports)
    rows.append(common.Row(
        step=f"motion-model fit ({fit.info['n_points']} points x {fit.info['n_samples']} samples)",
        ours=fit,
        notes=(f"fit_motion_model per point (harmonics 5 4 2 1, lstsq on 23 terms); median residual "
               f"{fit.info['residual_rms_3d_mm_median']:.2f} mm RMS (0.3 mm tracker noise); "
               f"inputs loaded untimed; baseline after imports {fit.info['baseline_mb']:.0f} MB"),
        command="[fit_motion_model(phase_c, phase_r, T) for each of 100 points]",
    ))


def _sweep_row(rows, me, inputs, imports, n):

    o3d_error = _open3d_status()
    specs = {"ours": {"target": f"{me}:sweep_ours", "kwargs": {"inputs": inputs}, "imports": imports}}
    if not o3d_error:
        specs["ref"] = {"target": f"{me}:sweep_open3d", "kwargs": {"inputs": inputs}, "imports": ("numpy",)}
    specs["warm"] = {"target": f"{me}:sweep_ours_warm", "kwargs": {"inputs": inputs}, "imports": imports}
    both = common.run_steps_interleaved(specs, repeats=n)
    ours, ref, warm = both["ours"], both.get("ref"), both["warm"]
    info = ours.info
    verdict = "meets" if ours.median_s <= TARGET_SWEEP_S else "MISSES"
    m, npts, _ = info["shape"]
    notes = (f"{verdict} target <= {TARGET_SWEEP_S:g} s; sweep_phase point-to-plane, batched over phases, exact "
             f"closest points (compiled search of a bounding-volume hierarchy); iterations mean {info['iterations_mean']:.1f} / max {info['iterations_max']} "
             f"(cap {MAX_ITERATIONS}), {info['converged']}/{m} converged, median RMS {info['rms_median_mm']:.3f} mm; "
             f"SurfaceIndex build {info['index_s']:.3f} s and the process's first query (imports numba, loads "
             f"the compiled search from its cache) {info['first_query_s']:.3f} s, both untimed; same predicted points for both; "
             f"baseline after imports {info['baseline_mb']:.0f} MB")
    dt_warm, dr_warm = _agreement(info["T"], warm.info["T"], inputs)
    notes += (f"; warm start (every 10th phase from T0, the others from their registered neighbour): "
              f"{warm.median_s:.2f} s, {warm.info['iterations_mean']:.1f} iterations per phase, "
              f"{dt_warm:.4f} mm / {dr_warm:.4f} deg from the cold start")
    if ref is not None:
        dt, dr = _agreement(info["T"], ref.info["T"], inputs)
        notes += (f". Open3D {ref.info['open3d']}: 101 registration_icp point-to-plane from T0, max_iteration "
                  f"{MAX_ITERATIONS}, max distance {O3D_MAX_DISTANCE_MM:g} mm, target {ref.info['n_target']} points "
                  f"sampled with triangle normals ({O3D_POINTS_PER_MM2:g}/mm^2; sampling {ref.info['sample_s']:.2f} s "
                  f"untimed), multithreaded (OpenMP); median inlier RMSE {ref.info['rmse_median_mm']:.3f} mm; "
                  f"ours vs Open3D at the mesh centre: max {dt:.3f} mm, {dr:.3f} deg over the 101 phases")
    else:
        notes += f". Open3D reference not run: {o3d_error}"
    rows.append(common.Row(
        step=f"respiration sweep ({m} phases x {npts} points, {info['n_faces']}-face mesh)",
        ours=ours, reference=ref, reference_name="Open3D point-to-plane ICP x 101" if ref else "",
        notes=notes,
        command="registration.spatiotemporal.sweep_phase(None, index, T0, fixed_phase=0.65, points=P)",
    ))


def _register_row(rows, n):

    case = common.ensure_phantom_case("sample_case", size="sample", preset="default", seed=1, session=True)
    model = _sample_model(case)
    with common.scratch_dir("register-") as root:
        out = root / "reg"
        argv = [*common.heartreg_cli(), "register", model, case / "session", "-o", out, "-q"]
        runs = common.run_command(argv, repeats=n, before=lambda: shutil.rmtree(out, ignore_errors=True))
        import json

        result = json.loads((out / "registration.json").read_text())
        n_files = sum(1 for p in out.rglob("*") if p.is_file())
    timings = ", ".join(f"{k} {v:.2f}" for k, v in result.get("timings_s", {}).items())
    rows.append(common.Row(
        step=f"heartreg register (sample phantom case, {result['n_points']} points, {result['n_faces']} faces)",
        ours=runs,
        notes=(f"whole CLI process (start-up, reading the session, both sweeps of {len(result['respiration_sweep']['phases'])} "
               f"phases, static comparison, {n_files} output files incl. plots and the 3-D view); "
               f"stage times of the last run (s): {timings}"),
        command="heartreg register " + " ".join(str(a) for a in argv[2:]).replace(str(common.REPO_DIR) + "/", ""),
    ))


if __name__ == "__main__":
    sys.exit(main())
