"""Outputs that survive: strict JSON, fsync before and after the rename,
symlinked outputs followed, and SIGKILL/SIGTERM/closed stdout during a
write or a batch leaving every earlier result and the summary valid."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import re
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from napari_imgreg import _atomic
from napari_imgreg._atomic import atomic_write
from napari_imgreg._json import dump, dumps, strict_json
from napari_imgreg.cli import main
from napari_imgreg.cli._common import write_json

SRC = Path(__file__).resolve().parents[1] / "src"


def strict_load(text: str):
    """json.loads that refuses NaN/Infinity, as JavaScript or jq do."""

    def refuse(name):
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


# ------------------------------------------------------------ strict JSON
def test_strict_json_nulls_non_finite_numbers_and_says_why():
    data = {"Q": -math.inf, "metrics": {"err": math.nan, "n": np.int64(3)},
            "t": np.array([1.0, np.inf]), "ok": True, "s": "NaN", "big": 2**63}
    out = strict_json(data)
    assert out["Q"] is None and out["metrics"]["err"] is None and out["t"] == [1.0, None]
    assert out["metrics"]["n"] == 3 and type(out["metrics"]["n"]) is int
    assert out["ok"] is True and out["s"] == "NaN" and out["big"] == 2**63
    assert out["null_reasons"] == {
        "/Q": "infinite (-Infinity)", "/metrics/err": "not a number (NaN)",
        "/t/1": "infinite (+Infinity)",
    }
    strict_load(dumps(data))  # parses as standard JSON


def test_strict_json_leaves_clean_data_as_it_is_and_escapes_pointers():
    clean = {"a": [1, 2.5, None], "b": {"c": "x"}}
    assert strict_json(clean) == clean
    assert strict_json({"a/b": {"~": math.nan}})["null_reasons"] == {"/a~1b/~0": "not a number (NaN)"}
    assert strict_json([math.nan]) == [None]  # no place for reasons in a list
    assert strict_json({"x": math.nan}, reasons={"/x": "no pose"})["null_reasons"] == {
        "/x": "no pose (was not a number (NaN))"}


def test_dump_writes_what_json_dump_writes_at_once():
    """The text json.dump writes (made by json.dumps, whose C encoder is
    several times faster), in one write."""
    import io
    import json

    data = {"a": [1, 2.5, None, "é", {"b": np.float64(0.1), "c": math.inf}], "d": (True, 3)}
    for kwargs in ({}, {"indent": 1}, {"indent": 2, "ensure_ascii": False},
                   {"separators": (",", ":")}):
        expected = io.StringIO()
        json.dump(strict_json(data), expected, allow_nan=False, **kwargs)
        writes = []

        class Recording(io.StringIO):
            def write(self, text):
                writes.append(text)
                return super().write(text)

        got = Recording()
        dump(data, got, **kwargs)
        assert got.getvalue() == expected.getvalue() and len(writes) == 1


def test_strict_json_refuses_objects_with_their_place():
    with pytest.raises(TypeError, match="/a/0"):
        strict_json({"a": [object()]})


def test_write_json_is_strict(tmp_path):
    path = tmp_path / "r.json"
    write_json(path, {"q": float("nan"), "pose": {"t": [0.0, float("-inf"), 1.0]}})
    data = strict_load(path.read_text())
    assert data["q"] is None and data["pose"]["t"] == [0.0, None, 1.0]
    assert set(data["null_reasons"]) == {"/q", "/pose/t/1"}


def test_failed_registration_result_is_strict_json():
    from napari_imgreg.camera import Intrinsics, Pose
    from napari_imgreg.prior import Prior
    from napari_imgreg.registration.pipeline import Registration

    intr = Intrinsics(640, 480, 500.0, 500.0, 319.5, 239.5)
    pose = Pose.from_attitude(10.0, 5.0, 0.0, [0.0, -50.0, 2.0])
    prior = Prior(intrinsics=intr, pose=pose)
    reg = Registration(status="failed", photo="a.jpg", intrinsics=intr, pose=pose, prior=prior,
                       metrics={"reprojection_error_px": math.nan}, q=-math.inf, grade="failed",
                       hints=[], trials=[], timings_s={"total": 1.0})
    result = reg.to_dict()
    text = json.dumps(result, allow_nan=False)  # no NaN/Infinity anywhere
    back = strict_load(text)
    assert back["quality"]["Q"] is None and back["metrics"]["reprojection_error_px"] is None
    assert back["null_reasons"]["/quality/Q"] == "infinite (-Infinity)"


#: Writers in files being written by other developers when this test was
#: (their json.dump is to become napari_imgreg._json.dump): listed, not hidden.
_PENDING = {"napari_imgreg/sample/rough.py"}


def test_every_json_writer_of_the_package_is_strict():
    """No file writer calls json.dump (or writes json.dumps text) directly:
    all go through _json. (json.dumps of a single value embedded in another
    format, such as a CSV cell, is not a JSON file and is not checked here.)"""
    offenders = []
    for path in (SRC / "napari_imgreg").rglob("*.py"):
        if path.name == "_json.py" or path.relative_to(SRC).as_posix() in _PENDING:
            continue
        for n, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
            code = line.split("#", 1)[0]
            if re.search(r"\bjson\.dump\(|\.write(_text)?\(json\.dumps\(|= json\.dumps\(", code):
                offenders.append(f"{path.relative_to(SRC)}:{n}: {line.strip()}")
    assert not offenders, "\n".join(offenders)


def test_other_writers_write_strict_json(tmp_path):
    from napari_imgreg.geo import Georef
    from napari_imgreg.interpret.files import write_features_geojson  # noqa: F401 - importable
    from napari_imgreg.sample import _write_json

    _write_json(tmp_path / "s.json", {"a": np.float32("nan")})
    assert strict_load((tmp_path / "s.json").read_text())["a"] is None
    Georef("EPSG:32633", np.array([500000.0, 4649776.0, 0.0])).save(tmp_path / "georef.json")
    strict_load((tmp_path / "georef.json").read_text())


# ------------------------------------------------------------- fsync, links
def test_write_fsyncs_file_before_rename_and_folder_after(tmp_path, monkeypatch):
    events = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd):
        kind = "dir" if os.path.isdir(f"/proc/self/fd/{fd}") else "file"
        events.append(f"fsync {kind}")
        real_fsync(fd)

    def replace(a, b):
        events.append("rename")
        real_replace(a, b)

    monkeypatch.setattr(_atomic.os, "fsync", fsync)
    monkeypatch.setattr(_atomic.os, "replace", replace)
    with atomic_write(tmp_path / "a.json") as fh:
        fh.write("{}")
    assert events == ["fsync file", "rename", "fsync dir"]


def test_symlinked_output_is_followed_not_replaced(tmp_path):
    real = tmp_path / "store" / "result.json"
    real.parent.mkdir()
    real.write_text("old")
    link = tmp_path / "result.json"
    link.symlink_to(real)
    write_json(link, {"new": 1})
    assert link.is_symlink() and os.readlink(link) == str(real)
    assert json.loads(real.read_text()) == {"new": 1}
    # A chain of links and a dangling link: the final target is written.
    chain = tmp_path / "chain.json"
    chain.symlink_to(link.name)
    write_json(chain, {"newer": 2})
    assert chain.is_symlink() and json.loads(real.read_text()) == {"newer": 2}
    dangling = tmp_path / "later.json"
    dangling.symlink_to("store/later.json")
    write_json(dangling, [1])
    assert dangling.is_symlink() and json.loads((real.parent / "later.json").read_text()) == [1]
    assert not [p for p in tmp_path.rglob(".*")]  # no temporary left


def test_symlink_loop_is_an_os_error_not_a_hang(tmp_path):
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.symlink_to(b.name)
    b.symlink_to(a.name)
    with pytest.raises(OSError, match="symbolic links"):
        write_json(a, {})


# ------------------------------------------------------- fault injection
def _python(code: str, *args, **kwargs) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(SRC), "PYTHONHASHSEED": "0"}
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code), *map(str, args)],
                          env=env, capture_output=True, text=True, timeout=120, **kwargs)


def test_sigkill_between_temp_file_and_rename_keeps_the_old_file(tmp_path):
    path = tmp_path / "RESULT.json"
    write_json(path, {"status": "registered", "n": 1})
    proc = _python("""
        import os, signal, sys
        from napari_imgreg import _atomic
        from napari_imgreg.cli._common import write_json
        def killed(src, dst):  # the temp file is written and fsynced: die before the rename
            assert os.path.getsize(src) > 0
            os.kill(os.getpid(), signal.SIGKILL)
        _atomic.os.replace = killed
        write_json(sys.argv[1], {"status": "failed", "n": 2})
    """, path)
    assert proc.returncode == -signal.SIGKILL
    assert json.loads(path.read_text()) == {"status": "registered", "n": 1}
    # The temporary file is left (no process survived to remove it), hidden:
    # batch and --skip-existing never read dot files.
    leftovers = [p.name for p in tmp_path.iterdir() if p.name != "RESULT.json"]
    assert all(n.startswith(".RESULT.json.") for n in leftovers)


#: A runner for `batch` with registration stubbed: each photo "registers"
#: at once, except that photo number STALL waits (marking that it started)
#: until it is killed; KILL_AT_SUMMARY kills it inside the Nth summary.json rename.
BATCH_RUNNER = """
    import os, signal, sys, time
    from pathlib import Path
    from napari_imgreg.cli import main
    from napari_imgreg.registration import pipeline
    from napari_imgreg import _atomic

    stall = int(os.environ.get("STALL", "0"))
    kill_at = int(os.environ.get("KILL_AT_SUMMARY", "0"))
    marker = Path(os.environ["MARKER"])
    count = {"photo": 0, "summary": 0}

    def register(scene, image, prior, params=None, photo_name="", on_progress=None):
        count["photo"] += 1
        if count["photo"] == stall:
            marker.write_text(photo_name)
            while True:
                time.sleep(0.05)
        return pipeline.Registration(
            status="registered", photo=photo_name, intrinsics=prior.intrinsics, pose=prior.pose,
            prior=prior, metrics={"reprojection_error_px": float("nan")}, q=0.5, grade="good",
            hints=[], trials=[], timings_s={"total": 0.0})

    pipeline.register = register
    real_replace = _atomic.os.replace

    def replace(src, dst):
        if str(dst).endswith("summary.json"):
            count["summary"] += 1
            if count["summary"] == kill_at:
                os.kill(os.getpid(), signal.SIGKILL)
        real_replace(src, dst)

    _atomic.os.replace = replace
    sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture(scope="module")
