"""``python -m galvo_driver.twin_node``: a rig's hardware-in-the-loop twin as a process.

Starts a :class:`~galvo_driver.twin.Twin` (the board firmware in simavr behind a pty, its
trigger output wired to Aravis' fake GigE Vision camera, which renders each exposure with
the simulator) and prints one line on stdout once both are up::

    TWIN_READY {"backend": "rig", "serial_port": "/dev/pts/N", "camera_serial": ...}

the ``galvo_driver`` parameters of a ``rig`` backend on it (JSON). It then serves, as the
node ``twin``:

    sim/set_scene  galvoscan_msgs/SetScene: the scene the camera renders (an operator's
                   hands placing targets in front of the twin's rig)

until SIGINT/SIGTERM, which stop the board and the camera.

Usage::

    python -m galvo_driver.twin_node --rig reference --scene stair_block --seed 0 \\
        --workdir twin_logs
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
from pathlib import Path


def _make_node(twin):
    from galvoscan_msgs.srv import SetScene
    from rclpy.node import Node

    from galvoscan_common.boundary import CallbackErrors, guard_service

    node = Node('twin')
    errors = CallbackErrors()

    def on_set_scene(req, resp):
        if req.scene_yaml:
            text = req.scene_yaml
        elif req.scene_path:
            try:
                text = Path(req.scene_path).read_text()
            except OSError as exc:
                resp.success, resp.message = False, f'{req.scene_path}: {exc}'
                return resp
        else:
            resp.success, resp.message = False, 'scene_yaml or scene_path needed'
            return resp
        try:
            resp.objects = twin.set_scene(text)
        except ValueError as exc:
            resp.success, resp.message = False, str(exc)
            return resp
        resp.success = True
        return resp

    node.create_service(SetScene, 'sim/set_scene',
                        guard_service('sim/set_scene', on_set_scene, node.get_logger(), errors))
    return node


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog='python -m galvo_driver.twin_node',
                                description=__doc__.split('\n')[0])
    p.add_argument('--rig', default='reference', help='simulator rig (name or YAML)')
    p.add_argument('--scene', default='stair_block', help='starting scene (name or YAML)')
    p.add_argument('--seed', type=int, default=0, help='simulator seed')
    p.add_argument('--serial', default='GSTWIN0', help="the camera's serial number")
    p.add_argument('--boot-count', type=int, default=1, help="the board's boot counter")
    p.add_argument('--rate', type=float, default=1.0,
                   help="the board's simulated seconds per wall-clock second (0 < rate <= 1; "
                        'below 1 a loaded host has more time before the watchdog trips)')
    p.add_argument('--workdir', default=None,
                   help='folder of the board and render logs (default: a temporary one)')
    args, ros_args = p.parse_known_args(argv)

    import rclpy

    from galvo_driver.twin import Twin
    from galvoscan_common.executor import spin_nodes
    from galvoscan_common.runtime import tune_this_process

    tune_this_process()
    try:
        twin = Twin(args.rig, args.scene, args.seed, serial=args.serial,
                    boot_count=args.boot_count, workdir=args.workdir, rate=args.rate).start()
    except (ValueError, RuntimeError, OSError) as exc:
        print(f'twin: {exc}', file=sys.stderr, flush=True)
        return 1
    node = None
    try:
        print('TWIN_READY ' + json.dumps(twin.driver_parameters()), flush=True)
        rclpy.init(args=ros_args or None)
        node = _make_node(twin)
        spin_nodes([node])
    except KeyboardInterrupt:
        pass
    finally:
        # a second Ctrl-C must not stop the board and the camera half-way
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        twin.close()
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
