import numpy as np
import pytest

from geonav.camera import Camera
from geonav.errors import TaskError
from geonav.tasks import (
    Lattice,
    NavTask,
    TaskSet,
    bfs_distances,
    bind,
    blocked_cells,
    sample_meta_tasks,
    whole_scene_tasks,
)
from geonav.testing import textured_scene


def test_lattice_geometry():
    lat = Lattice((-30.0, -15.0, 30.0, 15.0), 15.0)
    assert lat.shape == (4, 2)
    assert lat.center((0, 0)).x_m == -22.5 and lat.center((3, 1)).y_m == 7.5
    assert lat.cell_of(lat.center((2, 1))) == (2, 1)
    assert not lat.contains((4, 0)) and lat.contains((3, 1))
    with pytest.raises(TaskError):
        Lattice((0, 0, 10, 10), 15.0)


def test_bfs_goes_around_walls():
    blocked = np.zeros((5, 5), bool)
    blocked[2, 0:4] = True  # wall at ix=2, gap at iy=4
    d = bfs_distances(blocked, (0, 0))
    assert d[4, 0] == 4 + 2 * 4  # up to iy=4, across, back down
    assert d[2, 2] == -1
    blocked[2, 4] = True
    assert bfs_distances(blocked, (0, 0))[4, 0] == -1


def test_obstacles_follow_altitude(scene):
    lat = Lattice((-150.0, -150.0, 150.0, 150.0), 15.0)
    counts = {alt: int(blocked_cells(scene, lat, alt).sum()) for alt in (75, 45, 15)}
    # towers are 60 m, houses 12 m; clearance 5 m
    assert counts[75] == 0
    assert 0 < counts[45] < counts[15]
    # every cell blocked at 45 m has a tower (>40 m) within the safety radius
    b45 = blocked_cells(scene, lat, 45)
    for ix, iy in np.argwhere(b45):
        p = lat.center((int(ix), int(iy)))
        col, row = scene.to_pixel(p.x_m, p.y_m)
        r = int(3.0 / scene.gsd_m) + 1
        patch = scene.dsm[int(row) - r:int(row) + r + 1, int(col) - r:int(col) + r + 1]
        assert patch.max() > 40.0


def test_no_dsm_no_obstacles(flat_scene):
    lat = Lattice((-60.0, -60.0, 60.0, 60.0), 15.0)
    assert not blocked_cells(flat_scene, lat, 15).any()


def test_bind_errors(scene):
    cam = Camera()
    ok = NavTask("t", "meta", (-30, -30, 30, 30), 15.0, 75.0, (0, 0))
    bind(ok, scene, cam)
    with pytest.raises(TaskError, match="outside scene"):
        bind(NavTask("t", "meta", (150, 150, 250, 250), 15.0, 75.0, (0, 0)), scene, cam)
    with pytest.raises(TaskError, match="needs 300 m of imagery"):
        bind(NavTask("t", "meta", (-30, -30, 30, 30), 15.0, 300.0, (0, 0)), scene, cam)
    with pytest.raises(TaskError, match="outside the"):
        bind(NavTask("t", "meta", (-30, -30, 30, 30), 15.0, 75.0, (9, 9)), scene, cam)
    lat = Lattice((-150.0, -150.0, 150.0, 150.0), 15.0)
    blocked = np.argwhere(blocked_cells(scene, lat, 15.0))
    cell = (int(blocked[0][0]), int(blocked[0][1]))
    with pytest.raises(TaskError, match="is an obstacle at 15 m"):
        bind(NavTask("t", "scene", lat.region_m, 15.0, 15.0, cell), scene, cam)


def test_unreachable_target():
    s = textured_scene(300.0, 0.5, seed=2, towers=False)
    s.dsm[:] = 0
    # a ring of 30 m walls around the centre cell of a 5x5 lattice of 10 m
    rows, cols = s.dsm.shape
    c = cols // 2
    s.dsm[c - 30:c + 30, c - 30:c + 30] = 30.0  # walls from 5 m to 15 m off the centre
    s.dsm[c - 10:c + 10, c - 10:c + 10] = 0.0
    task = NavTask("t", "scene", (-25, -25, 25, 25), 10.0, 15.0, (2, 2),
                   obstacles=__import__("geonav.tasks").tasks.ObstacleModel(1.0, 5.0))
    with pytest.raises(TaskError, match="unreachable"):
        bind(task, s, Camera())


