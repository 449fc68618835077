"""Least-cost snapping of traces (interpret.snap) against images with known contacts."""

from __future__ import annotations

import numpy as np
import pytest

from napari_imgreg.interpret.snap import SnapParams, cost_image, snap_path, snap_trace

H, W = 120, 240


def _contact_row(col: np.ndarray) -> np.ndarray:
    """The true contact: a bend across relief, row as a function of column."""
    return 60.0 + 8.0 * np.sin(2 * np.pi * col / 160.0)


def _area_image(rows_of, dark_above: bool = True, supersample: int = 8) -> np.ndarray:
    """A uint8 RGB image: grey 60 above the contact, 180 below, anti-aliased."""
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    rr = np.arange(H)[:, None, None] + sub[None, None, :]
    cc = np.arange(W)[None, :, None] + 0 * sub
    below = rr > rows_of(cc)
    frac = below.mean(axis=2)
    lo, hi = (60.0, 180.0) if dark_above else (180.0, 60.0)
    img = lo + (hi - lo) * frac
    return np.repeat(np.round(img)[..., None], 3, axis=2).astype(np.uint8)


def _median_offset(px: np.ndarray, rows_of) -> float:
    dense = np.concatenate([np.linspace(a, b, 20, endpoint=False) for a, b in zip(px[:-1], px[1:])])
    return float(np.median(np.abs(dense[:, 1] - rows_of(dense[:, 0]))))


def test_follows_a_curved_contact_from_two_clicks_subpixel():
    img = _area_image(_contact_row)
    clicks = np.array([[10.0, _contact_row(np.array(10.0))], [230.0, _contact_row(np.array(230.0))]])
    px = snap_trace(img, clicks)
    assert np.allclose(px[0], clicks[0], atol=3.5) and np.allclose(px[-1], clicks[-1], atol=3.5)
    assert _median_offset(px, _contact_row) < 0.25  # pixels: sub-pixel on a clean edge
    # The straight line between the clicks is up to 8 px off: snapping did the work.
    straight = np.stack([np.linspace(10, 230, 50), np.linspace(clicks[0, 1], clicks[1, 1], 50)], 1)
    assert _median_offset(straight, _contact_row) > 3.0


def test_keeps_its_polarity_across_a_thin_band_and_ignores_a_stronger_edge_nearby():
    """A dark bed 6 px thick: clicking its base follows the base, not the top,
    nor a much stronger edge (a skyline) 15 px above."""
    def base(col):
        return 70.0 + 0 * col

    img = np.full((H, W, 3), 170.0)
    img[64:70] = 90.0   # the thin dark bed (top edge at 63.5, base at 69.5)
    img[:49] = 255.0    # bright sky above a stronger edge at 48.5
    img[:, 118:121] = 100.0  # a cross-cutting joint
    img = img.astype(np.uint8)
    clicks = np.array([[20.0, 69.5], [220.0, 69.5]])
    px = snap_trace(img, clicks)
    assert np.median(np.abs(px[:, 1] - 69.5)) < 0.5
    assert px[:, 1].min() > 66  # never on the top edge or the skyline


def test_polarity_is_read_along_the_contact_not_on_the_rocks_mottling_under_a_click():
    """Clicks 1.5 px below the lower contact of a thin dark bed, each on a
    speck of mottling whose fine-scale gradient points the other way. Read at
    the clicks alone the polarity flipped and the trace ran along the bed's
    upper contact; read along the clicked segment (8 px inward from each
    click) the speck is outvoted, at the cost's fine scale too, and the trace
    keeps to the lower contact, to a tenth of a pixel."""
    img = np.full((120, 200), 0.6)
    img[58:63] = 0.3  # contacts at rows 57.5 (upper) and 62.5 (lower)
    clicks = np.array([[20.0, 64.0], [180.0, 64.0]])
    for c, r in clicks.astype(int):
        img[r - 1, c], img[r + 1, c] = 0.95, 0.05  # bright above, dark below
    img8 = (img * 255).astype(np.uint8)
    for params in (SnapParams(), SnapParams(polarity_px=0.7)):
        px = snap_trace(img8, clicks, params)
        assert np.all(np.abs(px[1:-1, 1] - 62.5) < 0.1)
    assert SnapParams().polarity_px == 1.5
    with pytest.raises(ValueError, match="polarity_px"):
        SnapParams(polarity_px=0.1)


