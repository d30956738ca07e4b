"""Bring up the galvoscan graph: every node in one process, or one process per node.

This stands in for ``ros2 launch`` (launch is not installable from PyPI). Parameters come
from one YAML file laid out as ``node_name: ros__parameters: {...}``, exactly as a launch
file would pass it, so the same file works with an apt ROS install.

One process
    All nodes on one ``rclpy.experimental.EventsExecutor``, driven by ``spin_once`` (its
    ``spin()`` ignores SIGINT/SIGTERM in rclpy 7.1). ``MultiThreadedExecutor`` loses most
    500 Hz frames here. With the driver in the process, the extractor's ``intra_process``
    defaults to true: the driver hands it each image and state directly
    (:mod:`galvoscan_common.intra`) and publishes them over DDS only to other subscribers.
Separate processes
    Each node runs its own console script with ``--ros-args --params-file``, with the
    malloc, BLAS and Fast DDS settings of :mod:`galvoscan_common.runtime` in its environment
    (the one-process arrangement applies them to itself). The supervisor
    watches them: a node that exits unexpectedly is logged and, with ``respawn``, restarted
    (at most ``max_respawns`` times); otherwise the graph is stopped. Ctrl-C (SIGINT) or
    SIGTERM stops every child with SIGINT, then SIGTERM, then SIGKILL after timeouts, so the
    driver's ``finally`` puts the galvos in the safe state.
"""

from __future__ import annotations

import importlib
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from galvoscan_common.executor import spin_nodes
from galvoscan_common.runtime import (
    child_env,
    die_with_parent,
    remove_zombie_shm_segments,
    tune_this_process,
)

log = logging.getLogger('galvoscan.bringup')

#: node name -> (console script, "module:Class") of every node the graph can hold.
NODES = {
    'galvo_driver': ('galvo_driver', 'galvo_driver.driver_node:GalvoDriverNode'),
    'stripe_extractor': ('stripe_extractor',
                         'stripe_extractor.extractor_node:StripeExtractorNode'),
    'reconstructor': ('reconstructor', 'reconstructor.reconstructor_node:ReconstructorNode'),
    'calibration': ('calibration_node', 'calibration_tools.calibration_node:CalibrationNode'),
}
DEFAULT_NODES = ('galvo_driver', 'stripe_extractor', 'reconstructor')


def load_params(path: str | os.PathLike | None) -> dict:
    """Read a ``node: ros__parameters: {...}`` YAML file; ``None`` gives ``{}``."""
    if path is None:
        return {}
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except (OSError, yaml.YAMLError) as exc:
        raise ValueError(f'{path}: cannot read parameters: {exc}') from exc
    if not isinstance(data, dict):
        raise ValueError(f'{path}: expected a mapping of node names, got {type(data).__name__}')
    for node, section in data.items():
        if not isinstance(section, dict) or not isinstance(section.get('ros__parameters'), dict):
            raise ValueError(f"{path}: key '{node}' must hold 'ros__parameters: {{...}}'")
    return data


def with_sim_starting_calibration(params_file, nodes, workdir) -> str | None:
    """The parameters file to start ``nodes`` with, the calibration node given a start.

    The calibration node starts from the file its ``initial_calibration`` names. When it
    names none and the driver simulates a rig (backend ``sim``, the default), this writes
    that rig's design values (:func:`galvoscan.simulated_rig.nominal_calibration`) to
    ``workdir/nominal_calibration.yaml`` and returns a copy of the parameters that points
    the calibration node at it. Otherwise ``params_file`` is returned unchanged.

    Raises
    ------
    ValueError
        An unreadable parameters file or an unknown rig.
    """
    params = load_params(params_file)
    if 'calibration' not in nodes:
        return params_file
    cal = dict(params.get('calibration', {}).get('ros__parameters', {}))
    driver = params.get('galvo_driver', {}).get('ros__parameters', {})
    if cal.get('initial_calibration') or driver.get('backend', 'sim') != 'sim':
        return params_file
    rig = driver.get('rig', 'reference')
    workdir = Path(workdir)
    start = _write_design_values(rig, workdir / 'nominal_calibration.yaml')
    cal['initial_calibration'] = str(start)
    params['calibration'] = {'ros__parameters': cal}
    out = _write_params(params, workdir, 'params.yaml')
    log.info('calibration starts from the design values of sim rig %s (%s)', rig, start)
    return out


def _write_design_values(rig: str, path: Path) -> Path:
    """Write the design values of sim rig ``rig`` as a calibration file at ``path``.

    Raises ``ValueError`` for an unknown rig.
    """
    from galvoscan.simulated_rig import nominal_calibration
    from reconstructor import calibration_file

    try:
        nominal = nominal_calibration(rig)
    except OSError as exc:
        raise ValueError(f'rig {rig}: {exc}') from None
    path.parent.mkdir(parents=True, exist_ok=True)
    calibration_file.save(nominal, path)
    return path