def test_meta_tasks_reproducible_with_margin(tmp_path):
    s = textured_scene(1000.0, 1.0, seed=4)
    a = sample_meta_tasks(s, 4, size_m=150, alt_m=300, step_m=15, seed=7)
    b = sample_meta_tasks(s, 4, size_m=150, alt_m=300, step_m=15, seed=7)
    assert a.to_dict() == b.to_dict()
    assert sample_meta_tasks(s, 4, seed=8).to_dict() != a.to_dict()
    for t in a.tasks:
        x0, y0, x1, y1 = t.region_m
        assert x1 - x0 == 150 and t.lattice.shape == (10, 10)
        assert x0 - 300 >= s.bounds_m[0] and x1 + 300 <= s.bounds_m[2]
        assert x0 % s.gsd_m == pytest.approx(0) or x0 % s.gsd_m == pytest.approx(s.gsd_m)
    path = a.save(tmp_path / "t.json")
    c = TaskSet.load(path)
    assert c.to_dict() == a.to_dict()
    c.check_scene(s)
    with pytest.raises(TaskError, match="made for scene"):
        c.check_scene(textured_scene(1000.0, 1.0, seed=4, name="other"))
    with pytest.raises(TaskError, match="needs 750 m"):
        sample_meta_tasks(textured_scene(400.0, 1.0), 2)


def test_whole_scene_tasks_share_lattice_and_target():
    s = textured_scene(500.0, 0.5, seed=5)
    ts = whole_scene_tasks(s, (75, 45, 15), step_m=15, seed=1)
    assert [t.alt_m for t in ts.tasks] == [75, 45, 15]
    assert len({(t.region_m, t.target_cell) for t in ts.tasks}) == 1
    assert ts.tasks[0].region_m[0] - 75 >= s.bounds_m[0] - 1e-6
    assert all(t.max_steps == 120 for t in ts.tasks)


def test_taskset_file_errors(tmp_path):
    with pytest.raises(TaskError, match="does not exist"):
        TaskSet.load(tmp_path / "none.json")
    (tmp_path / "bad.json").write_text("[1, 2")
    with pytest.raises(TaskError, match="not valid JSON"):
        TaskSet.load(tmp_path / "bad.json")
    (tmp_path / "old.json").write_text('{"schema_version": 0}')
    with pytest.raises(TaskError, match="schema_version"):
        TaskSet.load(tmp_path / "old.json")