def test_where_the_contact_fades_under_the_clicks_the_straighter_polarity_wins():
    """The contact is clicked where its visible stretch ends, and the thin bed
    fades there (no contrast within 12 px of either click): the polarity is
    not readable. Both polarities are traced; the bed's base runs straight,
    its top is a wavy erosion surface — the trace keeps to the straight one
    that the clicks lie on."""
    cols = np.arange(200)
    top = 55.0 + 4.0 * np.sin(2 * np.pi * cols / 25.0)  # wavy upper contact
    rows = np.arange(120)[:, None]
    bed = (rows > top[None, :]) & (rows < 64.5)          # base straight at 64.5
    fade = np.clip((np.minimum(cols - 20, 180 - cols) - 12) / 10.0, 0, 1)[None, :]
    img = 0.6 - 0.3 * bed * fade
    img8 = (img * 255).astype(np.uint8)
    clicks = np.array([[20.0, 64.5], [180.0, 64.5]])
    px = snap_trace(img8, clicks)
    dense = np.concatenate([np.linspace(a, b, 20, endpoint=False) for a, b in zip(px[:-1], px[1:])])
    inner = dense[(dense[:, 0] > 45) & (dense[:, 0] < 155)]
    assert len(inner) and np.all(np.abs(inner[:, 1] - 64.5) < 0.6)
    # Read at the clicks the bed is not there: the polarity is unclear.
    from napari_imgreg.interpret.snap import _luminance_derivatives, _polarity

    gx, gy = _luminance_derivatives(img8, 1.5)
    assert _polarity(gx, gy, np.array([0.0, 1.0]), clicks)[1] is False


SAND = np.array([200.0, 170.0, 120.0])  # warm and bright
MUD = np.array([120.0, 115.0, 110.0])   # neutral grey, darker


def _layered(bounds, colours, supersample: int = 8) -> np.ndarray:
    """A uint8 RGB image of level beds, anti-aliased: bed ``i`` (``colours[i](cols)``,
    (W, 3)) lies below row ``bounds[i - 1]`` and above row ``bounds[i]``."""
    sub = (np.arange(supersample) + 0.5) / supersample - 0.5
    rr = np.arange(H)[:, None] + sub[None, :]
    k = sum((rr > row).astype(int) for row in bounds)  # (H, supersample): the bed index
    cols = np.arange(W, dtype=np.float64)
    img = np.zeros((H, W, 3))
    for i, colour in enumerate(colours):
        img += (k == i).mean(axis=1)[:, None, None] * colour(cols)[None]
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


def _flat(rgb):
    return lambda cols: np.broadcast_to(np.asarray(rgb, np.float64), (len(cols), 3))


def _fading(rgb_ends, rgb_middle):
    """``rgb_ends`` near the image's sides, ``rgb_middle`` over its middle third."""
    def colour(cols):
        w = np.clip((np.minimum(cols, W - 1 - cols) - 40) / 30.0, 0, 1)[:, None]
        return (1 - w) * np.asarray(rgb_ends, np.float64) + w * np.asarray(rgb_middle, np.float64)
    return colour


def _middle_rows(px: np.ndarray, lo: float = 70, hi: float = 170) -> np.ndarray:
    dense = np.concatenate([np.linspace(a, b, 20, endpoint=False) for a, b in zip(px[:-1], px[1:])])
    return dense[(dense[:, 0] > lo) & (dense[:, 0] < hi), 1]


CLICKS_ON_60 = np.array([[10.0, 60.0], [230.0, 60.0]])


