"""PLY and PCD clouds keep every field, and independent readers read them as written."""

import numpy as np
import pytest
from plyfile import PlyData
from pypcd4 import PointCloud

from reconstructor.cloud import CLOUD_DTYPE, load_cloud, save_cloud


def _cloud(n=257, seed=3):
    rng = np.random.default_rng(seed)
    cloud = np.empty(n, CLOUD_DTYPE)
    cloud['x'] = rng.uniform(-0.5, 0.5, n)
    cloud['y'] = rng.uniform(-0.6, 0.6, n)
    cloud['z'] = rng.uniform(0.55, 0.75, n)
    cloud['intensity'] = rng.uniform(0.0, 4095.0, n)  # 12-bit sensors exceed 255
    cloud['width'] = rng.uniform(2.0, 9.0, n)
    return cloud


@pytest.mark.parametrize('suffix', ['.ply', '.pcd'])
def test_round_trip_through_our_reader(tmp_path, suffix):
    cloud = _cloud()
    path = save_cloud(cloud, tmp_path / f'c{suffix}')
    back = load_cloud(path)
    assert back.dtype == CLOUD_DTYPE
    np.testing.assert_array_equal(back, cloud)
    assert not list(tmp_path.glob('.*.tmp'))


def test_ply_fields_in_plyfile(tmp_path):
    cloud = _cloud()
    save_cloud(cloud, tmp_path / 'c.ply')
    vertex = PlyData.read(str(tmp_path / 'c.ply'))['vertex']
    assert [p.name for p in vertex.properties] == list(CLOUD_DTYPE.names)
    for name in CLOUD_DTYPE.names:
        np.testing.assert_array_equal(vertex[name], cloud[name])


def test_pcd_follows_pcl_conventions_in_pypcd4(tmp_path):
    cloud = _cloud()
    save_cloud(cloud, tmp_path / 'c.pcd')
    pc = PointCloud.from_path(tmp_path / 'c.pcd')
    assert tuple(pc.fields) == CLOUD_DTYPE.names
    assert all(np.dtype(t) == np.float32 for t in pc.types)
    assert pc.points == len(cloud)
    np.testing.assert_array_equal(pc.numpy(CLOUD_DTYPE.names),
                                  np.column_stack([cloud[n] for n in CLOUD_DTYPE.names]))
    header = (tmp_path / 'c.pcd').read_bytes().split(b'DATA binary\n')[0].decode()
    assert 'TYPE F F F F F' in header and 'SIZE 4 4 4 4 4' in header
    assert 'rgb' not in header  # no colour packed as an unsigned integer (PCL reads it as NaN)


@pytest.mark.parametrize('suffix', ['.ply', '.pcd'])
def test_open3d_reads_the_coordinates(tmp_path, suffix):
    import open3d as o3d

    cloud = _cloud()
    save_cloud(cloud, tmp_path / f'c{suffix}')
    pts = np.asarray(o3d.io.read_point_cloud(str(tmp_path / f'c{suffix}')).points)
    np.testing.assert_allclose(pts, np.column_stack([cloud['x'], cloud['y'], cloud['z']]),
                               rtol=0, atol=1e-7)


@pytest.mark.parametrize('suffix', ['.ply', '.pcd'])
def test_empty_cloud(tmp_path, suffix):
    path = save_cloud(np.empty(0, CLOUD_DTYPE), tmp_path / f'e{suffix}')
    assert load_cloud(path).shape == (0,)


def test_bad_input_is_refused_and_writes_nothing(tmp_path):
    with pytest.raises(ValueError, match='extension'):
        save_cloud(_cloud(), tmp_path / 'c.xyz')
    with pytest.raises(ValueError, match='dtype'):
        save_cloud(np.zeros((4, 3), np.float32), tmp_path / 'c.ply')
    assert not list(tmp_path.iterdir())
    save_cloud(_cloud(), tmp_path / 'c.pcd')
    cut = tmp_path / 'cut.pcd'
    cut.write_bytes((tmp_path / 'c.pcd').read_bytes()[:-3])
    with pytest.raises(ValueError, match='does not match'):
        load_cloud(cut)
    other = tmp_path / 'o.ply'
    other.write_bytes(b'ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n'
                      b'end_header\n1\n')
    with pytest.raises(ValueError, match='does not match'):
        load_cloud(other)


def _pcl_tool(name):
    """PCL's own converter (Debian pcl-tools, installed by `make test`)."""
    import shutil

    path = shutil.which(name)
    assert path, f'{name} not found: Debian pcl-tools (make test installs it)'
    return path


def test_pcl_reads_our_pcd_and_writes_every_field_to_ply(tmp_path):
    """PCL's pcl_pcd2ply loads our PCD with every field; its binary PLY holds them unchanged."""
    import subprocess

    cloud = _cloud()
    save_cloud(cloud, tmp_path / 'ours.pcd')
    out = subprocess.run([_pcl_tool('pcl_pcd2ply'), '-format', '1', '-use_camera', '0',
                          str(tmp_path / 'ours.pcd'), str(tmp_path / 'pcl.ply')],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    assert 'Available dimensions: x y z intensity width' in out.stdout, out.stdout
    vertex = PlyData.read(str(tmp_path / 'pcl.ply'))['vertex']
    assert [p.name for p in vertex.properties] == list(CLOUD_DTYPE.names)
    for name in CLOUD_DTYPE.names:
        np.testing.assert_array_equal(vertex[name], cloud[name])


@pytest.mark.parametrize('fmt', ['0', '1'])  # PCL's ascii and binary PCD
def test_pcl_reads_our_ply_and_writes_every_field_to_pcd(tmp_path, fmt):
    """PCL's pcl_ply2pcd loads our PLY with every field; pypcd4 reads them back from its PCD."""
    import subprocess

    cloud = _cloud()
    save_cloud(cloud, tmp_path / 'ours.ply')
    out = subprocess.run([_pcl_tool('pcl_ply2pcd'), '-format', fmt, str(tmp_path / 'ours.ply'),
                          str(tmp_path / 'pcl.pcd')], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stdout + out.stderr
    assert 'Available dimensions: x y z intensity width' in out.stdout, out.stdout
    pc = PointCloud.from_path(tmp_path / 'pcl.pcd')
    assert tuple(pc.fields) == CLOUD_DTYPE.names and pc.points == len(cloud)
    back = pc.numpy(CLOUD_DTYPE.names)
    for i, name in enumerate(CLOUD_DTYPE.names):
        if fmt == '1':
            np.testing.assert_array_equal(back[:, i], cloud[name])
        else:  # PCL prints 8 significant digits; float32 needs 9 to be exact
            np.testing.assert_allclose(back[:, i], cloud[name], rtol=1e-7, atol=0)
