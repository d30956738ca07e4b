"""``galvoscan rig``: draw a plausible rig of the family, re-set one for a distance, check one.

    galvoscan rig random --seed N [--distance Z] [--sensor S] [--bit-depth B] [--head H]
        [--laser below|above|left|right] --out FILE
    galvoscan rig reset --rig FILE --distance Z --out FILE
    galvoscan rig check FILE [--distance Z]

Distances are working distances in metres (stand-off from the G1 exit mirror, 0.1 to 1.0);
see :mod:`galvoscan_sim.rig_family` for what a drawn rig varies and the ranges.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import yaml

from galvoscan_sim import load_rig, rig_family
from galvoscan_sim.rig import RIG_FILES


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog='galvoscan rig', description=__doc__.split('\n')[0])
    sub = p.add_subparsers(dest='action', required=True)
    r = sub.add_parser('random', help='draw a random, physically valid rig of the family')
    r.add_argument('--seed', type=int, required=True, help='same seed, same rig (>= 0)')
    r.add_argument('--distance', help='working distance [m], 0.1 to 1.0 (default: drawn)')
    r.add_argument('--sensor', choices=sorted(rig_family.SENSORS),
                   help='camera sensor class (default: drawn)')
    r.add_argument('--bit-depth', type=int, help='output bit depth the sensor offers '
                   '(8, 10, 12 or 16; default: drawn)')
    r.add_argument('--head', choices=sorted(rig_family.HEADS),
                   help='galvo head class of both heads (default: drawn)')
    r.add_argument('--laser', choices=list(rig_family.LASER_SIDES),
                   help='where the laser head sits, seen from the camera: below or above '
                        '(stripe along the image rows), left or right (beside it: stripe '
                        'along the columns) (default: drawn)')
    r.add_argument('--out', required=True, help='rig YAML file to write')
    s = sub.add_parser('reset', help='re-set a rig for another working distance')
    s.add_argument('--rig', required=True, help='rig YAML file (or a shipped name)')
    s.add_argument('--distance', required=True, help='working distance [m], 0.1 to 1.0')
    s.add_argument('--out', required=True, help='rig YAML file to write')
    c = sub.add_parser('check', help='check a rig with the simulator')
    c.add_argument('rig', help='rig YAML file (or a shipped name)')
    c.add_argument('--distance', help='the working distance [m] it should be set up for')
    return p


class _Dumper(yaml.SafeDumper):
    """Block mappings, flow lists: the layout of the shipped rig files."""


_Dumper.add_representer(
    list, lambda dumper, data: dumper.represent_sequence('tag:yaml.org,2002:seq', data,
                                                         flow_style=True))


def _header(lines: list[str]) -> str:
    return ''.join(f'# {line}\n' for line in lines)


def _write(path: Path, header: list[str], data: dict) -> None:
    """Write ``data`` as YAML under a comment header, atomically; then load it back."""
    text = _header(header) + yaml.dump(data, Dumper=_Dumper, sort_keys=False,
                                            default_flow_style=False, width=95)
    fd, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', dir=path.parent)
    try:
        with os.fdopen(fd, 'w', encoding='utf-8') as f:
            f.write(text)
        load_rig(tmp)                                  # the reader takes it as written
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _out_path(text: str) -> Path:
    path = Path(text)
    if not path.parent.is_dir():
        raise ValueError(f'--out: the directory {str(path.parent)!r} does not exist')
    if path.is_dir():
        raise ValueError(f'--out: {text!r} is a directory, not a file')
    return path


def _random(args) -> int:
    if args.seed < 0:
        raise ValueError(f'--seed: expected a non-negative integer, got {args.seed}')
    distance = None if args.distance is None else rig_family.check_distance(args.distance)
    out = _out_path(args.out)
    build = {'sensor': args.sensor, 'bit_depth': args.bit_depth, 'head': args.head,
             'laser': args.laser}
    data = rig_family.draw_rig(args.seed, distance, build)
    kind = rig_family.build_of(data)
    z = rig_family.working_distance(data)
    how = (f'--distance {args.distance}' if distance is not None
           else 'distance drawn from 0.1..1.0 m')
    _write(out, [
        f'Random rig of the galvoscan family: galvoscan rig random --seed {args.seed} ({how}).',
        'Drawn by galvoscan_sim.rig_family.draw_rig: every Table 3 imperfection and the',
        'geometry (l, d, lens, principal point, G2 placement, triangulation angle) inside',
        'galvoscan_sim.rig_family.RANGES, then set up for the working distance and checked',
        'with the simulator (galvoscan_sim.rig_family.check_rig).',
        f"Build: {kind['sensor']} sensor at {kind['bit_depth']} bits, {kind['head']}-class "
        f"galvo heads, the laser {rig_family.side_words(kind['laser'])}",
        '(galvoscan_sim.rig_family.SENSORS, HEADS, LASER_SIDES).',
        f'Working distance {z:.4f} m (stand-off from the G1 exit mirror); the sheet at',
        'U2 = 0 crosses the optical axis at U1 = 0 at W = '
        + ', '.join(f'{v:.4f}' for v in rig_family.working_point(data)) + ' m.',
        'SI units everywhere: m, rad, V, s; signals in electrons (e-).',
    ], data)
    print(f'{out}: rig {data["name"]}, working distance {z * 1e3:.1f} mm, '
          f"{kind['sensor']} {kind['bit_depth']} bit, {kind['head']} head, laser "
          f"{rig_family.side_words(kind['laser'])}")
    return 0


def load_rig_source(text: str) -> tuple[dict, str]:
    """(parsed rig description, source) of a shipped rig name or a rig YAML path."""
    data, source = RIG_FILES.read(text)
    return data, source


def _reset(args) -> int:
    distance = rig_family.check_distance(args.distance)
    out = _out_path(args.out)
    data, source = load_rig_source(args.rig)
    new = rig_family.reset_for_distance(data, distance)
    _write(out, [
        f'{source} re-set for a working distance of {distance:g} m: galvoscan rig reset',
        '(galvoscan_sim.rig_family.reset_for_distance): G2 head slid to keep the',
        'triangulation angle, sheet re-aimed, lens and laser refocused, power and exposure',
        'adjusted; imperfections unchanged. SI units: m, rad, V, s, e-.',
    ], new)
    print(f'{out}: {source} re-set for {distance * 1e3:.1f} mm')
    return 0


def _check(args) -> int:
    distance = None if args.distance is None else rig_family.check_distance(args.distance)
    data, source = load_rig_source(args.rig)
    problems = rig_family.check_rig(data, distance)
    for p in problems:
        print(f'{source}: {p}', file=sys.stderr)
    if not problems:
        z = rig_family.working_distance(data)
        print(f'{source}: valid; working distance {z * 1e3:.1f} mm')
    return 1 if problems else 0


def main(argv=None) -> int:
    """Run ``galvoscan rig ...`` with ``argv`` (the words after ``rig``); returns the exit
    status (0 done, 1 a rig that fails its check, 2 bad arguments or input)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exc:                      # argparse printed why
        return int(exc.code) if isinstance(exc.code, int) else 2
    action = {'random': _random, 'reset': _reset, 'check': _check}[args.action]
    try:
        return action(args)
    except (ValueError, OSError) as exc:          # ConfigError is a ValueError
        print(f'galvoscan rig {args.action}: {exc}', file=sys.stderr)
        return 2