def test_trained_colour_keeps_to_a_contact_whose_luminance_fades_beside_a_shadow():
    """Sandstone over mudstone at row 60; a shadow (every channel × 0.6) 4 px
    below. Over the middle third the mudstone is lit as bright as the
    sandstone: the contact is only a change of colour there, the shadow the
    only luminance edge. On the luminance alone the trace follows the shadow;
    trained on the colour step under the clicks (warm to grey), which the
    shadow lacks, it keeps to the contact, to a hundredth of a pixel."""
    lit = MUD * SAND.mean() / MUD.mean()
    img = _layered([60.0, 64.0], [_flat(SAND), _fading(MUD, lit), _fading(0.6 * MUD, 0.6 * lit)])
    assert np.median(np.abs(_middle_rows(snap_trace(img, CLICKS_ON_60, SnapParams(colour_weight=0)))
                            - 64.0)) < 0.1
    rows = _middle_rows(snap_trace(img, CLICKS_ON_60))
    assert len(rows) and np.all(np.abs(rows - 60.0) < 0.05)


def test_trained_colour_keeps_to_the_clicked_side_of_a_thin_bed_of_one_polarity():
    """A grey bed 5 px thick between a warm sandstone above and a dark brown
    bed below: both of its contacts darken downwards (one polarity), but the
    colour steps differ (warm to grey, grey to brown). The upper contact is
    clicked; over the middle third the grey bed is lit as bright as the
    sandstone, so only the lower contact shows in luminance there. On the
    luminance alone the trace crosses to the lower contact; trained on the
    clicked colour pair it keeps to the upper one."""
    grey, brown = np.array([140.0, 140.0, 140.0]), np.array([110.0, 78.0, 45.0])
    img = _layered([60.0, 65.0], [_flat(SAND), _fading(grey, grey * SAND.mean() / grey.mean()),
                                  _flat(brown)])
    assert np.median(np.abs(_middle_rows(snap_trace(img, CLICKS_ON_60, SnapParams(colour_weight=0)))
                            - 65.0)) < 0.1
    rows = _middle_rows(snap_trace(img, CLICKS_ON_60))
    assert len(rows) and np.all(np.abs(rows - 60.0) < 0.05)


def test_trained_colour_ignores_mottling_of_one_colour_beside_a_weak_contact():
    """Dark mottles (the upper bed's own colour × 0.6, so no change of colour
    at their rims) 4–8 px above a contact that keeps 15 % of its luminance
    contrast over the middle: on the luminance alone the trace runs along the
    mottles' upper rims; trained on the colour step, along the contact."""
    top, bottom = np.array([185.0, 160.0, 118.0]), np.array([115.0, 112.0, 108.0])
    weak = bottom * (0.85 * top.mean() + 0.15 * bottom.mean()) / bottom.mean()
    img = _layered([60.0], [_flat(top), _fading(bottom, weak)]).astype(np.float64)
    rng = np.random.default_rng(1)
    for c0 in range(30, 210, 14):
        img[53:57, c0:c0 + rng.integers(10, 18)] *= 0.6
    img = np.round(img).astype(np.uint8)
    luminance_only = snap_trace(img, CLICKS_ON_60, SnapParams(colour_weight=0))
    assert np.median(np.abs(_middle_rows(luminance_only, 40, 200) - 60)) > 3.0
    rows = _middle_rows(snap_trace(img, CLICKS_ON_60), 40, 200)
    assert len(rows) and np.all(np.abs(rows - 60.0) < 0.05)


def test_without_a_colour_step_the_trace_is_the_luminance_ones():
    """A grey photo, and a colour photo whose beds differ only in brightness:
    nothing to train on, the trace is exactly the luminance-only one."""
    grey = _area_image(_contact_row)
    cols = np.array([10.0, 230.0])
    clicks = np.stack([cols, _contact_row(cols)], axis=1)
    for img in (grey[..., 0], grey):
        np.testing.assert_array_equal(snap_trace(img, clicks),
                                      snap_trace(img, clicks, SnapParams(colour_weight=0)))
    assert SnapParams().colour_weight == 1.0
    with pytest.raises(ValueError, match="colour_weight"):
        SnapParams(colour_weight=-1)