def with_reconstructor_calibration(params_file, nodes, workdir) -> str | None:
    """The parameters file to start ``nodes`` with, the reconstructor given a calibration.

    When the reconstructor is among ``nodes``, its ``calibration_file`` is empty and the
    driver simulates a rig (backend ``sim``, the default), this gives it the calibration that
    ``galvoscan demo`` or ``galvoscan calibrate`` wrote last for that rig
    (:mod:`galvoscan.calibration_memory`), or else the rig's design values
    (:func:`galvoscan.simulated_rig.nominal_calibration`, written to ``workdir``), and logs
    which. Otherwise ``params_file`` is returned unchanged, and a reconstructor without a
    calibration on a real rig is named in a warning.

    Raises
    ------
    ValueError
        An unreadable parameters file or an unknown rig.
    """
    params = load_params(params_file)
    if 'reconstructor' not in nodes:
        return params_file
    recon = dict(params.get('reconstructor', {}).get('ros__parameters', {}))
    driver = params.get('galvo_driver', {}).get('ros__parameters', {})
    if recon.get('calibration_file'):
        log.info('reconstructor uses the calibration file of the parameters: %s',
                 recon['calibration_file'])
        return params_file
    if driver.get('backend', 'sim') != 'sim':
        log.warning('the reconstructor has no calibration_file: it skips every frame until '
                    'one is loaded (set reconstructor: calibration_file in the parameters)')
        return params_file
    from galvoscan import calibration_memory

    rig = driver.get('rig', 'reference')
    record = calibration_memory.last(rig)
    if record is not None:
        recon['calibration_file'] = record['path']
        log.info('reconstructor uses the calibration %s wrote last: %s (sim rig %s, %s)',
                 record.get('written_by', 'galvoscan'), record['path'], rig,
                 record.get('written_at', ''))
    else:
        start = _write_design_values(rig, Path(workdir) / 'design_values.yaml')
        recon['calibration_file'] = str(start)
        log.info('reconstructor uses the design values of sim rig %s: no calibration has been '
                 'made for it yet (make demo, or galvoscan calibrate all --sim, makes one)', rig)
    params['reconstructor'] = {'ros__parameters': recon}
    return _write_params(params, workdir, 'params_reconstructor.yaml')


def _write_params(params: dict, workdir, name: str) -> str:
    """Write a completed parameters file into ``workdir``; its path."""
    out = Path(workdir) / name
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(params, sort_keys=False))
    return str(out)


def with_stripe_orientation(params_file, nodes, workdir) -> str | None:
    """The parameters file to start ``nodes`` with, the stripe extractor oriented the way
    the rig's stripe runs and the driver's raster stepping the G1 axis across it.

    When the stripe extractor is among ``nodes`` and its ``orientation`` is not given (or
    the driver and its ``raster_g1_axis``), it is taken from the rig's calibration
    (``reconstructor.planning.stripe_layout``: along the rows for a laser below or above
    the camera, along the columns beside it): the reconstructor's ``calibration_file``,
    else the calibration node's ``initial_calibration``, else (backend ``sim``) the
    simulated rig's design values.
    A copy of the parameters with it is written to ``workdir`` and returned; otherwise
    ``params_file`` is returned unchanged.

    Raises
    ------
    ValueError
        An unreadable parameters or calibration file, or an unknown rig.
    """
    params = load_params(params_file)
    ext = dict(params.get('stripe_extractor', {}).get('ros__parameters', {}))
    drv = dict(params.get('galvo_driver', {}).get('ros__parameters', {}))
    wants_ext = 'stripe_extractor' in nodes and not ext.get('orientation')
    wants_drv = 'galvo_driver' in nodes and not drv.get('raster_g1_axis')
    if not (wants_ext or wants_drv):
        return params_file
    from reconstructor import calibration_file
    from reconstructor.planning import stripe_layout

    source = None
    for node, key in (('reconstructor', 'calibration_file'),
                      ('calibration', 'initial_calibration')):
        path = params.get(node, {}).get('ros__parameters', {}).get(key)
        if path and Path(path).is_file():
            source = Path(path)
            break
    driver = params.get('galvo_driver', {}).get('ros__parameters', {})
    if source is None and driver.get('backend', 'sim') == 'sim':
        source = _write_design_values(driver.get('rig', 'reference'),
                                      Path(workdir) / 'design_values_extractor.yaml')
    if source is None:
        log.warning('stripe_extractor: no calibration to take the stripe direction from; '
                    'it extracts a stripe along the rows (set stripe_extractor: orientation '
                    'for a laser beside the camera)')
        return params_file
    try:
        model = calibration_file.load(source).model
    except (OSError, ValueError) as exc:
        raise ValueError(f'{source}: {exc}') from exc
    layout = stripe_layout(model)
    log.info('the stripe runs along the image %s (%s)',
             'rows' if layout.orientation == 'horizontal' else 'columns', source)
    if wants_ext:
        ext['orientation'] = layout.orientation
        params['stripe_extractor'] = {'ros__parameters': ext}
    if wants_drv:
        drv['raster_g1_axis'] = 'tilt' if layout.across == 1 else 'pan'
        params['galvo_driver'] = {'ros__parameters': drv}
    return _write_params(params, workdir, 'params_extractor.yaml')


