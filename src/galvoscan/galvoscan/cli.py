"""The ``galvoscan`` command: bring-up, bags, calibration and the main job.

    galvoscan run [--params FILE] [--one-process] [--nodes a,b,c] [--duration S]
    galvoscan scan ...          (start a scan pattern on the running driver and follow it)
    galvoscan record ...        (see galvoscan record --help)
    galvoscan replay ...
    galvoscan bag-recover ...
    galvoscan calibrate STAGE ...
    galvoscan operator [--sim [--seed N] [--exact]]
                                (the calibration's operator: print the running calibration
                                node's instructions and answer them from the keyboard; --sim:
                                place the targets in the simulator as a person would)
    galvoscan evaluate [--rig FILE] [--seed N] [--quick] [--out DIR]
    galvoscan demo [--out DIR]  (the main job on the reference rig: calibrate through the simulated
                                operator, scan, score; what `make demo` runs)
    galvoscan rig random --seed N [--distance Z] --out FILE  (draw a plausible rig)
    galvoscan view [--ws-port 8765] [--http-port 8080] [--host 0.0.0.0] [--no-browser-page]
                                (Foxglove WebSocket and a browser page on the running graph)
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
import tempfile

#: sub-command -> "module:function" taking argv (the rest of the command line).
DELEGATED = {
    'record': 'galvoscan_bag.record_node:main',
    'replay': 'galvoscan_bag.replay_node:main',
    'bag-recover': 'galvoscan_bag.recover:main',
    'calibrate': 'galvoscan.offline:main',
    'operator': 'galvoscan.operator:main',
    'scan': 'galvoscan.scan_client:main',
    'evaluate': 'galvoscan.evaluate:main',
    'view': 'galvoscan_view.view_node:main',
    'rig': 'galvoscan.rig_cli:main',
}


def _delegate(target, argv):
    module, func = target.split(':')
    return getattr(importlib.import_module(module), func)(argv)


def _run(argv):
    from galvoscan import bringup

    parser = argparse.ArgumentParser(prog='galvoscan run',
                                     description='Start the galvoscan graph and supervise it.')
    parser.add_argument('--params', help='parameters YAML (node: ros__parameters: ...)')
    parser.add_argument('--one-process', action='store_true',
                        help='all nodes in this process on one EventsExecutor')
    parser.add_argument('--nodes', default=','.join(bringup.DEFAULT_NODES),
                        help='comma-separated node names (default: %(default)s)')
    parser.add_argument('--duration', type=float, help='stop after this many seconds')
    parser.add_argument('--respawn', action='store_true',
                        help='restart a node that exits unexpectedly (separate processes)')
    parser.add_argument('--log-dir', help="write each node's output to DIR/<node>.log (its "
                        'warnings and errors are printed here too)')
    args = parser.parse_args(argv)
    nodes = [n for n in args.nodes.split(',') if n]
    try:
        # refuse a bad file before starting anything
        workdir = tempfile.mkdtemp(prefix='galvoscan-run-')
        params = bringup.prepare_params(args.params, nodes, workdir)
        if args.one_process:
            bringup.run_one_process(nodes, params, args.duration)
            return 0
        sup = bringup.Supervisor(nodes, params, respawn=args.respawn, log_dir=args.log_dir,
                                 echo=True)
    except ValueError as exc:
        print(f'galvoscan run: {exc}', file=sys.stderr)
        return 2
    return sup.run(args.duration)


def main(argv=None):
    argv = list(sys.argv[1:] if argv is None else argv)
    logging.basicConfig(level=logging.INFO, format='[%(name)s] %(levelname)s %(message)s')
    commands = ['run', *DELEGATED, 'demo']
    if argv and argv[0] not in commands and argv[0] not in ('-h', '--help'):
        print(f"galvoscan: unknown command '{argv[0]}'; one of {', '.join(commands)}\n",
              file=sys.stderr)
    if not argv or argv[0] in ('-h', '--help') or argv[0] not in commands:
        print(__doc__.strip())
        return 0 if argv and argv[0] in ('-h', '--help') else 2
    command, rest = argv[0], argv[1:]
    if command == 'run':
        return _run(rest)
    if command == 'demo':
        rc = _delegate(DELEGATED['evaluate'], ['--demo', *rest])
    else:
        rc = _delegate(DELEGATED[command], rest)
    if rc == 0 and command in ('demo', 'calibrate'):
        # `galvoscan run` on this simulated rig starts its reconstructor from this calibration
        from galvoscan.calibration_memory import remember_from_command

        remember_from_command(command, rest)
    return rc


if __name__ == '__main__':
    sys.exit(main())