def test_a_waypoint_on_the_photos_border_continues_the_trace():
    """A waypoint clicked on the last column or row: the piece that ends there
    is refined up to a pixel and a half past the border; the next piece must
    still start from it, and the trace stays in the photo (it raised "click outside the photo" on 7 of 60 such
    random cases)."""
    rng = np.random.default_rng(0)
    for k in range(60):
        img = (rng.random((80, 120)) * 255).astype(np.uint8)
        way = [119.0, rng.uniform(0, 79)] if k % 2 else [rng.uniform(0, 119), 79.0]
        clicks = np.array([[rng.uniform(0, 119), rng.uniform(0, 79)], way,
                           [rng.uniform(0, 119), rng.uniform(0, 79)]])
        px = snap_trace(img, clicks)
        assert np.isfinite(px).all()
        assert np.all(px >= 0) and np.all(px <= [119, 79])  # in the photo


def test_waypoints_are_visited_in_order():
    img = _area_image(_contact_row)
    cols = np.array([10.0, 120.0, 230.0])
    clicks = np.stack([cols, _contact_row(cols)], axis=1)
    px = snap_trace(img, clicks)
    d = np.linalg.norm(px - clicks[1], axis=1)
    assert d.min() < 2.0
    assert np.all(np.diff(px[:, 0]) > -1.0)  # one pass from left to right


def test_darkness_cost_follows_a_dark_fracture():
    img = np.full((H, W), 200, np.uint8)
    cols = np.arange(W)
    rows = np.round(40 + 0.25 * cols).astype(int)
    img[rows, cols] = 30  # a one-pixel dark fracture
    px = snap_trace(img, np.array([[5.0, 41.0], [235.0, 99.0]]),
                    SnapParams(cost="darkness", smoothing_px=0.0, simplify_px=0.0))
    on_line = np.abs(px[:, 1] - (40 + 0.25 * px[:, 0])) <= 1.0
    assert on_line.mean() > 0.95


def test_colour_and_colour_edge_costs():
    img = np.zeros((H, W, 3), np.uint8)
    img[..., 0] = 150
    img[50:53, :, 1] = 200  # a green vein, 3 px, in red rock
    img[50:53, :, 0] = 20
    px = snap_trace(img, np.array([[10.0, 51.0], [230.0, 51.0]]),
                    SnapParams(cost="colour", simplify_px=0.0))
    assert np.all(np.abs(px[:, 1] - 51.0) <= 1.0)
    cost = cost_image(img, SnapParams(cost="colour_edge"))
    assert cost[49:50].mean() < cost[20].mean()  # the vein's boundary is cheap
    assert cost.min() >= 0.02 - 1e-12 and cost.max() <= 1.0 + 1e-12


def test_snap_path_on_a_known_cost_takes_the_cheap_corridor():
    cost = np.ones((50, 50))
    cost[10, :] = 0.01  # a cheap row
    px = snap_path(cost, np.array([[0.0, 10.0], [49.0, 10.0]]),
                   SnapParams(snap_radius_px=0, simplify_px=0.0))
    assert np.all(px[:, 1] == 10.0)
    assert len(px) == 50 and px[0, 0] == 0 and px[-1, 0] == 49


def test_bad_input():
    img = np.zeros((20, 20), np.uint8)
    with pytest.raises(ValueError, match="two clicks"):
        snap_trace(img, np.array([[1.0, 1.0]]))
    with pytest.raises(ValueError, match="outside"):
        snap_path(np.ones((20, 20)), np.array([[1.0, 1.0], [25.0, 3.0]]))
    with pytest.raises(ValueError, match="cost"):
        SnapParams(cost="curvature")
    with pytest.raises(ValueError, match="margin_px"):
        SnapParams(margin_px=2)


def test_repeated_and_dense_clicks_do_not_break_the_trace():
    """An already-snapped line given as clicks (vertices a pixel apart, repeats)."""
    img = _area_image(_contact_row)
    cols = np.array([10.0, 10.0, 10.4, 11.0, 60.0, 60.0, 230.0])
    clicks = np.stack([cols, _contact_row(cols)], axis=1)
    px = snap_trace(img, clicks)
    assert len(px) >= 2 and np.isfinite(px).all()
    assert _median_offset(px, _contact_row) < 0.5


