"""The rig's hardware-in-the-loop twin: the ``rig`` backend scanning through the firmware in
simavr and Aravis' GigE Vision fake camera, which renders each exposure with the simulator
at the DAC outputs of its trigger edge.

Every frame the backend pairs is traced back independently of the pairing: the camera's
render log holds each image's CRC with the edge it was rendered for, the board's log holds
the DAC outputs at every edge, and the image is rendered again here from the codes of the
EVENT the backend tagged it with. A frame tagged with another trigger's EVENT fails, whatever
the driver did.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from galvo_driver.rig_backend import RigBackend
from galvo_driver.serial_link import protocol as p
from galvo_driver.twin import Twin, ad5754r_volts, image_crc, renders_by_image
from stripe_extractor.config import ExtractorConfig
from stripe_extractor.extractor import extract

ROWS = 36
RATE = 20.0  # [Hz]: the renderer's pace on a shared machine, not the camera's
SEED = 3


@pytest.fixture(scope='module')
def twin(tmp_path_factory):
    # the board at half speed: a test process the shared machine stalls keeps its heartbeat
    with Twin('reference', 'stair_block', seed=SEED, serial='GSTWINTEST',
              workdir=tmp_path_factory.mktemp('twin'), rate=0.5) as t:
        yield t


def test_each_paired_frame_is_the_exposure_at_its_own_events_codes(twin):
    from galvoscan_sim import Simulator, load_rig, load_scene

    be = RigBackend(twin.port, camera_serial=twin.serial, camera_clock='camera',
                    features={'ExposureTime': twin.exposure_us(), 'PixelFormat': 'Mono8'})
    # the stripe swept over the stair block, G1 on it; neighbouring rows differ in every
    # channel, so that a frame tagged with a neighbour's EVENT cannot pass
    u = np.linspace(-0.25, 0.25, ROWS)
    volts = np.column_stack([0.02 * np.cos(7 * u), -0.02 * np.sin(5 * u), 0.01 * u, u])
    be.open()
    try:
        be.arm()
        n = be.start(volts, RATE)
        frames = []
        deadline = time.monotonic() + 2 * ROWS / RATE + 30.0
        while be.running and time.monotonic() < deadline:
            frames += be.poll(0.05)
        frames += be.poll(0.0)
        stats = be.stats
    finally:
        be.close()
    board = twin.board.log()
    renders = renders_by_image(twin.renders())
    assert n == ROWS
    # the camera renders every edge (it delays frames, never misses them): most pair
    assert len(frames) >= ROWS // 2, (len(frames), stats.get('pairing'), renders)
    edges = set(int(c) for c in board.rising_edges())
    rig = load_rig('reference')
    sim = Simulator(rig, load_scene('stair_block'), seed=SEED)
    commanded = p.volts_to_codes(volts)
    config = ExtractorConfig(line_width_px=4.0)
    for f in frames:
        codes = tuple(int(c) for c in p.volts_to_codes(f.voltages))  # the EVENT's codes
        assert codes == tuple(int(c) for c in commanded[f.seq]) and f.laser_on
        rec = renders[image_crc(f.image)]  # the render of the edge that exposed this image
        assert rec.cycle in edges and board.codes_at(rec.cycle) == rec.codes
        assert rec.codes == codes, f'frame {f.seq}: image of codes {rec.codes}, EVENT {codes}'
        # the image is the simulator's exposure at those codes
        again = sim.render(ad5754r_volts(codes, 0xF, 4), exposure=rec.exposure_s,
                           frame_index=rec.index)
        assert np.array_equal(f.image, again.image)
        if len(again.truth.stripe) >= 200:
            found = extract(f.image, config)
            assert len(found) >= 100, f'frame {f.seq}: {len(found)} stripe columns'
            # where the true stripe is, the extracted one is (within 1 px)
            truth_v = dict(zip(again.truth.stripe.column, again.truth.stripe.v, strict=True))
            near = [abs(v - truth_v[int(round(c))]) < 1.0
                    for c, v in zip(found.u, found.v, strict=True) if int(round(c)) in truth_v]
            assert np.mean(near) > 0.9
