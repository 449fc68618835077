"""RegistrationParams (params.py): dict/JSON round trip, partial files, errors, baseline."""

from __future__ import annotations

import json

import pytest

from napari_imgreg.errors import InputError
from napari_imgreg.registration.features import FeatureParams
from napari_imgreg.registration.filters import FilterParams
from napari_imgreg.registration.lidar_views import LidarViewParams
from napari_imgreg.registration.params import RegistrationParams, load_params
from napari_imgreg.registration.pose import PoseParams
from napari_imgreg.registration.stages.area import AreaParams
from napari_imgreg.registration.stages.dense import DenseParams
from napari_imgreg.registration.stages.edges import EdgeParams


def non_default() -> RegistrationParams:
    return RegistrationParams(
        photo_filters=FilterParams(gamma=1.8, wallis=True, wallis_window=61),
        render_filters=FilterParams(clahe=True, clahe_tiles=4, brightness=-5.0),
        features=FeatureParams("FAST", "SIFT", max_features=3000, threshold_scale=0.5,
                               grid=(6, 4), ratio=0.75, symmetric=False,
                               geometric_model="homography", geometric_threshold_px=4.5),
        pose=PoseParams(reprojection_error_px=9.0, iterations=800, confidence=0.99, refine=False),
        match_width=800, max_iterations=2, converged_deg=0.1, converged_m=0.2,
        auto_adapt=False, max_trials=2, search_prior=False, n_search=5, verify=False,
        sun_relight=False, edge_align=False, dense_refine=False, area_match=False,
        area=AreaParams(width=800, template_px=41, stride_px=20, min_score=0.3),
        edges=EdgeParams(levels=(256, 512, 1024), search_rotation_deg=(8.0, 4.0, 2.0), keep=2,
                         oriented=False, kind_weights={"albedo": 0.0, "skyline": 3.0}),
        dense=DenseParams(modes=("shaded", "normal"), levels=(128, 256), optimize_focal=True,
                          max_seconds=3.0, max_samples=50_000),
        lidar_views=True, lidar=LidarViewParams(hog_scales=(2.0, 6.0), use_lsd_mask=False),
    )


def test_dict_round_trip():
    p = non_default()
    d = p.to_dict()
    assert set(d) == {"photo_filters", "render_filters", "features", "pose", "match_width",
                      "max_iterations", "converged_deg", "converged_m", "auto_adapt",
                      "max_trials", "search_prior", "n_search", "verify",
                      "sun_relight", "edge_align", "dense_refine", "area_match", "area",
                      "edges", "dense", "uncertainty", "lidar_views", "lidar", "seed"}
    assert RegistrationParams.from_dict(d) == p
    assert RegistrationParams.from_dict(RegistrationParams().to_dict()) == RegistrationParams()


def test_json_round_trip(tmp_path):
    p = non_default()
    path = tmp_path / "params.json"
    path.write_text(json.dumps(p.to_dict()))  # to_dict is JSON-ready (grid as a list)
    assert json.loads(json.dumps(p.to_dict())) == p.to_dict()  # tuples as lists
    q = load_params(path)
    assert q == p and q.features.grid == (6, 4)
    assert q.edges.levels == (256, 512, 1024) and q.dense.modes == ("shaded", "normal")


def test_partial_dicts_keep_the_defaults():
    d = RegistrationParams()
    p = RegistrationParams.from_dict({"features": {"detector": "ORB", "descriptor": "ORB"},
                                      "pose": {"refine": False}, "max_trials": 7})
    assert (p.features.detector, p.features.descriptor) == ("ORB", "ORB")
    assert p.features.max_features == d.features.max_features
    assert p.features.ratio == d.features.ratio
    assert p.pose.refine is False
    assert p.pose.reprojection_error_px == d.pose.reprojection_error_px
    assert p.max_trials == 7
    assert p.photo_filters == d.photo_filters and p.render_filters == d.render_filters
    assert p.match_width == d.match_width and p.verify == d.verify
    assert RegistrationParams.from_dict({}) == d
    p = RegistrationParams.from_dict({"edges": {"keep": 5}, "dense": {"levels": [128, 256]}})
    assert p.edges == EdgeParams(keep=5)
    # The registration's MI time limit (6 s) stays when other MI fields are set.
    assert p.dense == DenseParams(levels=(128, 256), max_seconds=6.0)