def photo_scene(tmp_path_factory):
    """A scene folder: a small quad mesh and four sample photos with their records."""
    from napari_imgreg.sample import sample_scene

    src = sample_scene("small")
    folder = tmp_path_factory.mktemp("durable") / "scene"
    folder.mkdir()
    (folder / "wall.obj").write_text(
        "v -200 -300 -50\nv 200 -300 -50\nv 200 300 -50\nv -200 300 -50\nf 1 2 3\nf 1 3 4\n")
    for k in range(1, 4):
        for suffix in (".jpg", ".json"):
            shutil.copy2(src / f"IMG_{k:04d}{suffix}", folder / f"IMG_{k:04d}{suffix}")
    shutil.copy2(src / "IMG_0001.jpg", folder / "IMG_0004.jpg")
    shutil.copy2(src / "IMG_0001.json", folder / "IMG_0004.json")
    return folder


def _start_batch(scene, out, tmp_path, **env):
    marker = tmp_path / "started"
    full_env = {**os.environ, "PYTHONPATH": str(SRC), "MARKER": str(marker),
                **{k: str(v) for k, v in env.items()}}
    proc = subprocess.Popen(
        # --workers 0: in this process, where the stubbed registration is.
        [sys.executable, "-c", textwrap.dedent(BATCH_RUNNER), "batch", str(scene), "--out",
         str(out), "--workers", "0", *env.pop("EXTRA", ())],
        env=full_env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    return proc, marker


def _wait_for(marker, proc, timeout=90.0):
    t0 = time.monotonic()
    while not marker.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() - t0 < timeout, "the batch never reached the stalled photo"
        time.sleep(0.05)


def _check_valid(out, n_done):
    summary = strict_load((out / "summary.json").read_text())
    assert summary["n_done"] == n_done == len(summary["photos"])
    # summary.csv is written first and summary.json last: a kill between the two
    # leaves the CSV at most one photo ahead, each of its rows with its result.
    import csv

    with open(out / "summary.csv", newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) in (n_done, n_done + 1)
    assert [r["photo"] for r in rows[:n_done]] == [r["photo"] for r in summary["photos"]]
    for row in rows:
        assert (out / (Path(row["photo"]).stem + ".result.json")).is_file()
    for row in summary["photos"]:
        strict_load((out / row["result"]).read_text())
    results = sorted(p.name for p in out.glob("*.result.json"))
    for name in results:
        assert strict_load((out / name).read_text())["status"] == "registered"
    return summary, results


def test_sigkill_during_batch_keeps_earlier_results_and_summary(photo_scene, tmp_path):
    out = tmp_path / "results"
    proc, marker = _start_batch(photo_scene, out, tmp_path, STALL=3)
    _wait_for(marker, proc)
    proc.kill()
    proc.communicate(timeout=30)
    summary, results = _check_valid(out, 2)
    assert results == ["IMG_0001.result.json", "IMG_0002.result.json"]
    assert not summary["complete"]
    # ... and --skip-existing carries on from there.
    code = _start_batch(photo_scene, out, tmp_path, EXTRA=["--skip-existing"])[0]
    stdout, stderr = code.communicate(timeout=120)
    assert code.returncode == 0, stderr
    summary, results = _check_valid(out, 4)
    assert summary["complete"] and summary["counts"]["skipped"] == 2
    assert "Traceback" not in stderr


def test_sigkill_inside_the_summary_write_keeps_the_previous_summary(photo_scene, tmp_path):
    out = tmp_path / "results"
    # Summary writes: one per photo; die in the third (after photo 3's result).
    proc, _ = _start_batch(photo_scene, out, tmp_path, KILL_AT_SUMMARY=3)
    proc.communicate(timeout=120)
    assert proc.returncode == -signal.SIGKILL
    summary, results = _check_valid(out, 2)  # summary.json of photo 2, intact
    assert len(results) == 3  # photo 3's result was written before its summary


def test_sigterm_during_batch_is_handled_like_ctrl_c(photo_scene, tmp_path):
    out = tmp_path / "results"
    proc, marker = _start_batch(photo_scene, out, tmp_path, STALL=2)
    _wait_for(marker, proc)
    proc.send_signal(signal.SIGTERM)
    stdout, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 143, stderr
    assert "Traceback" not in stderr
    summary, results = _check_valid(out, 1)
    assert summary["interrupted"] is True and summary["signal"] == "SIGTERM"
    assert not summary["complete"]
    assert "--skip-existing" in stdout


def test_closed_stdout_after_a_successful_write(photo_scene, tmp_path):
    out = tmp_path / "results"
    read_end, write_end = os.pipe()
    os.close(read_end)  # nobody reads: every print is a broken pipe
    env = {**os.environ, "PYTHONPATH": str(SRC), "MARKER": str(tmp_path / "m")}
    try:
        proc = subprocess.run(
            [sys.executable, "-c", textwrap.dedent(BATCH_RUNNER), "batch", str(photo_scene),
             "--out", str(out), "--workers", "0"],
            env=env, stdout=write_end, stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write_end)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr and "BrokenPipe" not in proc.stderr
    summary, _ = _check_valid(out, 4)
    assert summary["complete"]


@pytest.mark.parametrize("body", [
    '{"status": "registered", "pose": "abc"}',
    '{"status": "registered", "pose": {"position": "xyz"}}',
    '{"status": "registered", "quality": [1, 2]}',
    '{"status": "registered", "trials": 3}',
    '{"status": 5}',
    '{"status": "registered", "pose": {"position": [1, 2]}}',
    '[1, 2, 3]',
    '{"status": "registered", "timings_s": "fast"}',
    '',
    '{"status": "regis',
])
def test_skip_existing_over_a_malformed_result_redoes_it(photo_scene, tmp_path, monkeypatch, body):
    from napari_imgreg.registration import pipeline

    def register(scene, image, prior, params=None, photo_name="", on_progress=None):
        return pipeline.Registration(
            status="registered", photo=photo_name, intrinsics=prior.intrinsics, pose=prior.pose,
            prior=prior, metrics={}, q=0.5, grade="good", hints=[], trials=[],
            timings_s={"total": 0.0})

    monkeypatch.setattr(pipeline, "register", register)
    out = tmp_path / "results"
    out.mkdir()
    (out / "IMG_0001.result.json").write_text(body)
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(["batch", str(photo_scene), "--out", str(out), "--skip-existing",
                     "--workers", "0"])
    assert code == 0, stderr.getvalue()
    assert "IMG_0001.jpg: existing result unreadable" in stdout.getvalue()
    assert "redoing it" in stdout.getvalue()
    assert strict_load((out / "IMG_0001.result.json").read_text())["status"] == "registered"


@pytest.mark.parametrize("where", ["inside_a_file", "proc"])
def test_batch_checks_its_output_folder_before_the_scene(photo_scene, tmp_path, monkeypatch,
                                                          where):
    import napari_imgreg.cli.batch as batch

    monkeypatch.setattr(batch, "load_scene", lambda *a, **k: pytest.fail("scene loaded"))
    (tmp_path / "note.txt").write_text("x")
    out = tmp_path / "note.txt" / "results" if where == "inside_a_file" else Path("/proc/results")
    stderr = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(stderr):
        code = main(["batch", str(photo_scene), "--out", str(out)])
    lines = stderr.getvalue().strip().splitlines()
    assert code == 2 and len(lines) == 1 and str(out) in lines[0] and "cannot write" in lines[0]