def test_subpixel_refinement_is_exact_on_a_clean_edge():
    """The sub-pixel peak finder on an ideal step: a slanted edge at a known
    sub-pixel row, blurred as a lens would, the start on pixel centres."""
    from scipy import ndimage

    from napari_imgreg.interpret.snap import _luminance_derivatives, _subpixel

    rng = np.random.default_rng(3)
    errors = []
    for blur in (0.0, 0.8, 1.3):
        y0, slope = 40.0 + rng.uniform(0, 1), rng.uniform(-0.05, 0.05)
        ss = 8  # area-sampled: each pixel integrates its footprint
        rows = (np.arange(80 * ss) + 0.5) / ss - 0.5
        cols = (np.arange(120 * ss) + 0.5) / ss - 0.5
        edge = y0 + slope * (cols - 60.0)
        img = (0.3 + 0.4 * (rows[:, None] > edge[None, :])).reshape(80, ss, 120, ss).mean(axis=(1, 3))
        if blur:
            img = ndimage.gaussian_filter(img, blur)
        gx, gy = _luminance_derivatives(np.round(img * 255).astype(np.uint8), 0.7)
        c = np.arange(20.0, 100.0)
        start = np.stack([c, np.round(y0 + slope * (c - 60.0) + rng.uniform(-0.8, 0.8))], axis=1)
        errors.append(_subpixel(np.hypot(gx, gy), start)[:, 1] - (y0 + slope * (c - 60.0)))
    errors = np.concatenate(errors)
    assert np.median(np.abs(errors)) < 0.03 and np.abs(errors).max() < 0.1
    assert abs(errors.mean()) < 0.01  # no bias across the edge


def test_the_last_refinement_finds_a_step_whose_surroundings_differ_on_its_two_sides():
    """A contact at row 60.3 whose upper bed brightens towards it (a ramp over
    3 px) and a camera blur of 0.7 px: the smoothed gradient's peak, which
    placed the trace, lies off the step towards the ramp; the unsmoothed
    step, smoothed along the trace (``_refine_across``), lies on it."""
    from scipy import ndimage

    from napari_imgreg.interpret.snap import (_luminance_derivatives, _refine_across,
                                              _subpixel)

    y0 = 60.3
    # Rendered finely, then area-averaged (pixel centres at integers).
    fine = np.arange(-0.475, 119.5, 0.05)[:, None]
    above = fine < y0
    profile = np.where(above, 0.35 + 0.15 * np.exp(-(y0 - fine) / 1.5), 0.75)
    lum = profile.reshape(120, 20).mean(axis=1)[:, None] * np.ones((1, 240))
    lum = ndimage.gaussian_filter(lum, 0.7)
    rng = np.random.default_rng(3)
    img = np.clip(np.round((lum + rng.normal(0, 0.004, lum.shape)) * 255), 0, 255).astype(np.uint8)
    path = np.stack([np.arange(20.0, 220.0), np.full(200, 60.0)], axis=1)
    gx, gy = _luminance_derivatives(img, 0.7)
    smoothed_peak = _subpixel(np.clip(gy, 0, None), path)
    refined = _refine_across(img / 255.0, path, SnapParams(simplify_px=0.0))
    assert np.median(smoothed_peak[:, 1]) - y0 < -0.15  # towards the ramp: the bias removed
    assert abs(np.median(refined[20:-20, 1]) - y0) < 0.05
    assert np.ptp(refined[20:-20, 1]) < 0.1  # smoothed along the trace


def _shifted_row(by: float):
    return lambda col: _contact_row(col) + by


def test_the_trace_follows_the_models_contact_where_the_model_shows_it():
    """A registered pose 0.8 px off: the model's render shows the contact
    0.8 px below where the photo does. Followed (``reference``), the trace
    lies on the render's contact — where the projection finds the model's —
    to within a few hundredths of a pixel; without it, on the photo's."""
    photo = _area_image(_contact_row)
    render = _area_image(_shifted_row(0.8))
    clicks = np.array([[10.0, _contact_row(np.array(10.0))], [230.0, _contact_row(np.array(230.0))]])
    alone = snap_trace(photo, clicks)
    followed = snap_trace(photo, clicks, reference=render)
    assert _median_offset(alone, _contact_row) < 0.1
    assert _median_offset(followed, _shifted_row(0.8)) < 0.08
    # Off by the model's reach (1.5 px) or more: not followed (another edge).
    far = snap_trace(photo, clicks, reference=_area_image(_shifted_row(2.5)))
    assert _median_offset(far, _contact_row) < 0.1
    assert np.allclose(snap_trace(photo, clicks, SnapParams(model_reach_px=0), reference=render),
                       alone)


