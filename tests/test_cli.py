"""The ``elastic-jax`` command line: the files it promises, numbers equal to the library's,
exit codes for bad input and non-convergence, and Ctrl-C that leaves only complete files."""

import json
import pathlib
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
import trimesh

import elastic_jax as ej
from elastic_jax import cli, io, shapes

from .conftest import COMPILATION_CACHE

M, N = 13, 25
METRIC = ej.SplitMetric(1.0, 1.0, 0.1, 0.0)
# The session's compilation cache (conftest): subprocesses and in-process checks share it.
# --no-export: the subprocesses then compile the very programs the in-process checks do
# (an exported program compiles as a program of its own); test_demo... runs with export.
CACHE = ["--cache-dir", str(COMPILATION_CACHE), "--no-export"]
SMALL = ["--grid", str(M), str(N), "--degree", "3", "--times", "5", "--quiet", *CACHE]
# Shape commands: the configuration of tests/test_karcher.py (one compilation for both).
SHAPE = ["--grid", str(M), str(N), "--degree", "4", "--vf-degree", "4", "--times", "5"]
SHAPE += ["--quiet", *CACHE]
SHAPE_OPTIONS = ej.ShapeOptions(degree=4, vf_degree=4, n_times=5, rtol=None)


def _no_temporaries(directory):
    return [p.name for p in directory.rglob("*") if p.name.startswith(".")]


def _save(tmp_path, name, f):
    return str(io.save_surface(np.asarray(f), tmp_path / name))


def test_demo_writes_what_it_promises_and_matches_the_library(tmp_path):
    out, cache = tmp_path / "demo", tmp_path / "cache"
    small = SMALL[: -len(CACHE)]
    argv = [sys.executable, "-m", "elastic_jax", "demo", *small, "--cache-dir", str(cache)]
    runs = [
        subprocess.run([*argv, "--out", str(d)], capture_output=True, text=True, timeout=300)
        for d in (out, tmp_path / "again")
    ]
    assert [r.returncode for r in runs] == [0, 0], runs[0].stderr
    summary, again = (json.loads(r.stdout) for r in runs)
    # The second run reads the compiled solve from the persistent cache: same numbers.
    assert len(list(cache.rglob("*"))) >= 1
    assert again["distance"] == summary["distance"] and again["num_steps"] == summary["num_steps"]
    assert summary == json.loads((out / "summary.json").read_text())
    assert all(pathlib.Path(name).is_file() for name in summary["files"])
    names = {p.relative_to(out).as_posix() for p in out.rglob("*") if p.is_file()}
    assert {"summary.json", "path.png", "path/path.npz", "straight_cylinder.npz"} <= names
    assert sum(n.startswith("path/frame_") for n in names) == 5
    f1 = shapes.sample(shapes.bent_cylinder, M, N, curvature=0.0)
    f2 = shapes.sample(shapes.bent_cylinder, M, N, curvature=0.6, half_length=1.2)
    res = ej.geodesic(f1, f2, METRIC, degree=3, n_times=5)
    assert summary["distance"] == pytest.approx(float(res.distance), rel=1e-9)
    assert summary["converged"] is True
    np.testing.assert_allclose(np.load(out / "path" / "path.npz")["path"], res.path, atol=1e-9)
    assert _no_temporaries(out) == []


def test_geodesic_between_files_equals_the_library_call(tmp_path, capsys):
    # Concentric spheres from a mesh file and a grid file: the closed form sqrt(8 pi b)|r2 - r1|.
    f1 = shapes.sample(shapes.sphere, M, N, radius=1.0)
    f2 = shapes.sample(shapes.sphere, M, N, radius=2.0)
    a, b = _save(tmp_path, "a.npz", f1), _save(tmp_path, "b.npz", f2)
    code = cli.main(["geodesic", a, b, *SMALL, "--out", str(tmp_path / "out")])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0
    res = ej.geodesic(f1, f2, METRIC, degree=3, n_times=5)
    assert summary["distance"] == pytest.approx(float(res.distance), rel=1e-12)
    assert summary["distance"] == pytest.approx(np.sqrt(8 * np.pi), rel=2e-2)


def test_bad_input_and_non_convergence_have_their_own_exit_codes(tmp_path, capsys):
    good = _save(tmp_path, "good.npz", shapes.sample(shapes.sphere, M, N))
    bad = np.array(shapes.sample(shapes.sphere, M, N))
    bad[0, 5, 5] = np.nan
    nan_file = str(tmp_path / "nan.npz")
    np.savez(nan_file, f=bad)  # not through save_surface, which refuses it
    torus = str(tmp_path / "torus.ply")
    trimesh.creation.torus(1.0, 0.3).export(torus)
    garbage = str(tmp_path / "garbage.ply")
    pathlib.Path(garbage).write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\n")
    out = str(tmp_path / "out")
    cases = {  # argv, a word the one-line message must contain
        "missing": (["geodesic", good, str(tmp_path / "absent.npz")], "absent.npz"),
        "nan": (["geodesic", good, nan_file], "nan.npz"),
        "genus": (["geodesic", good, torus], "genus"),
        "degree": (["geodesic", good, good, "--degree", "40"], "--degree 40"),
        "metric": (["geodesic", good, good, "--metric", "1,-1,0,0"], "negative"),
        "garbage": (["geodesic", good, garbage], "garbage.ply"),
    }
    for key, (argv, word) in cases.items():
        code = cli.main([*argv, "--grid", str(M), str(N), "--quiet", "--no-cache", "--out", out])
        err = capsys.readouterr().err
        assert code == cli.EXIT_BAD_INPUT, key
        assert "bad input" in err and word in err, (key, err)
        assert len(err.strip().splitlines()) == 1, key
    assert not pathlib.Path(out).exists()  # refused before any work or file
    code = cli.main(["geodesic", good, good, "--grid", str(M), "24", "--no-cache", "--out", out])
    assert code == cli.EXIT_BAD_INPUT and "n must be odd" in capsys.readouterr().err
    # A step limit of 2: the files are written, the exit code says "not converged".
    f2 = _save(tmp_path, "big.npz", shapes.sample(shapes.bumpy, M, N))
    code = cli.main(["geodesic", good, f2, *SMALL, "--max-steps", "2", "--out", out])
    summary = json.loads(capsys.readouterr().out)
    assert code == cli.EXIT_NOT_CONVERGED
    assert summary["converged"] is False and summary["num_steps"] == 2