def prepare_params(params_file, nodes, workdir) -> str | None:
    """The parameters file both bring-ups (``galvoscan run``, ``launch/galvoscan.launch.py``)
    start ``nodes`` with: ``params_file`` completed, where it leaves them open, with the
    calibration node's start (:func:`with_sim_starting_calibration`), the reconstructor's
    calibration (:func:`with_reconstructor_calibration`) and the stripe's direction for the
    extractor and the driver's raster (:func:`with_stripe_orientation`), written to
    ``workdir`` when anything was added.

    Raises
    ------
    ValueError
        An unreadable parameters or calibration file, or an unknown rig.
    """
    params = with_sim_starting_calibration(params_file, nodes, workdir)
    params = with_reconstructor_calibration(params, nodes, workdir)
    return with_stripe_orientation(params, nodes, workdir)


def _bin(script: str) -> str:
    """The console script installed beside this interpreter (the venv's bin/)."""
    candidate = Path(sys.executable).with_name(script)
    return str(candidate) if candidate.exists() else script


@dataclass
class Child:
    name: str
    argv: list
    proc: subprocess.Popen | None = None
    respawns: int = 0
    started: float = field(default=0.0)


class Supervisor:
    """Start nodes as separate processes, watch them, stop them cleanly."""

    def __init__(self, nodes, params_file=None, respawn=False, max_respawns=3,
                 env=None, log_dir=None, echo=False):
        self.params_file = str(params_file) if params_file else None
        #: with ``log_dir``: also print each node's lines other than INFO and DEBUG to stderr
        self.echo = echo
        self.respawn = respawn
        self.max_respawns = max_respawns
        self.env = child_env(env)
        self.log_dir = Path(log_dir) if log_dir else None
        self.children = []
        for name in nodes:
            if name not in NODES:
                raise ValueError(f"unknown node '{name}'; known: {', '.join(NODES)}")
            argv = [_bin(NODES[name][0]), '--ros-args', '-r', f'__node:={name}']
            if self.params_file:
                argv += ['--params-file', self.params_file]
            self.children.append(Child(name, argv))
        self._stopping = False

    def start(self):
        remove_zombies()
        for child in self.children:
            self._start_child(child)

    def _start_child(self, child):
        out = None
        if self.log_dir:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            out = open(self.log_dir / f'{child.name}.log', 'ab')  # noqa: SIM115
        # a supervisor killed with SIGKILL takes its nodes with it: each gets SIGTERM and
        # runs its safe-state shutdown (the driver leaves the galvos at 0 V, laser off)
        start = out.tell() if out else 0
        child.proc = subprocess.Popen(child.argv, env=self.env, stdout=out,
                                      stderr=subprocess.STDOUT if out else None,
                                      preexec_fn=die_with_parent(signal.SIGTERM))
        if out:
            out.close()  # the child writes to its own descriptor, whatever becomes of us
            if self.echo:
                proc = child.proc
                threading.Thread(target=follow_log, name=f'{child.name}_log', daemon=True,
                                 args=(out.name, start, child.name,
                                       lambda: proc.poll() is not None)).start()
        child.started = time.monotonic()
        log.info('started %s (pid %d)', child.name, child.proc.pid)

    def poll(self) -> bool:
        """Check the children once. Returns False when the graph must stop."""
        for child in self.children:
            rc = child.proc.poll()
            if rc is None or self._stopping:
                continue
            log.error('%s exited with code %s', child.name, rc)
            if self.respawn and child.respawns < self.max_respawns:
                child.respawns += 1
                log.warning('respawning %s (%d/%d)', child.name, child.respawns,
                            self.max_respawns)
                self._start_child(child)
            else:
                return False
        return True

    def run(self, duration=None):
        """Supervise until Ctrl-C/SIGTERM, a child dies (without respawn) or ``duration`` [s]."""
        stop = []

        def _on_signal(signum, _frame):
            stop.append(signum)

        old = {s: signal.signal(s, _on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        t_end = None if duration is None else time.monotonic() + duration
        try:
            self.start()
            while not stop and self.poll():
                if t_end is not None and time.monotonic() > t_end:
                    break
                time.sleep(0.1)
        finally:
            self.stop()
            for s, handler in old.items():
                signal.signal(s, handler)
        return 0 if not any(c.proc.returncode not in (0, -2, -15, None)
                            for c in self.children) else 1

    def stop(self, timeout=10.0):
        """SIGINT every child, then SIGTERM, then SIGKILL once ``timeout`` has passed."""
        self._stopping = True
        for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGKILL):
            alive = [c for c in self.children if c.proc and c.proc.poll() is None]
            if not alive:
                return
            for child in alive:
                log.info('sending %s to %s', signal.Signals(sig).name, child.name)
                child.proc.send_signal(sig)
            deadline = time.monotonic() + timeout
            while time.monotonic() < deadline and any(c.proc.poll() is None for c in alive):
                time.sleep(0.05)
            if sig == signal.SIGKILL:
                remove_zombies()


#: a ROS console line's level tag, e.g. ``[INFO] [1764272400.123456789] [reconstructor]: ...``
_QUIET_LEVEL = re.compile(rb'^\[(INFO|DEBUG)\]')


def follow_log(path, offset: int, name: str, finished, console=None, poll_s: float = 0.1):
    """Print a node's log lines other than INFO and DEBUG to stderr as the node writes them.

    The node writes its output straight into its log file (so nothing is lost if the
    supervisor dies); this follows the file from ``offset`` and prints its warnings, errors
    and anything written outside the ROS logger (a traceback), prefixed ``[name]``, until
    ``finished()`` is true and the file has no more lines.
    """
    console = console or sys.stderr

    def emit(line: bytes):
        if line.strip() and not _QUIET_LEVEL.match(line):
            text = line.decode('utf-8', 'replace').rstrip('\n')
            print(f'[{name}] {text}', file=console, flush=True)

    try:
        with open(path, 'rb') as f:
            f.seek(offset)
            pending = b''
            while True:
                line = f.readline()
                if line.endswith(b'\n'):
                    emit(pending + line)
                    pending = b''
                    continue
                pending += line               # end of the file so far: maybe half a line
                if finished():
                    for rest in (pending + f.read()).splitlines():
                        emit(rest)
                    return
                time.sleep(poll_s)
    except (OSError, ValueError):
        pass  # the console or the log went away while stopping


def remove_zombies():
    """Remove the shared-memory segments that dead DDS participants left, and say so."""
    removed = remove_zombie_shm_segments()
    if removed:
        log.info('removed %d Fast DDS shared-memory segments of processes that are gone',
                 len(removed))


def node_class(name):
    module, cls = NODES[name][1].split(':')
    return getattr(importlib.import_module(module), cls)


#: nodes whose service callbacks block while they call other nodes' services
BLOCKING_NODES = ('calibration',)


def _spin_in_thread(node):
    import threading

    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    ex = SingleThreadedExecutor()
    ex.add_node(node)

    def spin():
        while rclpy.ok():
            try:
                ex.spin_once(timeout_sec=0.1)
            except Exception:  # noqa: BLE001 - context shut down under us
                break

    thread = threading.Thread(target=spin, name=f'{node.get_name()}_executor', daemon=True)
    thread.start()
    return thread


def composed_defaults(name: str, nodes) -> dict:
    """Constructor defaults of node ``name`` when ``nodes`` share its process."""
    if name == 'stripe_extractor' and 'galvo_driver' in nodes:
        return {'intra_process_default': True}
    return {}


def run_one_process(nodes, params_file=None, duration=None, args=None):
    """Run ``nodes`` in this process on one EventsExecutor until Ctrl-C or ``duration`` [s]."""
    import rclpy
    from rclpy.executors import ExternalShutdownException

    tune_this_process()
    remove_zombies()
    ros_args = ['--ros-args'] + (['--params-file', str(params_file)] if params_file else [])
    rclpy.init(args=(args or []) + ros_args)
    instances = []
    try:
        on_executor = []
        for name in nodes:
            node = node_class(name)(**composed_defaults(name, nodes))
            instances.append(node)
            if name in BLOCKING_NODES:
                # its services wait on other nodes' services: give it its own executor
                _spin_in_thread(node)
            else:
                on_executor.append(node)
        spin_nodes(on_executor, duration=duration)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        for node in reversed(instances):
            safe = getattr(node, 'make_safe', None)
            if safe is not None:
                safe()
            node.destroy_node()
        rclpy.try_shutdown()
