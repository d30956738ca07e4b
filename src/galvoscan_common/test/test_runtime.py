"""Process settings: what children get, and that mallopt really stops the page faults."""

import subprocess
import sys
import textwrap

from galvoscan_common.runtime import ENV, FASTDDS_PROFILE, child_env

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
    assert child_env({})['FASTDDS_DEFAULT_PROFILES_FILE'] == str(FASTDDS_PROFILE)
    assert child_env({'FASTRTPS_DEFAULT_PROFILES_FILE': '/mine.xml'}).get(
        'FASTDDS_DEFAULT_PROFILES_FILE') is None
    assert child_env({'FASTDDS_DEFAULT_PROFILES_FILE': '/mine.xml'})[
        'FASTDDS_DEFAULT_PROFILES_FILE'] == '/mine.xml'
    assert 'FASTDDS_DEFAULT_PROFILES_FILE' not in child_env(
        {'RMW_IMPLEMENTATION': 'rmw_cyclonedds_cpp'})


def test_fastdds_profile_is_valid_xml_with_a_large_shm_segment():
    import xml.etree.ElementTree as ET

    ns = {'p': 'http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles'}
    root = ET.parse(FASTDDS_PROFILE).getroot()
    sizes = [int(e.text) for e in root.iterfind('.//p:transport_descriptor/p:segment_size', ns)]
    assert sizes and min(sizes) >= 16 * 389 * 1024     # room for 16 images or more