def test_bad_shape_options_exit_2_naming_the_flag_before_any_file(tmp_path, capsys):
    good = _save(tmp_path, "good.npz", shapes.sample(shapes.sphere, M, N))
    velocity, wrong = str(tmp_path / "v.npz"), str(tmp_path / "wrong.npz")
    np.savez(velocity, v=np.zeros((3, M, N)))
    np.savez(wrong, v=np.zeros((3, 9, 17)))
    partial = str(tmp_path / "mean.npz")  # a karcher output that lost its settings
    np.savez(partial, f=np.zeros((3, M, N)), velocities=np.zeros((2, 3, M, N)))
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "readme.txt").write_text("no surfaces here")
    out = tmp_path / "out"
    cases = {  # argv, what the one-line message must contain
        "times": (["shape-geodesic", good, good, "--times", "2"], "--times 2"),
        "rtol": (["shape-geodesic", good, good, "--rtol", "-0.1"], "--rtol -0.1"),
        "rtol text": (["shape-geodesic", good, good, "--rtol", "abc"], "--rtol abc"),
        "max-steps": (["karcher", good, good, "--max-steps", "0"], "--max-steps 0"),
        "outer-steps": (["distances", good, good, "--outer-steps", "-1"], "--outer-steps -1"),
        "vf-degree": (["distances", good, good, "--vf-degree", "30"], "--vf-degree 30"),
        "karcher-steps": (["karcher", good, good, "--karcher-steps", "-1"], "--karcher-steps"),
        "tol": (["karcher", good, good, "--tol", "0"], "--tol"),
        "step-size": (["karcher", good, good, "--step-size", "nan"], "--step-size"),
        "batch-size": (["distances", good, good, "--batch-size", "0"], "--batch-size"),
        "batch-size -1": (["karcher", good, good, "--batch-size", "-1"], "--batch-size"),
        "one file karcher": (["karcher", good], "at least 2"),
        "one file distances": (["distances", good], "at least 2"),
        "repeat -1": (["bench", "--repeat", "-1"], "--repeat"),
        "repeat 0": (["bench", "--repeat", "0"], "--repeat"),
        "geodesic max-steps": (["geodesic", good, good, "--max-steps", "0"], "--max-steps"),
        "geodesic times": (["geodesic", good, good, "--times", "2"], "--times"),
        "pca one file": (["pca", good], "at least 2"),
        "pca partial output": (["pca", partial], "karcher output without distances"),
        "folder without surfaces": (["karcher", str(empty), good], "suffixes found: txt"),
        "pca modes": (["pca", good, good, "--modes", "0"], "--modes"),
        "pca sigmas": (["pca", good, good, "--sigmas", "-1"], "--sigmas"),
        "pca mode-times": (["pca", good, good, "--mode-times", "2"], "--mode-times"),
        "pca central": (["pca", good, good, "--scheme", "central"], "central"),
        "shoot scale": (["shoot", good, velocity, "--scale", "nan"], "--scale"),
        "shoot tol": (["shoot", good, velocity, "--tol", "0"], "--tol"),
        "shoot max-newton": (["shoot", good, velocity, "--max-newton", "0"], "--max-newton"),
        "shoot times": (["shoot", good, velocity, "--times", "2"], "--times"),
        "shoot no file": (["shoot", good, str(tmp_path / "absent.npz")], "absent.npz"),
        "shoot no v": (["shoot", good, good], "no array v"),
        "shoot shape": (["shoot", good, wrong], "shape (3, 9, 17)"),
        "workers": (["distances", good, good, "--workers", "0"], "--workers"),
        "level-candidates": (
            ["shape-geodesic", good, good, "--level-candidates", "0"],
            "--level-candidates 0",
        ),
        "search-smoothing order": (
            ["distances", good, good, "--search-smoothing", "0.5,1"],
            "--search-smoothing (0.5, 1.0)",
        ),
        "search-smoothing text": (["karcher", good, good, "--search-smoothing", "a,b"], "a,b"),
        "alternations": (["distances", good, good, "--alternations", "-1"], "--alternations -1"),
        "warmup times": (["warmup", "--times", "2"], "--times 2"),
        "warmup rtol": (["warmup", "--rtol", "abc"], "--rtol abc"),
        "warmup vf-degree": (["warmup", "--vf-degree", "30"], "--vf-degree 30"),
        "warmup without a cache": (["warmup"], "--no-cache leaves none"),
    }
    for key, (argv, word) in cases.items():
        code = cli.main(
            [*argv, "--grid", str(M), str(N), "--quiet", "--no-cache", "--out", str(out)]
        )
        err = capsys.readouterr().err
        assert code == cli.EXIT_BAD_INPUT, key
        assert "bad input" in err and word in err, (key, err)
        assert len(err.strip().splitlines()) == 1, key
    assert not out.exists()


