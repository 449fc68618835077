"""Property-based tests of every command's argument parsing: any command
line gives exit 0, 1 or 2 (argparse's own usage errors are 2), one error
line and no traceback, within a time and a memory bound.

The argument lists are drawn from each command's own parser (every option
it declares), with values from a pool of real small files, missing or
unwritable paths and hostile numbers. They run in-process through
``napari_imgreg.cli.main(argv)``; the heavy work is stubbed (registration
returns the prior at once, the sample generator writes nothing, ``demo``
uses a tiny scene), so what is tested is the validation of the inputs.
"""

from __future__ import annotations

import atexit
import shutil
import argparse
import contextlib
import io
import json
import os
import stat
import tempfile
from pathlib import Path
from unittest import mock

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from PIL import Image

from hypothesis_bounds import SUITE, call_bounded, nasty_numbers

pytestmark = pytest.mark.filterwarnings("ignore")

_TMP = Path(tempfile.mkdtemp(prefix="imgreg-hypothesis-cli-"))
atexit.register(shutil.rmtree, _TMP, True)  # the scratch folder goes with the run
W, H = 64, 48


def _make_files() -> dict[str, list[str]]:
    """Small real inputs, and paths that are wrong in every way a user finds."""
    from napari_imgreg.camera import Intrinsics, Pose
    from napari_imgreg.geo import DEM

    t = _TMP
    scene = t / "scene"
    scene.mkdir()
    obj = "v -50 10 -20\nv 50 10 -20\nv 50 10 20\nv -50 10 20\nf 1 2 3\nf 1 3 4\n"
    (t / "wall.obj").write_text(obj)
    (scene / "wall.obj").write_text(obj)
    rng = np.random.default_rng(0)
    for folder in (t, scene):
        Image.fromarray(rng.integers(0, 255, (H, W, 3), dtype=np.uint8)).save(folder / "p.jpg")
    record = {"camera": {"width": W, "height": H, "fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5},
              "position": {"x": 0.0, "y": -30.0, "z": 0.0},
              "orientation": {"trend_deg": 0.0, "plunge_deg": 0.0, "roll_deg": 0.0}}
    for folder in (t, scene):
        (folder / "p.json").write_text(json.dumps(record))
    intr = Intrinsics(W, H, 60.0, 60.0, 31.5, 23.5)
    pose = Pose.from_attitude(0.0, 0.0, 0.0, [0.0, -30.0, 0.0])
    (t / "RESULT.json").write_text(json.dumps({
        "status": "registered", "photo": "p.jpg", "camera": intr.to_dict(),
        "pose": pose.to_dict(), "metrics": {}, "quality": {"Q": 0.5, "grade": "good"},
        "trials": [], "timings_s": {"total": 0.1}}))
    (t / "lines.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "LineString",
                                         "coordinates": [[10, 20], [40, 25]]},
         "properties": {"label": "bed"}}]}))
    (t / "lines3d.geojson").write_text(json.dumps({"type": "FeatureCollection", "features": [
        {"type": "Feature", "geometry": {"type": "LineString", "coordinates": [
            [0, 10, 0], [5, 10, 1], [10, 10, 3]]}, "properties": {"label": "bed"}}]}))
    (t / "params.json").write_text(json.dumps({"max_trials": 1}))
    (t / "bad_params.json").write_text(json.dumps({"max_trials": 0}))
    (t / "georef.json").write_text(json.dumps({"crs": "EPSG:32632",
                                               "origin": [500000.0, 5000000.0, 0.0]}))
    (t / "table.csv").write_text("photo,trend_deg,plunge_deg,roll_deg\n"
                                 "a.jpg,10,5,0\nb.jpg,100,-5,2\nc.jpg,200,0,1\n")
    (t / "table2.csv").write_text("photo,trend_deg,plunge_deg,roll_deg\n"
                                  "a.jpg,12,5,0\nb.jpg,102,-5,2\nc.jpg,202,0,1\n")
    DEM.from_array(np.zeros((4, 4)), 499990.0, 5000020.0, 10.0, 10.0,
                   crs="EPSG:32632").save_asc(t / "dem.asc") if hasattr(DEM, "save_asc") else \
        (t / "dem.asc").write_text("ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n"
                                   "0 0\n0 0\n")
    (t / "empty.json").write_text("")
    (t / "note.txt").write_text("not an input")
    ro = t / "readonly"
    ro.mkdir()
    ro.chmod(stat.S_IRUSR | stat.S_IXUSR)
    inputs = [str(t / n) for n in ("wall.obj", "p.jpg", "p.json", "RESULT.json", "lines.geojson",
                                    "lines3d.geojson", "params.json", "bad_params.json",
                                    "georef.json", "table.csv", "table2.csv", "dem.asc",
                                    "empty.json", "note.txt")]
    inputs += [str(scene), str(t / "missing.json"), str(t), "/proc/nope", "",
               str(WORKSPACE), "p.jpg", "IMG_0001.jpg"]
    outputs = [str(t / "out" / n) for n in ("o.json", "o.png", "o.npy", "o.geojson", "o.csv",
                                            "o.obj", "o.ply", "o.gpkg", "o.txt", "dir")]
    outputs += [str(ro / "o.json"), str(t / "note.txt" / "o.json"), "/proc/o.json", str(t),
                str(t / "out")]
    return {"inputs": inputs, "outputs": outputs}