def test_stage_settings_default_to_the_values_before_version_0_2():
    """EdgeParams and DenseParams hold what align_edges and refine_pose_mi took as
    keywords (same values); the registration stops MI after 6 s as it always did."""
    edges = {"levels": [320, 768], "search_rotation_deg": [12.0, 6.0, 4.0],
             "search_step_deg": 1.0, "keep": 3, "truncate_px": 40.0, "inlier_px": 4.0,
             "max_points": 3000, "max_rounds": 3, "oriented": True, "min_inlier_fraction": 0.3,
             "min_agreement": 0.25, "min_step_m": 0.6, "kind_weights": {}}
    dense = {"modes": None, "levels": [128, 256, 512], "bins": 32, "optimize_focal": False,
             "max_seconds": 10.0, "use_background": True, "blur_px": 1.0, "supersample": 2,
             "max_iterations": 25, "tol_px": 0.01, "rerender_px": 1.5,
             "max_renders_per_level": 3, "max_rotation_deg": 10.0, "max_samples": 120_000,
             "max_step_px": 2.0, "curvature": False, "full_pose_from": 0}
    assert EdgeParams().to_dict() == edges
    assert DenseParams().to_dict() == dense
    d = RegistrationParams()
    assert d.edges == EdgeParams()
    assert d.dense == DenseParams(max_seconds=6.0)
    for params in (EdgeParams(), DenseParams()):
        for name, (low, high) in params.RANGES.items():
            value = getattr(params, name)
            assert all(low <= v <= high for v in (value if isinstance(value, tuple) else (value,)))


def test_unknown_top_level_field_names_file_and_field(tmp_path):
    path = tmp_path / "my_params.json"
    path.write_text(json.dumps({"max_trails": 3}))
    with pytest.raises(InputError) as err:
        load_params(path)
    assert str(path) in str(err.value) and "max_trails" in str(err.value)


@pytest.mark.parametrize("section, field", [("features", "nfeatures"), ("pose", "threshold"),
                                            ("photo_filters", "gama"),
                                            ("render_filters", "wallis_size")])
def test_unknown_nested_field_names_file_section_and_field(tmp_path, section, field):
    path = tmp_path / "p.json"
    path.write_text(json.dumps({section: {field: 1}}))
    with pytest.raises(InputError) as err:
        load_params(path)
    msg = str(err.value)
    assert str(path) in msg and section in msg and field in msg


@pytest.mark.parametrize("data, words", [
    ({"features": {"detector": "SURF"}}, ["features", "SURF"]),
    ({"features": {"detector": "SIFT", "descriptor": "AKAZE"}}, ["features", "AKAZE"]),
    ({"features": 3}, ["features", "object"]),
    ({"pose": [1, 2]}, ["pose", "object"]),
    ({"area": {"template_px": 32}}, ["area", "odd"]),
    ({"area": {"stride": 8}}, ["area", "stride"]),
    ({"edges": {"levels": []}}, ["edges", "levels"]),
    ({"edges": {"keep": 0}}, ["edges", "keep", "[1, 20]"]),
    ({"edges": {"kind_weights": {"skyline": -1}}}, ["edges", "skyline"]),
    ({"edges": {"search_rotation": [1, 2, 3]}}, ["edges", "search_rotation"]),
    ({"dense": {"modes": ["colour"]}}, ["dense", "colour"]),
    ({"dense": {"max_seconds": -1}}, ["dense", "max_seconds"]),
    ({"dense": {"bins": 1024}}, ["dense", "bins"]),
    ({"dense": []}, ["dense", "object"]),
])
def test_invalid_nested_values_are_input_errors(data, words):
    with pytest.raises(InputError) as err:
        RegistrationParams.from_dict(data, "P.json")
    assert str(err.value).startswith("P.json: ")
    for w in words:
        assert w in str(err.value)