def test_out_checkpoints_and_locks_are_checked_before_any_work(tmp_path, capsys, monkeypatch):
    from elastic_jax.cli import karcher as _karcher

    good = _save(tmp_path, "good.npz", shapes.sample(shapes.sphere, M, N))
    other = _save(tmp_path, "other.npz", shapes.sample(shapes.sphere, M, N, radius=2.0))
    truncated = tmp_path / "truncated.npz"
    truncated.write_bytes(pathlib.Path(good).read_bytes()[:200])
    a_file = tmp_path / "a_file"
    a_file.write_text("not a directory")
    foreign, corrupt, held, fresh = (tmp_path / d for d in ("foreign", "corrupt", "held", "new"))
    for d in (foreign, corrupt, held):
        d.mkdir()
    np.savez(foreign / "karcher_checkpoint.npz", fingerprint="written by other inputs")
    (corrupt / "distances_checkpoint.npz").write_bytes(b"PK\x03\x04 cut short")
    stale = fresh / ".summary.json.tmp-k2j4x9ab.json"  # a killed run's temporary
    fresh.mkdir()
    stale.write_text("{")
    (fresh / ".keep").write_text("the user's")
    collection = ["karcher", good, other, *SHAPE]
    cases = {  # argv, --out, what the one-line message must contain
        "out is a file": (["geodesic", good, other, *SMALL], a_file, "not a directory"),
        "checkpoint of other inputs": ([*collection, "--resume"], foreign, "other shapes"),
        "checkpoint kept without --resume": (collection, foreign, "--overwrite"),
        "corrupt checkpoint": (
            ["distances", good, other, *SHAPE, "--resume"],
            corrupt,
            "cannot be read",
        ),
        "truncated input": (["geodesic", good, str(truncated), *SMALL], fresh, "truncated.npz"),
    }
    before = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file() and p != stale}
    for key, (argv, out, word) in cases.items():
        code = cli.main([*argv, "--out", str(out)])
        err = capsys.readouterr().err
        assert code == cli.EXIT_BAD_INPUT, (key, err)
        assert "bad input" in err and word in err, (key, err)
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, key
    # Nothing written or discarded; the killed run's temporary swept, the user's file kept.
    after = {p: p.read_bytes() for p in tmp_path.rglob("*") if p.is_file()}
    assert after == before and not stale.exists()
    # A second run on a directory that a first run holds is refused (advisory lock).
    from elastic_jax.cli.process import _locked

    with _locked(held / cli.LOCK_NAME):
        code = cli.main([*collection, "--out", str(held)])
    assert code == cli.EXIT_BAD_INPUT and "another elastic-jax run" in capsys.readouterr().err
    # --overwrite discards the checkpoint explicitly; the run then goes on.
    monkeypatch.setattr(_karcher, "karcher_mean", _fake_karcher([]))
    code = cli.main([*collection, "--out", str(foreign), "--overwrite"])
    assert code == cli.EXIT_OK and json.loads(capsys.readouterr().out)["num_steps"] == 1