#: A real workspace (the tiny scene, one photo) that the ``workspace``
#: sub-commands find in the pool; each run gets a fresh copy of PRISTINE, so
#: one example's changes do not leak into the next (hypothesis replays them).
WORKSPACE = _TMP / "ws.imgreg"
PRISTINE = _TMP / "pristine.imgreg"
#: Where ``workspace create`` is pointed half the time (removed before each run).
NEW_WORKSPACE = _TMP / "new.imgreg"
FILES = _make_files()


def _make_demo_scene() -> Path:
    """A tiny stand-in for the sample scene ``demo`` registers: a textured
    wall, a DEM, one photo with its record and ground truth."""
    import trimesh

    from napari_imgreg.geo import DEM

    folder = _TMP / "demo_scene"
    folder.mkdir()
    texture = np.zeros((8, 16, 3), np.uint8)
    texture[..., 0] = np.linspace(0, 255, 16)[None, :]
    mesh = trimesh.Trimesh(
        [[-50, 10, -20], [50, 10, -20], [50, 10, 20], [-50, 10, 20]], [[0, 1, 2], [0, 2, 3]],
        process=False, visual=trimesh.visual.TextureVisuals(
            uv=[[0, 0], [1, 0], [1, 1], [0, 1]], image=Image.fromarray(texture)))
    mesh.export(folder / "outcrop.obj")
    DEM.from_array(np.full((4, 4), -5.0), -60.0, 60.0, 40.0, 40.0).save_geotiff(folder / "dem.tif")
    shutil.copy(_TMP / "p.jpg", folder / "IMG_0001.jpg")
    shutil.copy(_TMP / "p.json", folder / "IMG_0001.json")
    result = json.loads((_TMP / "RESULT.json").read_text())
    (folder / "IMG_0001.truth.json").write_text(json.dumps(
        {"photo": "IMG_0001.jpg", "camera": result["camera"], "pose": result["pose"]}))
    return folder


DEMO_SCENE = _make_demo_scene()


def _commands() -> dict[str, list[argparse.Action]]:
    """Each command's options; a command with sub-commands (``workspace``)
    also gives one entry per sub-command ("workspace create", ...)."""
    from napari_imgreg.cli import build_parser

    def subparsers(parser):
        return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)),
                    None)

    commands = {}
    for name, p in subparsers(build_parser()).choices.items():
        commands[name] = [a for a in p._actions if not isinstance(a, argparse._HelpAction)]
        nested = subparsers(p)
        for sub_name, q in (nested.choices.items() if nested else ()):
            commands[f"{name} {sub_name}"] = [a for a in q._actions
                                              if not isinstance(a, argparse._HelpAction)]
    return commands


COMMANDS = _commands()
#: Options never drawn: --gui opens a napari window (tested in tests/widgets).
SKIP_OPTIONS = {"--gui"}

_numbers = nasty_numbers.map(lambda v: repr(v) if isinstance(v, float) else str(v))
_value = st.one_of(st.sampled_from(FILES["inputs"]), st.sampled_from(FILES["outputs"]), _numbers,
                   st.text(max_size=8).filter(lambda s: "\x00" not in s),
                   st.sampled_from(["small", "large", "color", "depth", "0", "-1", "nan", "1e9"]))


def _half(likely):
    """``likely`` half the time, any value otherwise."""
    return st.booleans().flatmap(lambda yes: likely if yes else _value)


