"""The synchronised raster steps G2 with the G1 axis that moves the view across the stripe."""

import numpy as np
import pytest

from galvo_driver.patterns import raster


def test_the_raster_couples_g2_with_g1_tilt_or_with_g1_pan():
    below = raster((-1.0, 1.0), (-0.5, 0.5), (-2.0, 2.0), 3, 5)
    beside = raster((-1.0, 1.0), (-0.5, 0.5), (-2.0, 2.0), 3, 5, g1_axis='pan')
    assert below.shape == (15, 4) and beside.shape == (15, 4)
    for table, coupled, held, n_lines in ((below, 1, 0, 3), (beside, 0, 1, 5)):
        for k, line in enumerate(np.split(table, n_lines)):
            assert np.ptp(line[:, held]) == 0.0            # one line at a fixed other axis
            # G2 tilt follows the coupled G1 axis linearly, serpentine line by line
            frac = (line[:, coupled] - line[0, coupled]) / (line[-1, coupled]
                                                            - line[0, coupled])
            assert np.allclose((line[:, 3] - line[0, 3]) / (line[-1, 3] - line[0, 3]), frac)
            assert (line[-1, 3] > line[0, 3]) == (k % 2 == 0)
    assert np.allclose(np.unique(beside[:, 1]), np.linspace(-0.5, 0.5, 5))
    assert np.allclose(np.unique(beside[:, 0]), np.linspace(-1.0, 1.0, 3))
    with pytest.raises(ValueError, match='g1_axis'):
        raster((-1.0, 1.0), (-0.5, 0.5), (-2.0, 2.0), 3, 5, g1_axis='roll')