@pytest.mark.parametrize("data, field", [
    ({"max_trials": "four"}, "max_trials"),
    ({"auto_adapt": "yes"}, "auto_adapt"),
    ({"pose": {"reprojection_error_px": "six"}}, "reprojection_error_px"),
    ({"photo_filters": {"gamma": "x"}}, "gamma"),
    ({"features": {"grid": [8]}}, "grid"),
    ({"area": {"min_score": "high"}}, "min_score"),
    ({"edges": {"search_rotation_deg": [12, "six", 4]}}, "search_rotation_deg"),
    ({"edges": {"levels": [320.5]}}, "levels"),
    ({"edges": {"oriented": "yes"}}, "oriented"),
    ({"dense": {"levels": "128"}}, "levels"),
    ({"dense": {"curvature": 1}}, "curvature"),
    ({"dense": {"max_iterations": 2.5}}, "max_iterations"),
])
def test_ill_typed_fields_are_input_errors(data, field):
    with pytest.raises(InputError, match=field):
        RegistrationParams.from_dict(data, "P.json")


def test_load_params_bad_files(tmp_path):
    missing = tmp_path / "nope.json"
    with pytest.raises(InputError, match="nope.json"):
        load_params(missing)
    broken = tmp_path / "broken.json"
    broken.write_text("{ not json")
    with pytest.raises(InputError, match="broken.json"):
        load_params(broken)
    listed = tmp_path / "list.json"
    listed.write_text("[1, 2]")
    with pytest.raises(InputError, match="list.json.*object"):
        load_params(listed)


def test_copy_is_deep():
    p = RegistrationParams()
    q = p.copy()
    assert q == p
    q.features.ratio = 0.5
    q.photo_filters.wallis = not p.photo_filters.wallis
    q.render_filters.gamma = 3.0
    q.pose.reprojection_error_px = 33.0
    q.edges.kind_weights["albedo"] = 0.0
    q.dense.max_seconds = 1.0
    assert p == RegistrationParams()


def test_baseline_is_the_plain_pipeline():
    b = RegistrationParams.baseline()
    # SIFT detection and description with Lowe's ratio test ...
    assert (b.features.detector, b.features.descriptor) == ("SIFT", "SIFT")
    assert b.features.ratio < 1.0
    # ... no filters on either image ...
    assert b.photo_filters.is_identity and b.render_filters.is_identity
    # ... one render → match → pose round, one trial, no adaptation, no search,
    # no verification.
    assert b.max_iterations == 1
    assert b.max_trials == 1 and b.auto_adapt is False
    assert b.search_prior is False
    assert b.verify is False
    # ... and none of the illumination-robust stages.
    assert not (b.sun_relight or b.edge_align or b.dense_refine or b.area_match)
    # Each call is a fresh object.
    b.features.ratio = 0.5
    assert RegistrationParams.baseline().features.ratio != 0.5


def test_baseline_differs_from_the_default_pipeline():
    d, b = RegistrationParams(), RegistrationParams.baseline()
    assert d != b
    assert d.auto_adapt and d.search_prior and d.verify and d.max_iterations > 1
    assert d.sun_relight and d.edge_align and d.dense_refine and d.area_match


@pytest.mark.parametrize("cls", [FilterParams, FeatureParams, PoseParams, AreaParams, EdgeParams,
                                 DenseParams, LidarViewParams])
def test_each_stage_round_trips_through_json_with_its_own_error(cls):
    """The shared StageParams base: plain JSON types out (no tuples), the same
    object back, and an unknown key named with the stage's kind."""
    d = cls().to_dict()
    assert json.loads(json.dumps(d)) == d  # tuples came out as lists
    assert cls.from_dict(d) == cls()
    with pytest.raises(KeyError, match=f"unknown {cls.KIND} parameter\\(s\\): nope"):
        cls.from_dict({**d, "nope": 1})


def test_seed003_settings_nest_their_views_as_plain_dicts():
    from napari_imgreg.registration.seed003 import Seed003Params

    d = Seed003Params().to_dict()
    assert isinstance(d["views"], dict) and isinstance(d["views"]["hog_scales"], list)
    assert isinstance(d["pairs"], list)
    assert Seed003Params.from_dict(d).to_dict() == d
