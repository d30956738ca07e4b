"""The evaluation places its objects around the evaluated rig's working point, for a rig set
up for any distance, and refuses bad ``--distances`` by name (no graph, no rclpy)."""

import numpy as np
import pytest

from galvoscan import eval_scenes
from galvoscan.evaluate import DISTANCES_MM, main
from galvoscan_sim import load_rig
from galvoscan_sim.config import read_yaml_file
from galvoscan_sim.rig_family import draw_rig, reset_for_distance, working_distance, working_point


def test_the_reference_rig_keeps_the_papers_scenes():
    rig = load_rig('reference')
    site = eval_scenes.site_of(rig)
    assert site.scale == 1.0 and site.lateral == (1.0, 1.0)
    # the paper's 30 positions, about the working point
    grid = np.array(site.stair_grid(6, 5)) - site.centre_W
    assert np.allclose(np.abs(grid[:, :2]).max(axis=0), eval_scenes.STAIR_GRID_HALF)
    # REFERENCE_REACH is this rig's G1 reach at 650 mm
    excess = eval_scenes.g1_reach(rig, eval_scenes.REFERENCE_DEPTH) - \
        np.array(eval_scenes.REFERENCE_REACH)
    assert np.all((excess >= 0) & (excess < 1e-3)), excess
    assert abs(site.depth - 0.65) < 1e-3
    # the cell positions are those of the paper's site, within the working point's offset
    paper = eval_scenes.cell_positions(np.eye(4))
    assert np.allclose(paper, eval_scenes.CELL_POSITIONS)
    assert np.abs(eval_scenes.cell_positions(np.eye(4), site) - paper).max() < 1e-3
    # a stand-off of the rig's own working distance is its working point
    assert np.linalg.norm(site.at_standoff(working_distance(rig)) - site.centre_W) < 1e-6


@pytest.mark.parametrize('mm', [100, 1000])
def test_a_rig_reset_for_a_distance_gets_scenes_there(mm):
    description = reset_for_distance(read_yaml_file(load_rig('reference').source), mm / 1e3)
    site = eval_scenes.site_of(description)
    assert np.allclose(site.centre_W, working_point(description))
    assert abs(np.linalg.norm(site.at_standoff(mm / 1e3)) - np.linalg.norm(site.centre_W)) \
        < 1e-6
    assert site.scale == round(np.linalg.norm(site.centre_W) / eval_scenes.REFERENCE_DEPTH, 2)
    grid = np.array(site.stair_grid(3, 2))
    assert grid.shape == (6, 3) and np.allclose(grid[:, 2], site.depth)
    assert np.ptp(grid[:, 0]) <= 2 * eval_scenes.STAIR_GRID_HALF[0] * site.lateral[0] + 1e-12
    assert np.ptp(grid[:, 0]) > 0
    assert site.lateral[0] <= site.scale and site.lateral[1] <= site.scale
    _, plate = eval_scenes.plate(0, site)
    assert np.allclose(plate['W_T_O'][:3, 3], site.centre_W)
    # the paper's plate: smaller at short range, never larger; scaled either way with grow
    assert plate['size'][0] == pytest.approx(eval_scenes.PLATE_SIZE * min(1.0, site.scale))
    _, grown = eval_scenes.plate(0, site, grow=True)
    assert grown['size'][0] == pytest.approx(eval_scenes.PLATE_SIZE * site.scale)
    assert eval_scenes.sphere_radius(site) <= eval_scenes.SPHERE_RADIUS
    text, _ = eval_scenes.cell_reference(np.eye(4), site)
    assert 'positions:' in text


def test_drawn_rigs_have_a_site_in_front_and_within_reach():
    from galvoscan_sim import rig_from_dict

    ext = eval_scenes.STAIR_AIM_EXTENT
    ref = (np.array(eval_scenes.STAIR_GRID_HALF) + ext) / eval_scenes.REFERENCE_REACH
    for seed in (0, 1, 2):
        description = draw_rig(seed)
        site = eval_scenes.site_of(description)
        assert site.depth > site.exit_m > 0
        assert abs(np.linalg.norm(site.centre_W) - site.exit_m
                   - working_distance(description)) < 1e-9
        # the stair block's outermost aims lie no further out, in G1's reach, than those of
        # the paper's grid on the reference rig
        reach = eval_scenes.g1_reach(rig_from_dict(description, 'drawn'), site.depth)
        grid = np.array(site.stair_grid(6, 5))
        outer = np.abs(grid[:, :2] - site.centre_W[:2]).max(axis=0) + ext
        assert np.all(outer / reach <= ref + 1e-9), (seed, outer / reach, ref)


