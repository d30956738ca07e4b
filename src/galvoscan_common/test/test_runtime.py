"""Process settings: what children get, and that mallopt really stops the page faults."""

import os
import signal
import subprocess
import sys
import textwrap

from galvoscan_common.runtime import (
    ENV,
    FASTDDS_PROFILE,
    PROFILE_VARS,
    SHM_DIR,
    child_env,
    remove_zombie_shm_segments,
)

# Makes three copies of a 389 kB buffer (one 720x540 image: a take, a Python bytes, a
# message) and frees them, 300 times, and prints the minor page faults.
_FAULTS = textwrap.dedent('''
    import resource, sys
    from galvoscan_common.runtime import tune_this_process
    if sys.argv[1] == 'tuned':
        assert tune_this_process()
    src = bytes(720 * 540)
    def frame():
        a, b, c = bytearray(src), bytearray(src), bytearray(src)
        del a, b, c
    for _ in range(20):
        frame()
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(300):
        frame()
    print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
''')


def _faults(mode, env):
    out = subprocess.run([sys.executable, '-c', _FAULTS, mode], env=env, check=True,
                         capture_output=True, text=True)
    return int(out.stdout.strip())


def test_child_env_adds_the_settings_without_overriding_the_user():
    env = child_env({'PATH': '/bin', 'OPENBLAS_NUM_THREADS': '4'})
    assert env['PATH'] == '/bin' and env['OPENBLAS_NUM_THREADS'] == '4'
    assert env['MALLOC_MMAP_THRESHOLD_'] == ENV['MALLOC_MMAP_THRESHOLD_']
    assert env['MALLOC_TRIM_THRESHOLD_'] == ENV['MALLOC_TRIM_THRESHOLD_']


def test_image_sized_copies_stop_page_faulting_once_tuned():
    """Untuned, glibc returns the freed top of the heap to the kernel (its trim threshold
    follows twice the largest block freed), so every frame's copies fault their pages in
    again. Tuned (by mallopt, or by the environment a child gets), the pages are reused."""
    plain = {k: v for k, v in child_env().items() if not k.startswith('MALLOC_')}
    untuned = _faults('plain', plain)
    assert untuned > 300 * 50
    assert _faults('tuned', plain) < 300
    assert _faults('plain', child_env(plain)) < 300


def test_fastdds_profile_only_when_nothing_else_is_chosen():
    assert FASTDDS_PROFILE.is_file()
    env = child_env({})
    assert [env[k] for k in PROFILE_VARS] == [str(FASTDDS_PROFILE)] * 2
    for key in PROFILE_VARS:
        mine = child_env({key: '/mine.xml'})
        assert [mine.get(k) for k in PROFILE_VARS].count('/mine.xml') == 1
        assert str(FASTDDS_PROFILE) not in mine.values()
    assert not set(PROFILE_VARS) & set(child_env({'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'}))


# Creates a participant and prints the sizes of the Fast DDS shared-memory segments mapped.
_SEGMENTS = textwrap.dedent('''
    import os, sys
    from galvoscan_common.runtime import tune_this_process
    if sys.argv[1] == 'tuned':
        tune_this_process()
    import rclpy
    rclpy.init()
    node = rclpy.create_node('segment_probe')
    sizes = set()
    with open(f'/proc/{os.getpid()}/maps') as maps:
        for line in maps:
            if '/dev/shm/fastrtps_' in line:
                lo, hi = (int(x, 16) for x in line.split()[0].split('-'))
                sizes.add(hi - lo)
    node.destroy_node()
    rclpy.shutdown()
    print(max(sizes))
''')


def _largest_segment(mode, env):
    out = subprocess.run([sys.executable, '-c', _SEGMENTS, mode], env=env, check=True,
                         capture_output=True, text=True, timeout=60)
    return int(out.stdout.strip().splitlines()[-1])