def _value_for(action: argparse.Action):
    name = (action.option_strings or [action.dest])[-1]
    # The workspace sub-commands get past "not a workspace" half the time
    # (a coin, not one_of, which would flatten into _value's many branches).
    if action.metavar == "WORKSPACE":
        new = "new folder" in (action.help or "")  # create's, not an existing one
        return _half(st.just(str(NEW_WORKSPACE if new else WORKSPACE)))
    if action.metavar == "SCENE_DIR" and action.dest == "scene":  # workspace create's
        return _half(st.just(str(DEMO_SCENE)))
    if action.metavar in ("PHOTO_NAME", "NAME"):
        return _half(st.sampled_from(["IMG_0001.jpg", "IMG_0002.jpg"]))
    if action.dest == "photos":  # workspace add's
        return _half(st.just(str(_TMP / "p.jpg")))
    if action.dest == "lines":
        return _half(st.just(str(_TMP / "lines.geojson")))
    if action.choices:
        return st.one_of(st.sampled_from([str(c) for c in action.choices]), _value)
    if name in ("--out", "--mesh-out", "--plots", "--render-out", "--overlay") or "out" in name:
        return st.one_of(st.sampled_from(FILES["outputs"]), _value)
    if action.type in (int, float):
        return st.one_of(_numbers, _value)
    return st.one_of(st.sampled_from(FILES["inputs"]), _value)


@st.composite
def command_lines(draw, command: str) -> list[str]:
    actions = COMMANDS[command]
    argv = command.split()
    for action in actions:
        if any(o in SKIP_OPTIONS for o in action.option_strings):
            continue
        required = not action.option_strings or action.required
        if not required and not draw(st.booleans()):
            continue
        if required and draw(st.integers(0, 30)) == 0:
            continue  # a missing required argument now and then
        if action.option_strings:
            flag = draw(st.sampled_from(action.option_strings))
            if action.nargs == 0:
                argv.append(flag)
                continue
            argv.append(flag)
        n = action.nargs if isinstance(action.nargs, int) else (
            draw(st.integers(1, 2)) if action.nargs in ("+", "*", argparse.REMAINDER) else 1)
        argv += [draw(_value_for(action)) for _ in range(n)]
    return argv


def _stubs():
    """Stand-ins for the heavy work, so each command line runs in milliseconds."""
    from napari_imgreg.registration import pipeline

    def register(scene, image, prior, params=None, photo_name="", on_progress=None, **kw):
        return pipeline.Registration(
            status="failed", photo=photo_name, intrinsics=prior.intrinsics, pose=prior.pose,
            prior=prior, metrics={"reprojection_error_px": float("nan")}, q=-float("inf"),
            grade="failed", hints=["stub"], trials=[], timings_s={"total": 0.0})

    def generate_outcrop(out_dir, size="small", seed=0, spec=None):
        Path(out_dir).mkdir(parents=True, exist_ok=True)
        return Path(out_dir)

    patches = [mock.patch.object(pipeline, "register", register),
               mock.patch("napari_imgreg.sample.generate_outcrop", generate_outcrop),
               mock.patch("napari_imgreg.sample.sample_scene", lambda *a, **k: DEMO_SCENE),
               # `sample --out` would copy the real cached scene for every example.
               mock.patch("napari_imgreg.sample.cached_sample_scene", lambda *a, **k: None)]
    # batch on a local Dask cluster would register in worker processes, out of
    # the stubs' reach and the time bound: a local run stays in this process
    # (clusters are tested in tests/test_distributed.py; --scheduler is still fuzzed).
    from napari_imgreg.registration import batch as dask_batch

    patches.append(mock.patch.object(dask_batch.ClusterParams, "in_process",
                                     property(lambda self: self.scheduler is None)))
    # Each mesh is parsed once (the real Scene.load, errors included), then reused.
    import importlib

    for name in ("_common", "register", "render", "batch", "project", "demo", "measure",
                 "interpret"):
        try:
            module = importlib.import_module(f"napari_imgreg.cli.{name}")
        except ImportError:  # a command not (or no longer) there
            continue
        if hasattr(module, "load_scene"):
            patches.append(mock.patch.object(module, "load_scene", _cached_load_scene))
    # One parser for every example: building it costs ~10 ms (argparse looks up
    # gettext catalogues for each help text), more than most examples' run;
    # parse_args leaves a parser as it was, so reusing it tests the same thing.
    import napari_imgreg.cli as cli

    if not _PARSER:
        _PARSER.append(cli.build_parser())
    patches.append(mock.patch.object(cli, "build_parser", lambda: _PARSER[0]))
    return patches


_PARSER: list = []


_SCENES: dict = {}


def _cached_load_scene(mesh, georef=None, dem=None):
    from napari_imgreg.scene import Scene

    key = (str(mesh), str(georef), str(dem))
    if key not in _SCENES:
        _SCENES[key] = Scene.load(mesh, georef=georef, dem=dem)
    return _SCENES[key]


def _make_workspace() -> None:
    """PRISTINE: a workspace of the tiny scene and its photo, made by the
    command itself (so the suite follows its format). ``workspace register``
    runs the real stepwise registration (not stubbed): its parameters keep
    that to one short trial, so 500 examples stay within the CI budget."""
    params = _TMP / "fast_params.json"
    params.write_text(json.dumps({"sun_relight": False, "area_match": False,
                                  "edge_align": False, "dense_refine": False,
                                  "max_trials": 1}))
    code, err = _run(["workspace", "create", str(PRISTINE), str(DEMO_SCENE),
                      "--params", str(params)], fresh=False)
    assert code == 0 and (PRISTINE / "workspace.json").is_file(), err


