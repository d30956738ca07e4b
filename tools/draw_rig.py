#!/usr/bin/env python3
"""Draw the scanner's layout, ray-traced by the simulator: docs/rig.png.

    .venv/bin/python tools/draw_rig.py [--rig reference] [--out docs/rig.png]

Two views of the rig in its world frame W (the nominal V0: x right, y down, z away from the
scanner). The camera's central ray is traced off the actual G1 mirrors at several G1
voltages, and the laser's central beam off the actual G2 mirrors at several G2 voltages, as
the simulator does for every pixel; the dot is the working point, where the laser sheet at
U2 = 0 crosses the camera's axis at U1 = 0.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from galvoscan_sim import load_rig  # noqa: E402
from galvoscan_sim.rig_family import working_point  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
VOLTS = (-10.0, -5.0, 0.0, 5.0, 10.0)


def _to_w(rig, p):
    return (rig.W_T_G @ np.append(p, 1.0))[:3]


def _dir_w(rig, d):
    return rig.W_T_G[:3, :3] @ d


def camera_rays(rig, channel: int, depth: float):
    """(start, end) in W of the central camera ray for each voltage of one G1 channel."""
    out = []
    for u in VOLTS:
        volts = np.zeros(4)
        volts[channel] = u
        th = rig.mirror_angles(rig.applied_voltages(volts))
        o, d = rig.trace_camera_rays(np.zeros((1, 2)), th[0], th[1])
        o, d = _to_w(rig, o[0]), _dir_w(rig, d[0])
        t = (depth - o[2]) / d[2]
        out.append((u, o, o + t * d))
    return out


def laser_beams(rig, depth: float):
    """(start on the G2 tilt mirror, end) in W of the laser's central beam per G2 tilt voltage."""
    out = []
    for u in VOLTS:
        th = rig.mirror_angles(rig.applied_voltages(np.array([0.0, 0.0, 0.0, u])))
        sheet = rig.laser_sheet_G(th[2], th[3])
        n, e = sheet.mirror_plane[:3], sheet.mirror_plane[3]
        src, c = sheet.source, sheet.central
        s = -(n @ src + e) / (n @ c)          # where the beam leaves the tilt mirror
        o, d = _to_w(rig, src + s * c), _dir_w(rig, c)
        t = (depth - o[2]) / d[2]
        out.append((u, o, o + t * d))
    return out


def draw(rig_name: str, out: Path) -> Path:
    rig = load_rig(rig_name)
    wp = working_point(rig)
    depth = 1.15 * wp[2]
    camera = _to_w(rig, rig.G_T_C[:3, 3])
    laser = _to_w(rig, rig.G_T_G2[:3, :3] @ rig.laser.position + rig.G_T_G2[:3, 3])
    fig, axes = plt.subplots(1, 2, figsize=(10, 6.2))
    for ax, (name, axis, channel) in zip(axes, (('side view (y, z)', 1, 1),
                                                ('top view (x, z)', 0, 0)), strict=True):
        for u, a, b in camera_rays(rig, channel, depth):
            ax.plot([a[2], b[2]], [a[axis], b[axis]], color='tab:blue',
                    lw=2.0 if u == 0 else 0.8, alpha=1.0 if u == 0 else 0.6)
        ax.plot([camera[2]], [camera[axis]], 's', color='tab:blue', ms=8, label='camera')
        if axis == 1:
            for u, a, b in laser_beams(rig, depth):
                ax.plot([a[2], b[2]], [a[axis], b[axis]], color='tab:red',
                        lw=2.0 if u == 0 else 0.8, alpha=1.0 if u == 0 else 0.6)
            ax.plot([laser[2]], [laser[axis]], '^', color='tab:red', ms=8, label='line laser')
            ax.plot([], [], color='tab:red', label='laser beam off G2, U2 = -10..10 V')
        which = 'tilt' if axis else 'pan'
        ax.plot([], [], color='tab:blue', label=f'camera axis off G1, U1 {which} = -10..10 V')
        ax.plot([wp[2]], [wp[axis]], 'ko', ms=6, label='working point')
        ax.set_xlabel('z, away from the scanner [m]')
        ax.set_ylabel(f'{"y, down" if axis else "x, right"} [m]')
        ax.set_title(name)
        ax.set_aspect('equal')
        ax.grid(alpha=0.3)
        ax.set_xlim(-0.2, depth)
        ax.set_ylim(*((0.75, -0.75) if axis == 1 else (-0.75, 0.75)))   # y down, as in W
        ax.legend(fontsize=7, loc='upper center', bbox_to_anchor=(0.5, -0.16), ncol=2)
    fig.suptitle(f'galvoscan rig "{rig.name}", ray-traced by the simulator')
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--rig', default='reference')
    p.add_argument('--out', type=Path, default=ROOT / 'docs' / 'rig.png')
    args = p.parse_args(argv)
    print(f'wrote {draw(args.rig, args.out)}')
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