def test_fastdds_really_loads_the_profile():
    """The participant's own shared-memory segment has the profile's size, whether the
    profile comes from the environment a child gets or from ``tune_this_process``; without
    it, Fast DDS's 0.5 MB default (one image) is what a participant gets."""
    import xml.etree.ElementTree as ET

    ns = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    size = int(ET.parse(FASTDDS_PROFILE).getroot().find('.//p:segment_size', ns).text)
    plain = {k: v for k, v in os.environ.items() if k not in PROFILE_VARS}
    assert _largest_segment('plain', plain) < 1024 * 1024
    assert _largest_segment('tuned', plain) >= size
    assert _largest_segment('plain', child_env(plain)) >= size


def test_fastdds_profile_is_valid_xml_with_a_large_shm_segment():
    import xml.etree.ElementTree as ET

    ns = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ET.parse(FASTDDS_PROFILE).getroot()
    sizes = [int(e.text) for e in root.iterfind('.//p:transport_descriptor/p:segment_size', ns)]
    assert sizes and min(sizes) >= 16 * 389 * 1024     # room for 16 images or more


def test_zombie_segments_of_killed_processes_are_removed_and_live_ones_kept(
        shm_segment_owner):
    (dead, dead_segments), (_, live_segments) = shm_segment_owner(), shm_segment_owner()
    assert not set(dead_segments) & set(live_segments)
    assert all(s.parent == SHM_DIR for s in dead_segments + live_segments)
    # the profile's 32 MB segment: it reached them through child_env
    assert max(s.stat().st_size for s in dead_segments) >= 32 * 1024 * 1024
    assert not set(remove_zombie_shm_segments()) & set(dead_segments + live_segments)
    dead.send_signal(signal.SIGKILL)
    dead.wait(10)
    assert all(s.is_file() and _lock(s).is_file() for s in dead_segments)    # left behind
    assert set(dead_segments) <= set(remove_zombie_shm_segments())
    assert not any(s.exists() or _lock(s).exists() for s in dead_segments)
    assert all(s.is_file() and _lock(s).is_file() for s in live_segments)    # kept


def _lock(segment):
    return segment.with_name(segment.name + '_el')


def test_zombie_cleaning_leaves_other_files_and_a_missing_directory_alone(tmp_path):
    (tmp_path / 'fastrtps_port7411_el').write_bytes(b'')
    (tmp_path / 'fastrtps_0123456789abcdef').write_bytes(b'x')
    (tmp_path / 'fastrtps_0123456789abcdef_el').write_bytes(b'')
    (tmp_path / 'unrelated_el').write_bytes(b'')
    assert remove_zombie_shm_segments(tmp_path) == [tmp_path / 'fastrtps_0123456789abcdef']
    assert sorted(p.name for p in tmp_path.iterdir()) == ['fastrtps_port7411_el',
                                                          'unrelated_el']
    assert remove_zombie_shm_segments(tmp_path / 'missing') == []


def test_the_startup_heap_is_frozen_out_of_full_collections():
    """After freeze_startup_heap a full collection no longer walks what start-up made."""
    code = textwrap.dedent('''
        import gc
        from galvoscan_common.runtime import freeze_startup_heap
        keep = [[i] for i in range(200_000)]                # long-lived, like rclpy's
        gc.collect()
        before = len(gc.get_objects(generation=2))
        frozen = freeze_startup_heap()
        after = len(gc.get_objects(generation=2))
        late = [[i] for i in range(10)]                     # made after: still collected
        gc.collect()
        print(before, frozen, after, len(gc.get_objects(generation=2)) - after)
    ''')
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True).stdout.split()
    before, frozen, after, late = map(int, out)
    assert before > 200_000 and frozen > 200_000
    assert after == 0 and late >= 10


def test_tests_and_benchmarks_draw_their_dds_domains_apart():
    import random

    from galvoscan_common.runtime import RUN_DOMAINS, TEST_DOMAINS, private_domain

    assert TEST_DOMAINS[1] < RUN_DOMAINS[0]
    rng = random.Random(0)
    runs = {private_domain(rng) for _ in range(2000)}
    tests = {private_domain(rng, test=True) for _ in range(2000)}
    assert not runs & tests
    assert min(runs) == RUN_DOMAINS[0] and max(runs) == RUN_DOMAINS[1]
    assert min(tests) == TEST_DOMAINS[0] and max(tests) == TEST_DOMAINS[1]
