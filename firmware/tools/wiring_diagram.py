"""Draw docs/hardware_wiring.png: how the galvo board is wired (docs/hardware.md).

    .venv/bin/python firmware/tools/wiring_diagram.py [--out docs/hardware_wiring.png]

The pins are those of firmware/src/board.h.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib.patches import FancyBboxPatch  # noqa: E402

BOXES = {
    # name: (x, y, w, h, title, colour)
    'pc': (0.2, 7.6, 2.4, 1.2, 'Host PC\n(serial backend)', '#dde7f3'),
    'mega': (4.0, 0.9, 3.4, 7.9, 'Arduino Mega 2560\n(galvo board firmware)', '#d9ecd9'),
    'dac': (9.4, 5.6, 2.9, 3.2, 'AD5754R breakout\nquad 16-bit DAC, +-10 V', '#f3e3c8'),
    'psu': (9.4, 9.3, 2.9, 1.0, '+-15 V supply (linear)', '#eeeeee'),
    'g1': (14.0, 7.6, 2.8, 1.3, 'Galvo driver G1\n(camera pair: pan, tilt)', '#e8dcf0'),
    'g2': (14.0, 5.6, 2.8, 1.3, 'Galvo driver G2\n(laser pair: pan, tilt)', '#e8dcf0'),
    'cam': (9.4, 2.6, 2.9, 1.3, 'Camera\n(trigger input, Line0)', '#dde7f3'),
    'laser': (9.4, 0.7, 2.9, 1.3, 'Line laser\n(TTL enable)', '#f6d5d5'),
    'ilk': (0.2, 1.0, 2.6, 1.6,
            'Interlock loop\n(door switch, key switch,\nE-stop in series)', '#f6d5d5'),
}


def box(ax, name):
    x, y, w, h, title, colour = BOXES[name]
    ax.add_patch(FancyBboxPatch((x, y), w, h, boxstyle='round,pad=0.05', fc=colour,
                                ec='black', lw=1.2))
    ax.text(x + w / 2, y + h - 0.15, title, ha='center', va='top', fontsize=8.5,
            fontweight='bold')


def wire(ax, pts, label, colour='black', label_at=0, dy=0.08, ha='left', style='-'):
    xs, ys = zip(*pts, strict=True)
    ax.plot(xs, ys, style, color=colour, lw=1.6, solid_capstyle='round')
    ax.plot([xs[0], xs[-1]], [ys[0], ys[-1]], 'o', color=colour, ms=3.5)
    (x0, y0), (x1, _) = pts[label_at], pts[label_at + 1]
    ax.text((x0 + x1) / 2 if ha == 'center' else x0 + 0.1, y0 + dy, label, fontsize=7.2,
            color=colour, ha=ha, va='bottom')


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--out', default=str(Path(__file__).resolve().parents[2] / 'docs'
                                         / 'hardware_wiring.png'))
    args = ap.parse_args(argv)
    fig, ax = plt.subplots(figsize=(13.5, 8.2))
    for name in BOXES:
        box(ax, name)
    mx1 = 7.4  # right edge of the Mega
    # host link
    wire(ax, [(2.6, 8.0), (4.0, 8.0)], 'USB\n1 Mbaud', '#1f4e99')
    # SPI + strobes to the DAC
    for y, label in ((8.3, 'D52 SCK -> SCLK'), (7.9, 'D51 MOSI -> SDIN'),
                     (7.5, 'D49 -> /SYNC  (10k pull-up)'), (7.1, 'D48 -> /LDAC  (10k pull-up)')):
        wire(ax, [(mx1, y), (9.4, y)], label, '#8a5a00')
    wire(ax, [(mx1, 6.7), (9.4, 6.7)], '5V -> DVcc,  GND -> DGND', '#555555')
    wire(ax, [(mx1, 6.3), (9.4, 6.3)], 'D53 (SS): output, unconnected', '#999999', style=':')
    ax.text(12.4, 3.25, '20 us high pulse per row;\nexposure must end within\nhalf a period',
            fontsize=6.8, va='center')
    ax.text(10.85, 5.75, 'BIN/2sCOMP -> DGND (offset binary)\n/CLR -> DVcc, REFIN/REFOUT\n'
            '(internal 2.5 V ref)', fontsize=6.8, ha='center', va='bottom')
    # supply
    wire(ax, [(10.85, 9.3), (10.85, 8.8)], '', '#555555')
    ax.text(10.95, 8.95, 'AVDD +15 V, AVSS -15 V, AGND', fontsize=7.2, color='#555555')
    wire(ax, [(12.3, 9.8), (15.4, 9.8), (15.4, 8.9)], 'galvo drivers\' own supply '
         '(per their manual)', '#555555', label_at=0)
    # DAC outputs
    wire(ax, [(12.3, 8.4), (14.0, 8.4)], 'VOUTA: U1_pan', '#6a2c91')
    wire(ax, [(12.3, 8.0), (14.0, 8.0)], 'VOUTB: U1_tilt', '#6a2c91')
    wire(ax, [(12.3, 6.4), (14.0, 6.4)], 'VOUTC: U2_pan', '#6a2c91')
    wire(ax, [(12.3, 6.0), (14.0, 6.0)], 'VOUTD: U2_tilt', '#6a2c91')
    # trigger, laser, interlock
    wire(ax, [(mx1, 3.5), (9.4, 3.5)], 'D11 (OC1A) -> trigger in', '#1f4e99')
    wire(ax, [(mx1, 2.9), (9.4, 2.9)], 'GND -> trigger GND', '#555555')
    wire(ax, [(mx1, 1.6), (9.4, 1.6)], 'D22 -> TTL enable (10k pull-down)', '#b22222')
    wire(ax, [(mx1, 1.0), (9.4, 1.0)], 'GND -> laser driver GND', '#555555')
    wire(ax, [(2.8, 2.2), (4.0, 2.2)], 'D2 (INT4)', '#b22222', dy=0.1)
    wire(ax, [(2.8, 1.4), (4.0, 1.4)], 'GND', '#555555', dy=0.1)
    ax.text(1.5, 0.8, 'closed = laser may run; open (or a cut wire) =\nlaser off, galvos at 0 V, '
            'FAULT to the host', fontsize=7, ha='center', va='top', color='#b22222')
    ax.text(5.7, 1.2, 'pins: firmware/src/board.h', fontsize=7, ha='center', style='italic')
    ax.set_xlim(0, 17.2)
    ax.set_ylim(0, 10.6)
    ax.set_aspect('equal')
    ax.axis('off')
    ax.set_title('galvoscan galvo board: wiring', fontsize=12)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(args.out)


if __name__ == '__main__':
    main()