def _warm_up() -> None:
    """Import what the commands import lazily, outside the time bound."""
    import napari_imgreg.interpret.files  # noqa: F401
    import napari_imgreg.interpret.project  # noqa: F401
    import napari_imgreg.orient  # noqa: F401
    import napari_imgreg.registration.pipeline  # noqa: F401
    import napari_imgreg.render  # noqa: F401

    for argv in (["register", FILES["inputs"][0], str(_TMP / "p.jpg"), "--out",
                  str(_TMP / "out" / "warm.json")],
                 ["render", FILES["inputs"][0], str(_TMP / "RESULT.json"), "--out",
                  str(_TMP / "out" / "warm.png")]):
        _run(argv)


_WARM: list = []


def _run(argv: list[str], fresh: bool = True) -> tuple[int, str]:
    from napari_imgreg.cli import main

    # Only a command line that may touch the pool's workspace pays for the copy.
    touches = argv[:1] == ["workspace"] or any(str(WORKSPACE) in a for a in argv)
    if fresh and touches and PRISTINE.is_dir():
        shutil.rmtree(NEW_WORKSPACE, ignore_errors=True)
        shutil.rmtree(WORKSPACE, ignore_errors=True)
        shutil.copytree(PRISTINE, WORKSPACE)

    err = io.StringIO()
    with contextlib.ExitStack() as stack:
        for patch in _stubs():
            stack.enter_context(patch)
        stack.enter_context(contextlib.redirect_stdout(io.StringIO()))
        stack.enter_context(contextlib.redirect_stderr(err))
        cwd = os.getcwd()
        os.chdir(_TMP)  # relative outputs land in the scratch folder
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse: --help/--version (0) or a usage error (2)
            code = exc.code if isinstance(exc.code, int) else 2
        finally:
            os.chdir(cwd)
    return code, err.getvalue()


def _check(argv: list[str]) -> None:
    if not _WARM:
        _make_workspace()
        _WARM.append(_warm_up())
    code, stderr = call_bounded(_run, argv)
    assert code in (0, 1, 2), (argv, code, stderr)
    assert "Traceback" not in stderr, (argv, stderr)
    if code == 2:
        assert stderr.strip(), argv  # said why
        lines = [ln for ln in stderr.strip().splitlines() if "error:" in ln]
        assert len(lines) == 1, (argv, stderr)


#: Every command and every ``workspace`` sub-command: the stubs keep each run
#: fast enough for the CI budget (``demo`` registers the tiny DEMO_SCENE).
_FAST = sorted(COMMANDS)


@pytest.mark.parametrize("command", _FAST)
@SUITE
@given(data=st.data())
def test_command_line(command, data):
    argv = data.draw(command_lines(command), label="argv")
    _check(argv)


def test_register_with_an_empty_photo_name_is_one_clear_error():
    """Found by the suite above: it was a ValueError traceback."""
    _check(["register", FILES["inputs"][0], ""])


def test_batch_with_a_file_as_scheduler_is_one_clear_error():
    """Found by the suite above: a ValueError traceback from Dask's client."""
    _check(["batch", str(_TMP / "scene"), "--out", str(_TMP / "out" / "o.json"),
            "--scheduler", FILES["inputs"][0]])


@SUITE
@given(st.lists(st.one_of(st.sampled_from(sorted(COMMANDS) + ["--help", "--version", "-v"]),
                          _value), max_size=4))
def test_any_words(argv):
    _check([a for a in argv if a not in SKIP_OPTIONS])


def test_command_options_are_all_reachable():
    """The drawn command lines cover every declared option of every command."""
    for command, actions in COMMANDS.items():
        assert actions, command
        for action in actions:
            assert action.option_strings or action.dest, command
    # The workspace sub-commands are drawn with their own options.
    assert {"workspace create", "workspace add", "workspace register", "workspace lines",
            "workspace project", "workspace export", "workspace info"} <= set(COMMANDS)


def test_the_pool_workspace_is_fresh_for_each_run():
    """One example's ``workspace add`` does not leak into the next one."""
    _check(["workspace", "info", str(WORKSPACE)])
    before = (WORKSPACE / "workspace.json").read_text()
    code, _ = _run(["workspace", "add", str(WORKSPACE), str(_TMP / "p.jpg")])
    assert code in (0, 1, 2)
    _run(["workspace", "info", str(WORKSPACE)])
    assert (WORKSPACE / "workspace.json").read_text() == before