@pytest.mark.parametrize('value, needle', [
    ('50', '50 mm is outside 100..1000 mm'), ('2000', 'outside'),
    ('200,abc', "'abc' is not a whole number"), ('0.65', "'0.65' is not a whole number")])
def test_bad_distances_are_refused_by_name(tmp_path, capsys, value, needle):
    with pytest.raises(SystemExit) as exc:
        main(['--distances', value, '--out', str(tmp_path / 'o')])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert '--distances' in err and needle in err
    assert not (tmp_path / 'o').exists()


def test_the_default_distances_are_the_papers():
    assert DISTANCES_MM == (100, 200, 350, 400, 650, 1000)


def test_a_failed_stage_at_a_distance_is_named_not_raised():
    from galvoscan.calibrate_client import StageError
    from galvoscan.evaluate import _not_measured

    row = _not_measured(StageError('laser_plane', 'compute laser_plane: 0 board poses'),
                        rig='r.yaml')
    assert row == {'error_mm': None, 'reason': 'not measured: compute laser_plane: 0 board '
                   'poses', 'failed_stage': 'laser_plane', 'rig': 'r.yaml'}
    assert 'failed_stage' not in _not_measured(RuntimeError('graph did not come up'))


def test_the_plate_raster_scans_the_plate_edge_to_edge():
    view = (0.060, 0.045)                        # one view at 650 mm
    centres, lines, spacing = eval_scenes.plate_raster(0.74, view, 3, 0.018)
    ys = np.sort(np.unique(lines))
    # evenly spaced lines over the whole plate, at most 18 mm apart, the outermost half a
    # spacing from the edges: every 20 mm coverage cell row is crossed by one
    assert spacing <= 0.018 and np.allclose(np.diff(ys), spacing)
    assert np.isclose(ys[0], -0.37 + spacing / 2) and np.isclose(ys[-1], 0.37 - spacing / 2)
    # each view is centred on its own lines, which fit in it
    assert np.allclose(centres[:, 1], lines.mean(axis=1))
    assert np.ptp(lines, axis=1).max() <= 0.9 * view[1]
    # the views of a row overlap and the outermost reach past the edges
    xs = np.unique(centres[:, 0])
    assert np.diff(xs).max() < view[0] and xs[0] - view[0] / 2 <= -0.37
    assert xs[-1] + view[0] / 2 >= 0.37
    # serpentine: consecutive views never jump more than one step in x
    assert np.abs(np.diff(centres[:, 0])).max() <= np.diff(xs).max() + 1e-12
    # a plate covered by points on those lines is fully covered; half of it is half
    x = np.linspace(-0.37, 0.37, 2000)
    pts = np.array([(a, b) for b in ys for a in x])
    assert eval_scenes.plate_coverage(pts, 0.74) == 1.0
    assert eval_scenes.plate_coverage(pts[pts[:, 0] < 0], 0.74) == pytest.approx(
        19 / 37, abs=1e-9)
    assert eval_scenes.plate_coverage(np.zeros((0, 2)), 0.74) == 0.0
    # decimated (--quick): fewer views, still centred on the plate
    few, few_lines, _ = eval_scenes.plate_raster(0.74, view, 2, 0.018, skip=3)
    assert len(few) < len(centres) / 4 and abs(few[:, 0].mean()) < 0.06
    # a short-range view too low for 3 lines takes fewer, still at most 18 mm apart
    short, short_lines, short_spacing = eval_scenes.plate_raster(0.74, (0.06, 0.02), 3, 0.018)
    assert short_lines.shape[1] == 2 and short_spacing <= 0.018
    assert np.ptp(short_lines, axis=1).max() <= 0.9 * 0.02
    with pytest.raises(ValueError, match='plate_raster'):
        eval_scenes.plate_raster(0.74, (0.06, 0.0), 3, 0.018)


def test_a_stripe_along_the_columns_rasters_the_plate_transposed():
    """Laser beside the camera: lines along the plate's y, spaced along x, in views of the
    same width and height (the raster of the laser below with x and y exchanged)."""
    view = (0.060, 0.045)
    rows = eval_scenes.plate_raster(0.74, view[::-1], 3, 0.018)
    cols = eval_scenes.plate_raster(0.74, view, 3, 0.018, across=0)
    assert np.allclose(cols[0], rows[0][:, ::-1]) and np.allclose(cols[1], rows[1])
    assert np.allclose(cols[0][:, 0], cols[1].mean(axis=1))     # centred on its x lines
    assert np.ptp(cols[1], axis=1).max() <= 0.9 * view[0]
    with pytest.raises(ValueError, match='across'):
        eval_scenes.plate_raster(0.74, view, 3, 0.018, across=2)
