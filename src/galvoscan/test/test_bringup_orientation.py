"""The bring-up orients the stripe extractor and the raster from the rig's calibration."""

import yaml

from galvoscan import bringup
from galvoscan_sim.rig_family import draw_rig

NODES = ('galvo_driver', 'stripe_extractor', 'reconstructor')


def _params(tmp_path, rig, extra=None):
    data = {'galvo_driver': {'ros__parameters': {'backend': 'sim', 'rig': str(rig)}},
            **(extra or {})}
    path = tmp_path / 'params.yaml'
    path.write_text(yaml.safe_dump(data))
    return path


def test_a_laser_beside_the_camera_gets_a_vertical_stripe_and_a_pan_raster(tmp_path):
    rig = tmp_path / 'beside.yaml'
    rig.write_text(yaml.safe_dump(draw_rig(3, 0.45, build={'sensor': 'IMX287',
                                                             'bit_depth': 8, 'laser': 'left'})))
    out = yaml.safe_load(open(bringup.with_stripe_orientation(
        _params(tmp_path, rig), NODES, tmp_path / 'work')))
    assert out['stripe_extractor']['ros__parameters']['orientation'] == 'vertical'
    assert out['galvo_driver']['ros__parameters']['raster_g1_axis'] == 'pan'


def test_the_reference_rig_keeps_the_rows_and_a_given_setting_is_kept(tmp_path):
    out = yaml.safe_load(open(bringup.with_stripe_orientation(
        _params(tmp_path, 'reference'), NODES, tmp_path / 'work')))
    assert out['stripe_extractor']['ros__parameters']['orientation'] == 'horizontal'
    assert out['galvo_driver']['ros__parameters']['raster_g1_axis'] == 'tilt'
    given = _params(tmp_path, 'reference', {
        'stripe_extractor': {'ros__parameters': {'orientation': 'vertical'}},
        'galvo_driver': {'ros__parameters': {'backend': 'sim', 'raster_g1_axis': 'pan'}}})
    assert bringup.with_stripe_orientation(given, NODES, tmp_path / 'work') == given
