"""The calibration's verdict (stage_runner.verdict): good, which stage to redo and where, or
incomplete, from the predicted uncertainty map of the chain's joint covariance."""

from calibration_tools.stage_runner import verdict
from reconstructor.calibration_file import Calibration
from reconstructor.model import nominal_example_rig
from reconstructor.uncertainty import covariance_record


def _calibration(variances):
    stages = {}
    for i, (stage, (name, var)) in enumerate(variances.items()):
        stages[stage] = {'created': str(i), 'updated': [name.split('[')[0]],
                         'covariance': covariance_record([name], [[var]])}
    return Calibration(model=nominal_example_rig(), source='calibrated', stages=stages)


def test_an_unfinished_chain_is_incomplete_and_names_what_is_missing():
    v = verdict(_calibration({'intrinsics': ('intrinsics.cx', 1.0)}))
    assert v.startswith('incomplete') and 'laser_axis' in v and 'intrinsics' not in v


def test_uniform_uncertainty_is_good_and_an_edge_term_names_its_stage_and_place():
    flat = {'intrinsics': ('intrinsics.fx', 1.0), 'dynamic_camera': ('l', 1e-8),
            'laser_plane': ('laser_plane_v0[3]', 1e-9),
            'laser_axis': ('laser_axis_point[2]', 1e-9)}
    assert verdict(_calibration(flat)).startswith('good: predicted')
    # a cubic term of G1 tilt's response: nothing at the centre, most at the top and bottom
    edge = {**flat, 'dynamic_camera': ('g1_tilt.poly[1]', 1e-12)}
    v = verdict(_calibration(edge))
    assert v.startswith('redo dynamic_camera with views near U1 = ('), v
    assert '8.0) V' in v.split(':')[0], v


def test_a_stage_whose_estimates_a_later_stage_replaced_still_counts():
    # The laser bundle (laser_axis) re-estimates laser_plane's U2 = 0 plane: the chain is
    # complete, and the verdict is read from the map.
    stages = {'intrinsics': ('intrinsics.fx', 1.0), 'dynamic_camera': ('l', 1e-8),
              'laser_plane': ('laser_plane_v0[3]', 1e-9),
              'laser_axis': ('laser_plane_v0[3]', 1e-9)}
    assert verdict(_calibration(stages)).startswith('good: predicted')