def _signal_at_first_checkpoint(argv, out, signum) -> tuple[int, str]:
    """Run the command line in a child, send ``signum`` as soon as its first checkpoint
    exists; its exit code and stderr.

    A shell running the suite in the background hands its children SIGINT ignored, and
    Python then installs no KeyboardInterrupt handler: the child restores what a terminal
    gives before it runs the command line.
    """
    child = (
        "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
        "from elastic_jax.cli import main; raise SystemExit(main(sys.argv[1:]))"
    )
    run = subprocess.Popen(
        [sys.executable, "-c", child, *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    checkpoint = out / "distances_checkpoint.npz"
    deadline = time.monotonic() + 240
    while not checkpoint.exists() and run.poll() is None and time.monotonic() < deadline:
        time.sleep(0.02)
    run.send_signal(signum)
    _, err = run.communicate(timeout=60)
    return run.returncode, err


def test_sigterm_is_handled_like_ctrl_c(tmp_path):
    fs = [shapes.sample(shapes.sphere, M, N, radius=r) for r in (1.0, 1.5, 2.0)]
    files = [_save(tmp_path, f"s{i}.npz", f) for i, f in enumerate(fs)]
    out = tmp_path / "out"
    # One working grid: the signal's handling does not depend on how a pair is solved.
    argv = ["distances", *files, *SHAPE, "--rtol", "none", "--strategy", "loop"]
    argv += ["--batch-size", "1", "--out", str(out)]
    code, err = _signal_at_first_checkpoint(argv, out, signal.SIGTERM)
    assert code == cli.EXIT_TERMINATED == 143, err
    assert "terminated" in err and "Traceback" not in err
    assert sorted(p.name for p in out.iterdir()) == ["distances_checkpoint.npz"]


def test_a_signal_python_drops_still_stops_the_command(tmp_path, capsys, monkeypatch):
    # Python runs a handler wherever the main thread is, a __del__ or a garbage collector's
    # callback included, and there it prints the exception and drops it.
    files = [_save(tmp_path, f"s{i}.npz", shapes.sample(shapes.sphere, M, N)) for i in range(2)]
    out = tmp_path / "out"
    reached = []

    class SignalledWhileCollected:
        def __del__(self):
            signal.raise_signal(signal.SIGTERM)

    def command(args, progress):
        SignalledWhileCollected()
        reached.append("after the dropped exception")
        progress("the next stage")
        reached.append("the next stage")
        return {"converged": True}

    monkeypatch.setitem(cli.COMMANDS, "distances", command)
    before = signal.getsignal(signal.SIGTERM), sys.unraisablehook
    code = cli.main(["distances", *files, *SHAPE, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == cli.EXIT_TERMINATED and reached == ["after the dropped exception"]
    assert "terminated" in err and "Traceback" not in err and "ignored" not in err
    assert not (out / "summary.json").exists()
    # The handler and the unraisable hook are the caller's again.
    assert (signal.getsignal(signal.SIGTERM), sys.unraisablehook) == before


def test_a_nan_solve_exits_3_with_valid_json(tmp_path, capsys, monkeypatch):
    from elastic_jax.cli import geodesic as _geodesic

    def nan_geodesic(f1, f2, metric, **options):
        nan = np.float64(np.nan)
        return ej.GeodesicResult(
            path=np.full((options["n_times"], *np.shape(f1)), np.nan),
            distance=nan,
            energy=nan,
            straight_energy=nan,
            coefficients=np.zeros((options["n_times"] - 2, 3)),
            num_steps=np.int32(4),
            converged=np.bool_(False),
            result=ej.RESULTS.nonfinite,
            grad_norm=nan,
            min_curvature=nan,
        )

    monkeypatch.setattr(_geodesic, "geodesic", nan_geodesic)
    a = _save(tmp_path, "a.npz", shapes.sample(shapes.sphere, M, N))
    out = tmp_path / "out"
    code = cli.main(["geodesic", a, a, *SMALL, "--out", str(out)])
    captured = capsys.readouterr()
    assert code == cli.EXIT_NOT_CONVERGED, captured.err
    summary = json.loads((out / "summary.json").read_text())  # valid JSON: no NaN token
    assert summary["distance"] is None and summary["num_steps"] == 4
    assert summary["converged"] is False and "Nonfinite" in summary["message"]
    assert [pathlib.Path(f).name for f in summary["files"]] == ["summary.json"]


def _fake_karcher(calls):
    def karcher_mean(shapes, metric, **kwargs):
        calls.append(kwargs)
        k = shapes.shape[0]
        # A resolved mean's first solves report their levels; a phase is not a line.
        level = {"level": 2, "levels": 4, "grid": (25, 49), "energy": 0.5, "step": 0}
        level.update({"shape": 1, "shapes": k, "seconds": 12.3})
        kwargs["job"].progress({**level, "stage": "registration rounds"})
        kwargs["job"].progress({**level, "stage": "level", "distance": 0.25, "converged": True})
        return ej.KarcherResult(
            mean=shapes[0],
            distances=np.zeros(k),
            registered=shapes,
            velocities=np.zeros_like(shapes),
            geodesics_converged=np.ones(k, bool),
            geodesics_resolution_limited=np.zeros(k, bool),
            history=np.array([[2.0, 0.5, 0.0], [1.0, 1e-6, 0.5]]),
            converged=True,
            num_steps=1,
            num_solves=3,
            result=ej.RESULTS.mean_velocity_small,
            level_distances=None,
        )

    return karcher_mean


def test_karcher_builds_one_options_record_and_keeps_its_own_steps(tmp_path, capsys, monkeypatch):
    from elastic_jax.cli import karcher as _karcher

    calls = []
    monkeypatch.setattr(_karcher, "karcher_mean", _fake_karcher(calls))
    files = [_save(tmp_path, f"s{i}.npz", shapes.sample(shapes.sphere, M, N)) for i in range(2)]
    argv = ["karcher", *files, *SHAPE, "--max-steps", "7", "--karcher-steps", "3"]
    argv += ["--scheme", "forward", "--tol", "0.01", "--warm-start", "--out", str(tmp_path / "out")]
    # Without --quiet: the progress lines.
    assert cli.main([*[a for a in argv if a != "--quiet"], "--rtol", "none"]) == 0
    captured = capsys.readouterr()
    summary = json.loads(captured.out)
    (kwargs,) = calls
    assert kwargs["warm_start"] is True and summary["settings"]["warm_start"] is True
    assert kwargs["options"] == SHAPE_OPTIONS.replace(max_steps=7, scheme="forward")
    assert (kwargs["max_steps"], kwargs["tol"], kwargs["step_size"]) == (3, 0.01, 1.0)
    assert summary["history"]["step_size"] == [0.0, 0.5]
    assert summary["result"] == "mean_velocity_small" and summary["num_solves"] == 3
    assert summary["message"].startswith("converged")
    lines = [line for line in captured.err.splitlines() if "first solves" in line]
    assert [line.split("] ")[1] for line in lines] == [
        "first solves, shape 2/2: level 2/4 (25 x 49) distance 0.25 (converged), 12 s"
    ]
    # Without --rtol the library's default: a resolved mean (levels), as karcher_mean's.
    assert cli.main([*argv, "--overwrite"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert calls[1]["options"].rtol == ej.ShapeOptions().rtol == summary["settings"]["rtol"]
    assert summary["settings"]["input_grid"] == summary["settings"]["grid"] == [M, N]


def test_distances_reports_each_pair_and_exits_3_when_one_did_not_converge(
    tmp_path, capsys, monkeypatch
):
    from elastic_jax.cli import distances as _distances

    seen = []

    def distance_matrix(shapes, metric, **kwargs):
        seen.append(kwargs)
        converged = np.ones((3, 3), bool)
        converged[0, 2] = converged[2, 0] = False
        change = np.full((3, 3), 0.01)
        np.fill_diagonal(change, 0.0)
        change[1, 2] = change[2, 1] = np.nan
        return ej.DistanceMatrixResult(
            np.ones((3, 3)) - np.eye(3),
            converged,
            change,
            estimate=np.full((3, 3), np.nan),
            grids=np.zeros((3, 3, 2), np.int32),
            spread=np.full((3, 3), np.nan),
            converged=np.asarray(False),
            result=ej.RESULTS.nonlinear_max_steps_reached,
            num_steps=np.asarray(30),
        )

    monkeypatch.setattr(_distances, "distance_matrix", distance_matrix)
    files = [_save(tmp_path, f"s{i}.npz", shapes.sample(shapes.sphere, M, N)) for i in range(3)]
    out = tmp_path / "out"
    candidates = ["--level-candidates", "2", "--both-orders", "--search-smoothing", "1,0.5"]
    candidates += ["--alternations", "2"]
    argv = ["distances", *files, *SHAPE, *candidates, "--out", str(out)]
    assert cli.main(argv) == cli.EXIT_NOT_CONVERGED
    summary = json.loads(capsys.readouterr().out)
    # The candidates' flags reach the library's record, beside the shape flags.
    (kwargs,) = seen
    assert kwargs["options"] == SHAPE_OPTIONS.replace(
        rtol=ej.ShapeOptions().rtol,
        level_candidates=2,
        both_orders=True,
        search_smoothing=(1.0, 0.5),
        alternations=2,
    )
    assert summary["converged"] is False
    assert summary["pairs_converged"][0] == [True, True, False]
    assert summary["refinement_change"][1] == [0.01, 0.0, None]  # NaN: not computed
    saved = np.load(out / "distances.npz")
    assert not saved["converged"][2, 0] and np.isnan(saved["refinement_change"][2, 1])


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::elastic_jax.ConvergenceWarning")
def test_ctrl_c_then_resume_equals_the_library(tmp_path, capsys):
    fs = [
        shapes.sample(shapes.ellipsoid, M, N, axes=axes)
        for axes in [(1.0, 0.8, 0.6), (1.2, 0.7, 0.6), (0.9, 0.9, 0.5), (1.0, 1.0, 0.4)]
    ]
    files = [_save(tmp_path, f"s{i}.npz", f) for i, f in enumerate(fs)]
    out = tmp_path / "out"
    # One working grid, as SHAPE_OPTIONS (the library's call below) asks.
    argv = ["distances", *files, *SHAPE, "--rtol", "none", "--strategy", "loop"]
    argv += ["--batch-size", "1"]
    # On a local Dask cluster: its workers load the solve from the session's cache.
    argv += ["--workers", "2", "--out", str(out)]
    # A real SIGINT (Ctrl-C) as soon as the first pair's checkpoint exists: 5 pairs remain.
    code, err = _signal_at_first_checkpoint(argv, out, signal.SIGINT)
    checkpoint = out / "distances_checkpoint.npz"
    assert code == cli.EXIT_INTERRUPTED, err
    assert "interrupted" in err
    assert sorted(p.name for p in out.iterdir()) == ["distances_checkpoint.npz"]
    assert 1 <= int(np.load(checkpoint)["done"].sum()) < 6

    code = cli.main([*argv, "--resume"])
    summary = json.loads(capsys.readouterr().out)
    expected = ej.distance_matrix(
        np.stack(fs),
        METRIC,
        modulo="rigid",
        options=SHAPE_OPTIONS,
        job=ej.JobOptions(strategy="loop"),
    )
    converged = np.asarray(expected.pairs_converged)
    assert code == (0 if converged.all() else cli.EXIT_NOT_CONVERGED)
    assert summary["converged"] is bool(converged.all())
    assert summary["pairs_converged"] == converged.tolist()
    np.testing.assert_allclose(summary["distances"], expected.distances, rtol=1e-9)
    np.testing.assert_allclose(summary["refinement_change"], expected.refinement_change, rtol=1e-9)
    saved = np.load(out / "distances.npz")
    np.testing.assert_allclose(saved["distances"], expected.distances, rtol=1e-9)
    np.testing.assert_array_equal(saved["converged"], converged)
    assert (out / "distances.png").exists() and (out / "distances.csv").exists()
    assert _no_temporaries(out) == []
    assert (out / "summary.json").stat().st_mode & 0o044  # not private, unlike mkstemp's


@pytest.mark.slow
@pytest.mark.filterwarnings("ignore::elastic_jax.ConvergenceWarning")
def test_karcher_and_shape_geodesic_equal_the_library(tmp_path, capsys):
    """karcher on a folder, then pca on its mean.npz (no solve again), and shape-geodesic:
    the library's numbers."""
    fs = [
        shapes.sample(shapes.ellipsoid, M, N, axes=axes, rotation=shapes.random_rotation(i))
        for i, axes in enumerate([(1.0, 0.8, 0.6), (1.2, 0.7, 0.6), (0.9, 0.9, 0.5)])
    ]
    folder = tmp_path / "collection"
    folder.mkdir()
    files = [_save(folder, f"s{i}.npz", f) for i, f in enumerate(fs)]
    (folder / "notes.txt").write_text("not a surface: left out")
    out = tmp_path / "karcher"
    # --max-steps (the inner solves', here their default) beside --karcher-steps: it
    # raised a TypeError when both reached karcher_mean as max_steps.
    argv = ["karcher", str(folder), *SHAPE, "--karcher-steps", "2", "--max-steps", "500"]
    argv += ["--rtol", "none"]
    argv += ["--strategy", "loop", "--out", str(out)]
    code = cli.main(argv)
    summary = json.loads(capsys.readouterr().out)
    res = ej.karcher_mean(
        np.stack(fs),
        METRIC,
        modulo="rigid",
        max_steps=2,
        options=SHAPE_OPTIONS,
        job=ej.JobOptions(strategy="loop"),
    )
    assert code == (0 if res.converged else cli.EXIT_NOT_CONVERGED)
    assert summary["converged"] is bool(res.converged) and summary["result"] == ej.RESULTS.name(
        res.result
    )
    assert summary["history"]["sum_sq_distances"] == res.history[:, 0].tolist()
    assert summary["settings"]["max_steps"] == 500 and summary["settings"]["karcher_steps"] == 2
    np.testing.assert_allclose(summary["distances"], res.distances, rtol=1e-9)
    np.testing.assert_allclose(np.load(out / "mean.npz")["f"], res.mean, atol=1e-9)
    assert {"mean.ply", "mean.png", "history.png", "summary.json"} <= {
        p.name for p in out.iterdir()
    }
    assert summary["inputs"] == files

    # pca on the karcher run's output: that mean, its velocities and settings, no solve.
    saved = out / "mean.npz"
    code = cli.main(["pca", str(saved), "--metric", "1,1,1,0", "--quiet", *CACHE])
    assert code == cli.EXIT_BAD_INPUT and "leave out --metric" in capsys.readouterr().err
    pca_out = tmp_path / "pca"
    argv = ["pca", str(saved), "--mode-times", "3", "--quiet", *CACHE, "--out", str(pca_out)]
    code = cli.main(argv)
    summary = json.loads(capsys.readouterr().out)
    pca = ej.tangent_pca(res, METRIC)
    assert pca.modes.shape[0] == 2 and summary["settings"]["modes"] == 2
    assert summary["karcher_inputs"] == files and summary["karcher_result"] == ej.RESULTS.name(
        res.result
    )
    np.testing.assert_allclose(summary["pca"]["explained"], pca.explained, rtol=1e-8)
    np.testing.assert_allclose(np.load(pca_out / "pca.npz")["scores"], pca.scores, atol=1e-8)
    assert set(json.loads((pca_out / "scores.json").read_text())["scores"]) == {"s0", "s1", "s2"}
    assert summary["pca"]["mode_paths_reached_sigmas"] == [[-2.0, 2.0], [-2.0, 2.0]]
    path = ej.mode_path(pca, 0, METRIC, n_times=3, degree=4, sigmas=2.0)
    np.testing.assert_allclose(np.load(pca_out / "pca.npz")["mode_paths"][0], path, atol=1e-8)

    out = tmp_path / "shape"
    argv = ["shape-geodesic", files[0], files[1], *SHAPE, "--rtol", "none", "--out", str(out)]
    code = cli.main(argv)
    summary = json.loads(capsys.readouterr().out)
    assert summary["levels"] is None and summary["settings"]["grid"] == [M, N]
    res = ej.shape_geodesic(fs[0], fs[1], METRIC, modulo="diff", options=SHAPE_OPTIONS)
    assert code == (0 if bool(res.converged) else cli.EXIT_NOT_CONVERGED)
    assert summary["distance"] == pytest.approx(float(res.distance), rel=1e-9)
    assert summary["distance"] < summary["parametrized_distance"]
    assert summary["rounds"] == int(res.rounds) and summary["grad_norm"] == float(res.grad_norm)
    assert summary["result"] == ej.RESULTS.name(res.result) and summary["message"] == res.message
    assert summary["message"] == res.message
    refinement = summary["refinement"]
    assert refinement["relative_change"] == float(res.refinement.relative_change)
    assert refinement["distance_time"] == float(res.refinement.distance_time)
    np.testing.assert_allclose(np.load(out / "registration.npz")["gamma"], res.gamma, atol=1e-9)
    # Where the energy lies, beside the meshes: the written path's energy by point and term.
    written = np.load(out / "path" / "path.npz")["path"]
    fields = np.load(out / "energy_density.npz")
    energy = float(ej.path_energy(METRIC, written))
    assert float(fields["total"].sum()) == pytest.approx(energy, rel=1e-10)
    terms = summary["energy_terms"]
    parts = sum(terms[k] for k in ("shear", "area", "bending", "rotation"))
    assert parts == pytest.approx(terms["total"], rel=1e-12)
    assert terms["total"] == pytest.approx(energy, rel=1e-10)
    ply = trimesh.load(out / "energy_density.ply", process=False)
    total = ply.metadata["_ply_raw"]["vertex"]["data"]["total"]
    np.testing.assert_array_equal(total[1:-1], fields["total"][1:-1, :-1].reshape(-1))
    assert (out / "energy_density.png").is_file()


def test_bench_reports_the_library_distance(capsys, tmp_path):
    argv = ["bench", *SMALL, "--repeat", "1", "--out", str(tmp_path)]
    assert cli.main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    f1 = shapes.sample(shapes.bent_cylinder, M, N, curvature=0.0)
    f2 = shapes.sample(shapes.bent_cylinder, M, N, curvature=0.6, half_length=1.2)
    res = ej.geodesic(f1, f2, METRIC, degree=3, n_times=5)
    solve = summary["geodesic_solve"]
    assert solve["distance"] == pytest.approx(float(res.distance), rel=1e-12)
    assert solve["num_steps"] == int(res.num_steps)
    assert len(solve["runs_s"]) == 1 and summary["settings"]["grid"] == [M, N]


def test_pca_and_shoot_equal_the_library_and_compose(tmp_path, capsys, monkeypatch):
    """pca on a collection whose velocities at the mean span two known directions (the
    Karcher part, tested above, replaced by a record): its modes, scores and mode paths
    are the library's; shoot from its mean with its mode velocity lands where mode_path
    does."""
    from elastic_jax.cli import karcher as _karcher

    mean = np.asarray(shapes.sample(shapes.ellipsoid, M, N, axes=(1.0, 0.8, 0.6)))
    x, y, z = mean
    stretch = np.stack([x, -0.5 * y, -0.5 * z])
    squash = np.stack([0 * x, y, -z])
    a, b = np.array([0.3, -0.1, 0.2, -0.4]), np.array([0.1, 0.2, -0.2, -0.1])
    velocities = 0.5 * (a[:, None, None, None] * stretch + b[:, None, None, None] * squash)

    def karcher_mean(collection, metric, **kwargs):
        k = collection.shape[0]
        return ej.KarcherResult(
            mean=mean,
            distances=np.ones(k),
            registered=collection,
            velocities=velocities,
            geodesics_converged=np.ones(k, bool),
            geodesics_resolution_limited=np.zeros(k, bool),
            history=np.array([[4.0, 1e-9, 0.0]]),
            converged=True,
            num_steps=0,
            num_solves=1,
            result=ej.RESULTS.mean_velocity_small,
            level_distances=None,
        )

    monkeypatch.setattr(_karcher, "karcher_mean", karcher_mean)
    files = [_save(tmp_path, f"s{i}.npz", shapes.sample(shapes.sphere, M, N)) for i in range(4)]
    out = tmp_path / "pca"
    # Degree 3 and N = 5 for the mode paths and the shot: tests/test_shooting.py's loop.
    shooting = ["--grid", str(M), str(N), "--degree", "3", "--quiet", *CACHE]
    argv = ["pca", *files, *shooting, "--modes", "3", "--mode-times", "5", "--out", str(out)]
    assert cli.main(argv) == 0
    summary = json.loads(capsys.readouterr().out)

    pca = ej.tangent_pca((mean, velocities), METRIC)
    assert pca.modes.shape[0] == 2  # rank 2: a third mode asked for is not there
    assert summary["settings"]["modes"] == 2
    written = {pathlib.Path(f).name for f in summary["files"]}
    assert {"modes.png", "mode2_minus.ply", "mode2_velocity.npz", "scores.json"} <= written
    np.testing.assert_allclose(summary["pca"]["explained"], pca.explained, rtol=1e-12)
    saved = np.load(out / "pca.npz")
    np.testing.assert_allclose(saved["modes"], pca.modes, atol=1e-12)
    centred = velocities - velocities.mean(axis=0)
    rebuilt = np.einsum("ik,k...->i...", saved["scores"], saved["modes"])
    assert np.max(np.abs(rebuilt - centred)) <= 1e-10 * np.max(np.abs(centred))
    scores = json.loads((out / "scores.json").read_text())
    assert scores["scores"]["s2"] == pytest.approx(np.asarray(pca.scores[2]).tolist(), rel=1e-12)
    # All the variance is in the two modes: their sum is the centred velocities' mean G-norm^2.
    norms2 = [float(ej.metric_inner(METRIC, mean, w, w)) for w in centred]
    assert summary["pca"]["total_variance"] == pytest.approx(np.mean(norms2), rel=1e-10)

    options = {"n_times": 5, "degree": 3, "sigmas": 2.0}
    path = np.asarray(ej.mode_path(pca, 0, METRIC, **options))
    np.testing.assert_allclose(saved["mode_paths"][0], path, atol=1e-9)
    plus = trimesh.load(out / "mode1_plus.ply", process=False).vertices
    assert np.max(np.abs(plus - io.grid_to_mesh(path[-1]).vertices)) < 1e-6

    shot = tmp_path / "shoot"
    argv = ["shoot", str(out / "mean.npz"), str(out / "mode1_velocity.npz"), "--scale", "2"]
    argv += ["--degree", "3", "--times", "5", "--quiet", *CACHE, "--out", str(shot)]
    assert cli.main(argv) == 0
    summary = json.loads(capsys.readouterr().out)
    endpoint = np.load(shot / "shoot.npz")["endpoint"]
    np.testing.assert_array_equal(np.load(shot / "path" / "path.npz")["path"][-1], endpoint)
    assert np.max(np.abs(endpoint - path[-1])) <= 1e-9 * np.max(np.abs(path[-1]))
    # The shot's length is the initial velocity's G-norm, 2 sigma_1, to first order in 1/N.
    sigma = float(np.sqrt(pca.variances[0]))
    assert summary["length"] == pytest.approx(2 * sigma, rel=0.05)
    assert summary["converged"] is True and len(summary["speeds"]) == 4


def test_fit_metric_equals_the_library_and_scores_the_held_out_files(tmp_path, capsys):
    """fit-metric over files with a labels file (name,label lines) and a held-out split:
    the coefficients are fit_metric's, the held-out scores retrieval_scores' of
    distance_matrix at the start and the fitted metric."""
    kinds = [(0.1, 1.0), (0.1, 1.4), (0.5, 1.0), (0.5, 1.4), (0.12, 1.2), (0.45, 1.2)]
    f = [shapes.sample(shapes.bent_cylinder, M, N, curvature=k, half_length=h) for k, h in kinds]
    files = [_save(tmp_path, f"s{i}.npz", x) for i, x in enumerate(f)]
    labels = ["straight", "straight", "bent", "bent", "straight", "bent"]
    # name,label lines in another order than the files.
    (tmp_path / "labels.csv").write_text("".join(f"s{i},{labels[i]}\n" for i in (3, 1, 0, 2)))
    test_labels = [labels[i] for i in (0, 2, 4, 5)]
    (tmp_path / "test.txt").write_text("\n".join(test_labels) + "\n")
    argv = ["fit-metric", *files[:4], "--labels", str(tmp_path / "labels.csv"), "--modulo"]
    argv += ["none", "--strategy", "loop", "--test", files[0], files[2], files[4], files[5]]
    argv += ["--test-labels", str(tmp_path / "test.txt"), *SMALL, "--out", str(tmp_path / "o")]
    code = cli.main(argv)
    summary = json.loads(capsys.readouterr().out)
    assert code == 0, summary["message"]
    small = {
        "modulo": "none",
        "options": ej.ShapeOptions(degree=3, n_times=5),
        "job": ej.JobOptions(strategy="loop"),
    }
    fit = ej.fit_metric(np.stack(f[:4]), labels[:4], **small)
    got = [summary["metric"][c] for c in "abcd"]
    np.testing.assert_allclose(got, [getattr(fit.metric, c) for c in "abcd"], rtol=1e-9)
    held = np.stack([f[0], f[2], f[4], f[5]])
    for name, metric in (("before", fit.initial_metric), ("after", fit.metric)):
        d = ej.distance_matrix(held, metric, **small)
        assert summary["held_out_scores"][name] == pytest.approx(
            ej.retrieval_scores(d.distances, test_labels)._asdict()
        )
    saved = np.load(tmp_path / "o" / "fit_metric.npz")
    np.testing.assert_allclose(saved["distances"], fit.distances, rtol=1e-9)


@pytest.mark.parametrize(
    "extra, words",
    [
        (["--labels", "L", "--learn", "c"], "learn must name at least two"),
        (["--labels", "missing.txt"], "--labels missing.txt: no such file"),
        (["--labels", "L", "--temperature", "0"], "--temperature"),
        (["--labels", "L", "--test", "A"], "--test and --test-labels go together"),
    ],
)
def test_fit_metric_refuses_bad_options_before_any_work(tmp_path, capsys, extra, words):
    files = [_save(tmp_path, f"s{i}.npz", shapes.sample(shapes.sphere, M, N)) for i in range(3)]
    (tmp_path / "L").write_text("a\na\nb\n")
    extra = [str(tmp_path / x) if x in ("L", "A") else x for x in extra]
    out = tmp_path / "out"
    code = cli.main(["fit-metric", *files, *extra, *SMALL, "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert words in err and len(err.strip().splitlines()) == 1, err
    assert not out.exists()


def test_mesh_files_are_read_in_the_frame_asked_for(tmp_path):
    from elastic_jax.cli.common import _load_all

    # bumpy is star-shaped about its centroid and asymmetric: radial projection in a
    # principal frame that differs from the file's axes.
    f = np.asarray(shapes.sample(shapes.bumpy, 13, 25))
    mesh_file = io.save_surface(f, tmp_path / "b.off")
    grid_file = io.save_surface(f, tmp_path / "b.npz")
    files = [str(grid_file), str(mesh_file)]  # the first file's grid is the common one
    for frame in ("principal", "input"):
        got = _load_all(files, None, "float64", lambda line: None, frame)
        np.testing.assert_array_equal(got[0], f)  # a grid file keeps its parametrization
        np.testing.assert_array_equal(got[1], io.load_surface(mesh_file, 13, 25, frame=frame))
    # the default is the principal frame, another parametrization than the file's axes give
    principal = _load_all(files, None, "float64", lambda line: None)[1]
    np.testing.assert_array_equal(principal, io.load_surface(mesh_file, 13, 25))
    assert np.abs(principal - got[1]).max() > 1e-2
    with pytest.raises(SystemExit) as exit_:
        cli.main(["geodesic", *files, "--frame", "sideways"])
    assert exit_.value.code == 2


def test_the_version_is_one_number_everywhere(capsys):
    """--version prints the package's __version__, which is also the installed
    distribution's version (pyproject reads it from the package) and the one the citation
    files give."""
    import re
    from importlib import metadata

    with pytest.raises(SystemExit) as stopped:
        cli.main(["--version"])
    assert stopped.value.code == 0
    assert capsys.readouterr().out.strip() == f"elastic-jax {ej.__version__}"
    assert metadata.version("elastic-jax") == ej.__version__
    root = pathlib.Path(__file__).resolve().parents[1]
    cff = (root / "CITATION.cff").read_text()
    assert re.search(r'^version: "([^"]+)"$', cff, re.M).group(1) == ej.__version__
    bibtex = (root / "docs" / "citing.md").read_text()
    assert re.search(r"version = \{([^}]+)\}", bibtex).group(1) == ej.__version__


@pytest.mark.parametrize("metric", [["--metric", "-1,1,0.1,0"], ["--metric=-1,1,0.1,0"]])
def test_a_negative_metric_coefficient_gets_the_metrics_own_error(capsys, metric):
    # Before any file is read (the files named here do not exist), as the metric's own
    # one-line message, not argparse's "expected one argument" for a value that starts
    # with "-".
    code = cli.main(["shape-geodesic", "missing1.ply", "missing2.ply", *metric, "--no-cache"])
    assert code == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "coefficient a=-1.0 is negative" in err and "missing" not in err
    assert len(err.strip().splitlines()) == 1


def test_the_degree_error_comes_before_any_mesh_is_read(tmp_path, capsys):
    # With --grid the degrees are checked against it before the meshes are mapped to the
    # sphere (seconds to minutes each): the log shows no file read.
    mesh = trimesh.creation.icosphere(subdivisions=2)
    files = [str(mesh.export(tmp_path / name) and tmp_path / name) for name in ("a.ply", "b.ply")]
    code = cli.main(["shape-geodesic", *files, "--grid", "9", "17", "--degree", "12"])
    assert code == cli.EXIT_BAD_INPUT
    err = capsys.readouterr().err
    assert "--degree 12" in err and "reading" not in err


def _ellipsoid_and_its_sphere(tmp_path, name: str, scale: float):
    """An ellipsoid meshed from an icosphere (.ply, float32 vertices, in the icosphere's
    order) and its map, the icosphere scaled by 100 (as FreeSurfer's spheres are)."""
    ico = trimesh.creation.icosphere(subdivisions=2)
    mesh = trimesh.Trimesh(ico.vertices * scale * np.array([1.0, 0.8, 0.6]), ico.faces)
    sphere = trimesh.Trimesh(100.0 * ico.vertices, ico.faces)
    paths = (tmp_path / f"{name}.ply", tmp_path / f"{name}_sphere.ply")
    mesh.export(paths[0])
    sphere.export(paths[1])
    return str(paths[0]), str(paths[1])


def test_sphere_files_must_match_the_inputs_before_any_work(tmp_path, capsys):
    a, sa = _ellipsoid_and_its_sphere(tmp_path, "a", 1.0)
    b, sb = _ellipsoid_and_its_sphere(tmp_path, "b", 1.5)
    grid = _save(tmp_path, "g.npz", shapes.sample(shapes.sphere, M, N))
    out = tmp_path / "out"
    cases = {
        "count": (["shape-geodesic", a, b, "--sphere", sa], "1 sphere file(s) for 2 input"),
        "grid": (["geodesic", a, grid, "--sphere", sa, sb], "g.npz is a grid file"),
        "missing": (["distances", a, b, "--sphere", sa, "nope.ply"], "--sphere nope.ply"),
        "target": (["shape-geodesic", a, grid, "--on-target-mesh"], "--on-target-mesh"),
    }
    for key, (argv, words) in cases.items():
        code = cli.main([*argv, "--no-cache", "--out", str(out)])
        err = capsys.readouterr().err
        assert code == cli.EXIT_BAD_INPUT, key
        assert words in err and "reading" not in err, (key, err)
        assert len(err.strip().splitlines()) == 1, key
    assert not out.exists()


def test_geodesic_through_sphere_files_reads_the_librarys_grids(tmp_path, capsys):
    a, sa = _ellipsoid_and_its_sphere(tmp_path, "a", 1.0)
    b, sb = _ellipsoid_and_its_sphere(tmp_path, "b", 1.5)
    out = tmp_path / "out"
    code = cli.main(["geodesic", a, b, *SMALL, "--sphere", sa, sb, "--out", str(out)])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0 and summary["settings"]["sphere"] == [sa, sb]
    path = np.load(out / "path" / "path.npz")["path"]
    np.testing.assert_array_equal(path[0], io.load_surface(a, M, N, sphere=sa))
    np.testing.assert_array_equal(path[-1], io.load_surface(b, M, N, sphere=sb))
    # the sphere map is not the one the command computes without it
    assert np.abs(path[0] - io.load_surface(a, M, N, frame="input")).max() > 1e-3


def test_normalize_area_compares_shapes_without_size(tmp_path, capsys):
    # Concentric spheres: sqrt(8 pi b) |r2 - r1| apart (math §9); normalized to area 4 pi
    # both are the unit sphere of the grid, 0 apart.
    f1 = shapes.sample(shapes.sphere, M, N, radius=1.0)
    f2 = shapes.sample(shapes.sphere, M, N, radius=2.0)
    a, b = _save(tmp_path, "a.npz", f1), _save(tmp_path, "b.npz", f2)
    out = tmp_path / "out"
    code = cli.main(["geodesic", a, b, *SMALL, "--normalize", "area", "--out", str(out)])
    summary = json.loads(capsys.readouterr().out)
    assert code == 0 and summary["settings"]["normalize"] == "area"
    assert summary["distance"] < 1e-12
    path = np.load(out / "path" / "path.npz")["path"]
    np.testing.assert_allclose(ej.surface_area(path[[0, -1]]), 4 * np.pi, rtol=1e-12)


@pytest.mark.slow  # 55 s on 2 cores
@pytest.mark.filterwarnings("ignore::elastic_jax.ConvergenceWarning")
def test_shape_geodesic_paints_its_path_on_the_target_mesh(tmp_path, capsys):
    a, sa = _ellipsoid_and_its_sphere(tmp_path, "a", 1.0)
    b, sb = _ellipsoid_and_its_sphere(tmp_path, "b", 1.5)
    out = tmp_path / "out"
    argv = ["shape-geodesic", a, b, *SHAPE, "--rtol", "none", "--outer-steps", "2"]
    code = cli.main([*argv, "--sphere", sa, sb, "--on-target-mesh", "--out", str(out)])
    summary = json.loads(capsys.readouterr().out)
    assert code in (0, cli.EXIT_NOT_CONVERGED)
    painted = sorted((out / "path").glob("target_mesh_*.ply"))
    assert len(painted) == 5 and all(str(p) in summary["files"] for p in painted)
    target = trimesh.load(b, process=False)
    last = trimesh.load(painted[-1], process=False)
    np.testing.assert_array_equal(last.faces, target.faces)
    # The path ends at the target's grid (modulo diff: no rotation), read back at its
    # vertices through the icosphere map: the vertices to the 13 x 25 grid's resolution
    # (4.2e-3 of the diagonal, measured).
    np.testing.assert_allclose(
        np.load(out / "path" / "path.npz")["path"][-1],
        io.load_surface(b, M, N, sphere=sb),
        rtol=0,
        atol=1e-14,
    )
    error = np.linalg.norm(last.vertices - target.vertices, axis=1).max()
    assert error / np.linalg.norm(np.ptp(target.vertices, axis=0)) < 1e-2