def test_view_coverage_counts_masked_and_outside_pixels():
    from geonav.tasks import view_coverage

    s = textured_scene(200.0, 0.5, seed=3, towers=False)
    s.mask[:, : s.width // 2] = False  # west half has no imagery
    cam = Camera()
    lat = Lattice((-60.0, -30.0, 60.0, 30.0), 15.0)
    cov = view_coverage(s, lat, 15.0, cam)  # 30 m views
    xs, _ = lat.centers()
    assert np.allclose(cov[xs > 15.0], 1.0) and np.allclose(cov[xs < -15.0], 0.0)
    # a view centred 7.5 m east of the mask edge: 22.5 of its 30 m are valid
    assert cov[xs == 7.5] == pytest.approx(0.75, abs=0.01)
    # at 300 m the 600 m view reaches far outside the 200 m scene
    assert cov.max() <= 1.0 and view_coverage(s, lat, 300.0, cam).max() < 0.11


def test_targets_and_starts_only_where_the_view_is_covered():
    s = textured_scene(400.0, 0.5, seed=4, towers=False)
    s.mask[:, : int(s.width * 0.45)] = False  # 45 % of the scene is masked
    ts = whole_scene_tasks(s, (75.0, 45.0, 15.0), step_m=15.0, seed=0)
    from geonav.tasks import view_coverage

    cam = ts.camera
    for task in ts.tasks:
        tm = bind(task, s, cam)
        cov = view_coverage(s, task.lattice, task.alt_m, cam)
        assert cov[task.target_cell] >= 0.99
        starts = tm.start_cells()
        assert starts and all(cov[c] >= 0.99 for c in starts)
        assert (cov < 0.99).any()  # some cells are excluded
    assert ts.tasks[0].min_coverage == 0.99
    meta = sample_meta_tasks(textured_scene(900.0, 1.0, seed=5, towers=False), 2, seed=1)
    assert all(t.min_coverage == 0.99 for t in meta.tasks)
    bad = NavTask("b", "scene", ts.tasks[0].region_m, 15.0, 15.0, (0, 0), 120)
    with pytest.raises(TaskError, match="valid imagery"):
        bind(bad, s, cam)
    # round trip keeps the threshold; old files without it get the default
    d = ts.tasks[0].to_dict()
    assert NavTask.from_dict(d).min_coverage == 0.99
    d.pop("min_coverage")
    assert NavTask.from_dict(d).min_coverage == 0.99


def test_tasks_keep_only_targets_that_chance_does_not_solve():
    from geonav.difficulty import start_success

    s = textured_scene(1000.0, 1.0, seed=4)
    cam = Camera(32, 45.0)
    free = sample_meta_tasks(s, 3, size_m=150, alt_m=300, step_m=7.5, max_steps=40, seed=2,
                             camera=cam)
    capped = sample_meta_tasks(s, 3, size_m=150, alt_m=300, step_m=7.5, max_steps=40,
                               seed=2, camera=cam, max_random_walk=0.05)
    rw = [start_success(bind(t, s, cam)) for t in capped.tasks]
    assert max(rw) <= 0.05 and capped.meta["max_random_walk"] == 0.05
    assert [t.lattice.shape for t in capped.tasks] == [(20, 20)] * 3
    # without the cap, central targets (random walk ~0.06 on this lattice) are kept too
    assert max(start_success(bind(t, s, cam)) for t in free.tasks) > min(rw)
    with pytest.raises(TaskError, match="random-walk success <= 0.01"):
        sample_meta_tasks(s, 2, size_m=150, alt_m=300, step_m=15, max_steps=70, seed=2,
                          camera=cam, max_random_walk=0.01)
    with pytest.raises(TaskError, match="keeps random-walk success"):
        whole_scene_tasks(textured_scene(500.0, 0.5, seed=5), (75,), step_m=50, seed=1,
                          max_random_walk=0.01)
    with pytest.raises(TaskError, match="max_random_walk must lie"):
        sample_meta_tasks(s, 1, max_random_walk=0.0)


def test_tasks_that_need_the_view_keep_view_blind_low_and_targets_inside():
    from geonav.difficulty import best_blind
    from geonav.tasks import starts_on_every_side

    s = textured_scene(1000.0, 1.0, seed=4)
    cam = Camera(32, 45.0)
    kw = dict(size_m=150, alt_m=300, step_m=10, max_steps=30, camera=cam)
    corner = sample_meta_tasks(s, 4, seed=2, max_random_walk=0.05, **kw)
    capped = sample_meta_tasks(s, 4, seed=2, max_blind=0.3, **kw)
    blind = [best_blind(bind(t, s, cam))[0] for t in capped.tasks]
    assert max(blind) <= 0.3 and capped.meta["max_blind"] == 0.3
    assert all(starts_on_every_side(bind(t, s, cam)) for t in capped.tasks)
    for t in capped.tasks:  # never on the region's edge
        nx, ny = t.lattice.shape
        assert 0 < t.target_cell[0] < nx - 1 and 0 < t.target_cell[1] < ny - 1
    # the random-walk cap alone picks targets a fixed bias reaches (corners, edges)
    assert max(best_blind(bind(t, s, cam))[0] for t in corner.tasks) > 0.3
    scene_ts = whole_scene_tasks(textured_scene(500.0, 0.5, seed=5), (75, 45), step_m=25,
                                 max_steps=40, seed=1, max_blind=0.3)
    assert scene_ts.meta["max_blind"] == 0.3
    s5 = textured_scene(500.0, 0.5, seed=5)
    assert all(best_blind(bind(t, s5))[0] <= 0.3 for t in scene_ts.tasks)
    with pytest.raises(TaskError, match="view-blind success <= 0.01"):
        sample_meta_tasks(s, 2, seed=2, max_blind=0.01, **kw)
    with pytest.raises(TaskError, match="max_blind must lie"):
        sample_meta_tasks(s, 1, max_blind=1.5)
