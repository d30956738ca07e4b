"""The sim backend at 12 bits: uint16 frames that the driver publishes as mono16 (the same
serialisation as the rig backend's Mono10/12/16 frames), that a bag holds and gives back,
and that the view page draws."""

import copy

import numpy as np
import yaml

from galvo_driver.genicam_camera import pixel_format_info
from galvo_driver.sim_backend import SimBackend
from galvoscan_bag.frames import read_frames
from galvoscan_bag.writer import BagWriter
from galvoscan_common import cdr
from galvoscan_sim.config import read_yaml_file
from galvoscan_sim.rig import RIG_DIR
from galvoscan_view.web import png_gray


def _frames(tmp_path, depth, n=2):
    data = copy.deepcopy(read_yaml_file(RIG_DIR / 'reference.yaml'))
    data['camera'].update(bit_depth=depth, black_level=2.0 * 2 ** (depth - 8))
    path = tmp_path / f'rig{depth}.yaml'
    path.write_text(yaml.safe_dump(data))
    backend = SimBackend(rig=str(path), scene='stair_block', seed=2)
    backend.open()
    backend.start(np.zeros((n, 4)), frame_rate=1000.0)
    frames = []
    while backend.running or len(frames) < n:
        frames += backend.poll()
    return frames


def test_a_12_bit_sim_rig_is_published_as_mono16_and_survives_a_bag(tmp_path):
    frames = _frames(tmp_path, 12)
    dtype, depth = pixel_format_info('Mono12')
    for f in frames:
        assert f.image.dtype == dtype and f.image.max() < 2 ** depth
        assert f.image.max() > 255                       # the stripe uses the deeper codes
    # what the driver node publishes on camera/image_raw
    raw = [cdr.serialize_image(f.image, cdr.Header(1, i, 'camera'))
           for i, f in enumerate(frames)]
    for f, data in zip(frames, raw, strict=True):
        msg = cdr.parse_image_cdr(data)
        assert msg.encoding == 'mono16'
        assert np.array_equal(cdr.image_to_array(msg), f.image)
    # recorded as the recorder writes it (the CDR bytes as received) and read back
    with BagWriter(tmp_path / 'bag') as bag:
        bag.add_topic('/camera/image_raw', 'sensor_msgs/msg/Image')
        bag.add_topic('/galvo/state', 'galvoscan_msgs/msg/GalvoState')
        for i, (f, data) in enumerate(zip(frames, raw, strict=True)):
            state = cdr.GalvoState(cdr.Header(1, i, 'v0'), i, *map(float, f.voltages),
                                   True, 0)
            bag.write('/camera/image_raw', data, 1_000_000_000 + i)
            bag.write('/galvo/state', cdr.serialize_galvo_state(state), 1_000_000_000 + i)
    back = list(read_frames(tmp_path / 'bag'))
    assert len(back) == len(frames)
    for f, b in zip(frames, back, strict=True):
        assert b.image.dtype == np.uint16 and np.array_equal(b.image, f.image)
    # the view page's image: scaled to 8 bits by its maximum, the stripe bright
    png = png_gray(frames[0].image)
    assert png.startswith(b'\x89PNG')


def test_an_8_bit_sim_rig_stays_mono8(tmp_path):
    (f,) = _frames(tmp_path, 8, n=1)
    assert f.image.dtype == pixel_format_info('Mono8')[0]
    msg = cdr.parse_image_cdr(cdr.serialize_image(f.image, cdr.Header(0, 0, 'camera')))
    assert msg.encoding == 'mono8'