def test_a_model_that_does_not_show_the_contact_is_not_followed():
    """The render with the opposite polarity (another contact, a shadow), or
    with no step at all but its own texture (an untextured model's shading,
    an intensity blind to the contact): the trace stays on the photo's."""
    photo = _area_image(_contact_row)
    clicks = np.array([[10.0, _contact_row(np.array(10.0))], [230.0, _contact_row(np.array(230.0))]])
    alone = snap_trace(photo, clicks)
    flipped = _area_image(_shifted_row(0.8), dark_above=False)
    assert np.allclose(snap_trace(photo, clicks, reference=flipped), alone)
    rng = np.random.default_rng(5)
    from scipy import ndimage

    texture = ndimage.gaussian_filter(rng.normal(128, 40, (H, W)), 1.5)
    texture = np.repeat(np.clip(texture, 0, 255)[..., None], 3, axis=2).astype(np.uint8)
    assert np.allclose(snap_trace(photo, clicks, reference=texture), alone)
    with pytest.raises(ValueError, match="render"):
        snap_trace(photo, clicks, reference=texture[:-1])


def test_the_model_reference_is_its_colours_or_none(tmp_path):
    """A textured model gives its unshaded colours at the photo's size; an
    untextured one none (its shading is no contact)."""
    from napari_imgreg import Scene
    from napari_imgreg.camera import Intrinsics, Pose
    from napari_imgreg.interpret.snap import model_reference

    verts = np.array([[-50.0, 0, -50], [50, 0, -50], [50, 0, 50], [-50, 0, 50]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.0, 0], [1, 0], [1, 1], [0, 1]])
    tex = np.zeros((64, 64, 3), np.uint8)
    tex[:32] = (200, 150, 100)  # the upper half (v ≥ 0.5) of the texture
    intr = Intrinsics(80, 60, 60.0, 60.0, 39.5, 29.5)
    # Looking north (+y) at the wall from 30 m, z up.
    pose = Pose.from_center(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), np.array([0, -30.0, 0]))
    textured = model_reference(Scene(verts, faces, uv=uv, texture=tex), intr, pose)
    assert textured.shape == (60, 80, 3)
    assert (textured[5, 40] == (200, 150, 100)).all() and (textured[55, 40] == 0).all()
    assert model_reference(Scene(verts, faces), intr, pose) is None


def test_a_point_clouds_reference_is_its_intensity():
    """A scan with intensity gives its intensity as grey (the beds show);
    bare points give none."""
    from napari_imgreg.camera import Intrinsics, Pose
    from napari_imgreg.cloud import CloudScene
    from napari_imgreg.interpret.snap import model_reference

    rng = np.random.default_rng(2)
    xz = rng.uniform(-5, 5, (60_000, 2))
    xyz = np.c_[xz[:, 0], np.zeros(len(xz)), xz[:, 1]]  # a wall in the x–z plane
    upper = xyz[:, 2] > 0.0
    intr = Intrinsics(80, 60, 60.0, 60.0, 39.5, 29.5)
    pose = Pose.from_center(np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]), np.array([0, -8.0, 0]))
    scan = CloudScene(xyz, intensity=np.where(upper, 0.9, 0.2), name="wall",
                      viewpoints=np.array([[0.0, -8.0, 0.0]]))
    reference = model_reference(scan, intr, pose)
    assert reference.shape == (60, 80, 3)
    assert reference[10, 40, 0] > reference[50, 40, 0] + 60  # the bright bed above
    bare = CloudScene(xyz, name="bare", viewpoints=np.array([[0.0, -8.0, 0.0]]))
    assert model_reference(bare, intr, pose) is None
