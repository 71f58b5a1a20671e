import numpy as np
import pytest

from geonav.camera import Camera, SliceRenderer, WarpRenderer, render
from geonav.errors import CameraError


def test_footprints_of_the_paper_altitudes():
    cam = Camera(84, 90.0)
    assert [round(cam.footprint_m(a), 6) for a in (300, 75, 45, 15)] == [600, 150, 90, 30]
    assert cam.ground_res_m(15) == pytest.approx(30 / 84)
    with pytest.raises(CameraError):
        Camera(4)
    with pytest.raises(CameraError):
        cam.footprint_m(0)


@pytest.mark.parametrize("alt", [75.0, 45.0, 15.0])
def test_slice_and_warp_paths_agree(scene, alt):
    """Same camera model: at the slice path's snapped centre the two renders differ by
    area-average vs. pyramid+bilinear filtering only: mean |diff| < 10 DN, no shift."""
    import cv2

    cam = Camera(84, 90.0)
    sl, wr = SliceRenderer(scene, cam), WarpRenderer(scene, cam)
    rng = np.random.default_rng(0)
    diffs = []
    for _ in range(10):
        x, y = rng.uniform(-100, 100, 2)
        xs, ys = sl.snap(x, y, alt)
        assert abs(xs - x) <= cam.ground_res_m(alt) / 2 * 1.01
        a, b = sl.render(x, y, alt), wr.render(xs, ys, alt)
        diffs.append(np.abs(a.astype(float) - b.astype(float)).mean())
        ga = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY).astype(np.float32)
        gb = cv2.cvtColor(b, cv2.COLOR_RGB2GRAY).astype(np.float32)
        (dx, dy), _ = cv2.phaseCorrelate(ga, gb)
        assert abs(dx) < 0.5 and abs(dy) < 0.5
    assert np.median(diffs) < 10.0


def test_view_moves_with_position_and_north_is_up(scene):
    cam = Camera(64, 90.0)
    wr = WarpRenderer(scene, cam)
    res = cam.ground_res_m(45.0)
    a = wr.render(0.0, 0.0, 45.0)
    b = wr.render(0.0, 10 * res, 45.0)  # 10 image pixels north
    # moving north shifts the image content down by 10 px
    assert np.abs(a[:-10].astype(int) - b[10:].astype(int)).mean() < 3.0
    c = wr.render(10 * res, 0.0, 45.0)  # 10 px east -> content shifts left
    assert np.abs(a[:, 10:].astype(int) - c[:, :-10].astype(int)).mean() < 3.0


def test_yaw_rotates_the_view(scene):
    wr = WarpRenderer(scene, Camera(64, 90.0))
    a = wr.render(0.0, 0.0, 45.0, yaw_deg=0.0)
    b = wr.render(0.0, 0.0, 45.0, yaw_deg=90.0)  # heading east: east is image-up
    assert np.abs(np.rot90(a, k=1).astype(int) - b.astype(int)).mean() < 4.0


def test_outside_is_filled_and_reported(scene):
    cam = Camera(64, 90.0)
    sl, wr = SliceRenderer(scene, cam, fill=0), WarpRenderer(scene, cam, fill=0)
    x_edge = scene.bounds_m[2]
    assert sl.coverage(x_edge, 0.0, 45.0) == pytest.approx(0.5, abs=0.05)
    assert wr.coverage(x_edge, 0.0, 45.0) == pytest.approx(0.5, abs=0.08)
    img = wr.render(x_edge, 0.0, 45.0)
    assert (img[:, -20:] == 0).all() and img[:, :20].mean() > 20
    assert sl.coverage(0.0, 0.0, 45.0) == 1.0
    with pytest.raises(CameraError, match="outside scene"):
        sl.render(x_edge + 500.0, 0.0, 45.0)


def test_render_function_caches_renderer(scene):
    a = render(scene, 5.0, 5.0, 75.0)
    b = render(scene, 5.0, 5.0, 75.0)
    assert a.shape == (84, 84, 3) and np.array_equal(a, b)
