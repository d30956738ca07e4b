"""The family benchmark deletes a passed rig's recorded bags and keeps everything else."""

import importlib.util
from pathlib import Path

_spec = importlib.util.spec_from_file_location(
    'rig_family_bench', Path(__file__).parents[1] / 'benchmarks' / 'rig_family.py')
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def test_drop_bags_deletes_only_calibration_data(tmp_path):
    ev = tmp_path / 'seed_000' / 'evaluation'
    keep = [ev / 'metrics.json', ev / 'calibration.yaml', ev / 'logs' / 'driver.log',
            ev / 'by_distance' / '650' / 'metrics.json']
    bags = [ev / 'calibration_data' / 'dynamic_camera' / 'bag_0.mcap',
            ev / 'by_distance' / '650' / 'calibration_data' / 'laser' / 'bag_0.mcap']
    for i, f in enumerate(keep + bags):
        f.parent.mkdir(parents=True, exist_ok=True)
        f.write_bytes(b'x' * (100 + i))
    freed = bench.drop_bags(tmp_path / 'seed_000')
    assert freed == sum(100 + i for i in range(len(keep), len(keep) + len(bags)))
    assert all(f.exists() for f in keep)
    assert not any(p.name == 'calibration_data' for p in tmp_path.rglob('*'))
    assert bench.drop_bags(tmp_path / 'seed_000') == 0  # nothing left to delete
