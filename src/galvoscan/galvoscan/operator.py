"""The operator's side of calibration: the simulated operator, and a person at the console.

``galvoscan operator`` prints the calibration node's instructions and sends what the person
types (placed, undo, skip, done). The rest of this module is the simulated operator, which
places the calibration targets in the simulator as a person would.

``galvoscan operator --sim`` (and ``galvoscan evaluate`` / ``demo`` while they calibrate)
runs it. It reads only what any operator reads, the calibration node's latched
``calibration/instruction`` (galvoscan_msgs/CalibrationInstruction), places the target it
names through ``sim/set_scene`` and answers through ``calibration/operator``
(galvoscan_msgs/OperatorAction). It is the only caller of ``sim/set_scene`` while a rig
calibrates.

A person's imprecision, every draw from one seeded generator and logged:

- position within +-60 mm of the centre asked for (uniform per axis); a target asked for on
  the laser line is aimed at the visible line, within +-10 mm across it
  (:data:`PERSON`);
- tilt within +-8 deg of the orientation asked for (a random axis);
- while "holding still", a small motion (+-0.01 mm: the target rests on a stand);
- now and then a person's mistake (:data:`MISTAKES`): the target put outside the region,
  a board turned a quarter or half turn in its plane, the target nudged during the
  capture.

``errors=0`` gives the zero-error operator: every target exactly where it was asked (the
reference the family benchmark compares the operator against).
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from dataclasses import dataclass, field

import numpy as np

log = logging.getLogger('galvoscan.operator')


@dataclass(frozen=True)
class Person:
    """How precisely a person places a target (half widths of uniform errors)."""

    position_m: float = 0.06
    laser_line_m: float = 0.01
    tilt_rad: float = math.radians(8.0)
    hold_m: float = 1e-5
    #: chance per placement of one of the mistakes below
    mistake_rate: float = 0.08


#: A person's imprecision (the calibration brief: within about 10 cm by eye, 10 mm on a
#: visible line, a rough tilt).
PERSON = Person()
#: The zero-error operator: targets exactly where asked.
EXACT = Person(0.0, 0.0, 0.0, 0.0, 0.0)
#: How long a placement waits for a scan that still runs before the target is put [s]: the
#: simulator changes no scene mid-scan, and the slowest search scans (81 views at 50 Hz on a
#: loaded machine) end within it.
SCAN_WAIT_S = 30.0
#: The mistakes a person makes now and then: put it outside the region asked for; turn a
#: board a quarter or half turn in its plane; nudge it during the capture.
MISTAKES = ('outside_region', 'turned', 'moved_during_capture')


def _rot(axis_angle) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(axis_angle, dtype=np.float64)).as_matrix()


def _quat_matrix(q) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, dtype=np.float64)).as_matrix()


def scene_text(kind: str, spec: dict, T) -> str:
    """The simulator scene of one kit target at ``V0_T_target`` (the scene frame is V0)."""
    from scipy.spatial.transform import Rotation

    from calibration_tools.capture_plans import circle_board_scene_yaml
    from calibration_tools.operator_flow import target_from_spec
    from calibration_tools.placement import board_scene_yaml, sphere_scene_yaml

    target = target_from_spec(kind, spec)
    T = np.asarray(T, dtype=np.float64)
    if kind == 'spheres':  # a robot's: exactly where asked
        from calibration_tools.hand_eye import artefact_scene_yaml

        return artefact_scene_yaml(target[1], target[0])
    if kind == 'sphere':
        gap = spec.get('backdrop_gap')
        wall = None if gap is None else float(T[2, 3] + target + float(gap))
        return sphere_scene_yaml(T[:3, 3], target, wall)
    if kind == 'circle_board':
        return circle_board_scene_yaml(T, target)
    return board_scene_yaml(target, T[:3, 3], Rotation.from_matrix(T[:3, :3]).as_rotvec())


@dataclass
class Draw:
    """One placement as the person made it: the pose and what went into it."""

    T: np.ndarray
    error_m: np.ndarray
    tilt_rad: float
    mistake: str = ''
    notes: list = field(default_factory=list)
    #: the mistake was forced (tests); ``again``: it is a forced nudge made once more
    forced: bool = False
    again: bool = False


def draw_placement(instr: dict, rng: np.random.Generator, person: Person = PERSON) -> Draw:
    """Where a person puts the target an instruction asks for.

    Parameters
    ----------
    instr : dict
        The instruction's fields (``centre``, ``extents``, ``orientation``, ``target``,
        ``on_laser_line``).
    rng : numpy Generator
        Every error is drawn from it.
    """
    c = np.asarray(instr['centre'], dtype=np.float64)
    R = _quat_matrix(instr['orientation'])
    err = rng.uniform(-1.0, 1.0, 3) * person.position_m
    if instr['on_laser_line']:
        # aimed at the visible line: precise across it (the instruction's tight extent: V0 y
        # for a line along the image rows, x for one along the columns) and in depth
        across = int(np.argmin(np.asarray(instr['extents'], dtype=np.float64)[:2]))
        err[across] = rng.uniform(-1.0, 1.0) * person.laser_line_m
        err[2] = rng.uniform(-1.0, 1.0) * person.laser_line_m
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    tilt = rng.uniform(-1.0, 1.0) * person.tilt_rad
    R = _rot(axis * tilt) @ R
    mistake = ''
    if person.mistake_rate > 0 and rng.uniform() < person.mistake_rate:
        mistake = str(rng.choice(MISTAKES))
        if mistake == 'turned' and instr['target'] in ('sphere', 'circle_board'):
            mistake = 'moved_during_capture'
    if mistake == 'outside_region':
        ext = np.asarray(instr['extents'], dtype=np.float64)
        d = rng.normal(size=2)
        d /= np.linalg.norm(d)
        err[:2] = d * (2.5 * ext[:2].max() + 0.02)
    elif mistake == 'turned':
        R = R @ _rot([0.0, 0.0, rng.choice([0.5, 1.0]) * math.pi])
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, c + err
    return Draw(T, err, float(tilt), mistake)


class SimulatedOperator:
    """Plays the operator of a running calibration node (see the module).

    Runs on its own rclpy context in a thread: ``start()``, ``stop()``. ``stats`` counts
    placements per stage, instructions seen and the errors it made.

    Parameters
    ----------
    domain_id : int
    seed : int
        Seeds every error.
    person : Person
        :data:`PERSON`, or :data:`EXACT` for the zero-error operator.
    mistakes : sequence of str, optional
        Mistakes forced on the first placements, in order (tests), before the random ones.
    """

    def __init__(self, domain_id: int, seed: int = 0, person: Person = PERSON,
                 mistakes=(), log_fn=None):
        self.domain_id, self.person = int(domain_id), person
        self.rng = np.random.default_rng(seed)
        self.forced = list(mistakes)
        self.log = log_fn or log.info
        self.stats = {'instructions': 0, 'placements': {}, 'mistakes': {}, 'moves_asked': 0,
                      'instructions_by_stage': {}}
        #: the node's last instruction of each stage's capture (state done): its feedback
        self.finished: dict[str, dict] = {}
        self._stop = threading.Event()
        self._thread = None
        self._seq = -1
        self._pending = None
        self._current = None  # (instr, Draw) being captured
        self._nudged = False
        self._nudge_at = None  # (stage, placement) of a forced nudge not yet seen caught
        self._nudge_owed = False
        self.seed = seed

    # -- lifecycle --------------------------------------------------------------------
    def start(self):
        self._thread = threading.Thread(target=self._run, name='simulated-operator',
                                        daemon=True)
        self._thread.start()
        return self

    def stop(self):
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10.0)

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
        return False

    # -- the loop ---------------------------------------------------------------------
    def _run(self):
        import rclpy
        from galvoscan_msgs.msg import CalibrationInstruction
        from rclpy.node import Node
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        ctx = rclpy.Context()
        rclpy.init(context=ctx, domain_id=self.domain_id)
        node = Node('simulated_operator', context=ctx)
        ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
        ex.add_node(node)
        from galvoscan_common.executor import ServiceClients

        self._services = ServiceClients(node, ex)
        qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
        node.create_subscription(CalibrationInstruction, 'calibration/instruction',
                                 self._on_instruction, qos)
        self.log(f'simulated operator: seed {self.seed}, position +-'
                 f'{self.person.position_m * 1e3:.0f} mm (+-{self.person.laser_line_m * 1e3:.0f}'
                 f' mm on a laser line), tilt +-{math.degrees(self.person.tilt_rad):.0f} deg, '
                 f'mistakes {self.person.mistake_rate:.0%} of placements')
        try:
            while not self._stop.is_set():
                ex.spin_once(timeout_sec=0.05)
                if self._pending is not None:
                    msg, self._pending = self._pending, None
                    try:
                        self._act(msg)
                    except (RuntimeError, ValueError) as exc:
                        self.log(f'simulated operator: {exc}')
        finally:
            ex.shutdown()
            node.destroy_node()
            rclpy.try_shutdown(context=ctx)

    def _on_instruction(self, msg):
        if msg.sequence != self._seq:
            self._seq = msg.sequence
            self.stats['instructions'] += 1
            by = self.stats['instructions_by_stage']
            if msg.stage:
                by[msg.stage] = by.get(msg.stage, 0) + 1
            if msg.state == 'done':
                self.finished[msg.stage] = {
                    'placements_planned': msg.placements_planned,
                    'placements_done': msg.placements_done,
                    'views_captured': msg.views_captured,
                    'views_rejected': dict(zip(msg.rejected_reasons,
                                               (int(c) for c in msg.rejected_counts),
                                               strict=False)),
                    'search_views': msg.searches, 'text': msg.text}
            self._pending = msg

    def _call(self, srv, name, req, resend=False):
        return self._services.call(srv, name, req, 60.0, resend)

    def _set_scene(self, text, wait_s: float = SCAN_WAIT_S):
        """Put the scene; while the simulator refuses because a scan runs, try again for up
        to ``wait_s`` [s] (a person's hands wait for the scan too)."""
        from galvoscan_msgs.srv import SetScene

        deadline = time.monotonic() + wait_s
        while True:
            resp = self._call(SetScene, 'sim/set_scene', SetScene.Request(scene_yaml=text),
                              resend=True)
            if resp.success:
                return
            if 'during a scan' not in resp.message or time.monotonic() > deadline:
                raise RuntimeError(f'sim/set_scene: {resp.message}')
            time.sleep(0.02)

    def _answer(self, action, placement):
        from galvoscan_msgs.srv import OperatorAction

        resp = self._call(OperatorAction, 'calibration/operator',
                          OperatorAction.Request(action=action, placement=placement))
        if not resp.accepted:
            self.log(f'simulated operator: {action} refused: {resp.message}')

    def _act(self, msg):
        import yaml

        instr = {k: getattr(msg, k) for k in (
            'stage', 'state', 'placement', 'target', 'target_spec', 'centre', 'extents',
            'orientation', 'on_laser_line', 'move', 'direction', 'text')}
        state = msg.state
        if state == 'capture' and self._current is not None:
            self._hold(instr)
            return
        if state not in ('place', 'move'):
            return
        spec = yaml.safe_load(instr['target_spec']) or {}
        if msg.by_robot:  # the robot brings the spheres exactly where asked
            self._current = None
            st = self.stats['placements']
            st[msg.stage] = st.get(msg.stage, 0) + 1
            self._set_scene(scene_text(instr['target'], spec, np.eye(4)))
            self._answer('placed', msg.placement)
            return
        move = np.asarray(instr['move'], dtype=np.float64)
        if state == 'move' and self._current is not None and \
                self._current[0]['placement'] == msg.placement and \
                (np.any(move) or 'turn' in instr['text']):
            # follow the direction given, with a person's imprecision again
            self.stats['moves_asked'] += 1
            draw = self._current[1]
            if 'turn' in instr['text'] and not np.any(move):
                redo = draw_placement(instr, self.rng, Person(0.0, 0.0, self.person.tilt_rad,
                                                              0.0, 0.0))
                draw.T[:3, :3] = redo.T[:3, :3]
            jitter = self.rng.uniform(-1.0, 1.0, 3) * 0.15 * np.abs(move)
            draw.T[:3, 3] += move + jitter
            draw.notes.append(f'moved by {np.round((move + jitter) * 1e3, 1).tolist()} mm')
            self.log(f'simulated operator: {msg.stage} placement {msg.placement}: '
                     f'{instr["direction"] or instr["text"]}; moved by '
                     f'{np.round((move + jitter) * 1e3, 1).tolist()} mm')
        else:  # asked to place it, or told it was not found: place it (again)
            self._nudge_owed |= self._forced_nudge_missed(msg)
            draw = draw_placement(instr, self.rng, self.person)
            if self.forced and state == 'place':
                draw = self._force(instr, draw, self.forced.pop(0))
            if self._nudge_owed and not draw.mistake:
                draw.mistake, draw.forced, draw.again = 'moved_during_capture', True, True
                self._nudge_owed = False
            self._current = (instr, draw)
            self._nudged = False
            st = self.stats['placements']
            st[msg.stage] = st.get(msg.stage, 0) + 1
            if draw.mistake and not draw.again:
                self.stats['mistakes'][draw.mistake] = \
                    self.stats['mistakes'].get(draw.mistake, 0) + 1
            self.log(f'simulated operator: {msg.stage} placement {msg.placement}: '
                     f'{instr["target"]} placed {np.round(draw.error_m * 1e3, 1).tolist()} mm '
                     f'from the centre asked for, tilted {math.degrees(draw.tilt_rad):+.1f} '
                     f'deg' + (f'; mistake: {draw.mistake}' if draw.mistake else '')
                     + (' (again)' if draw.again else ''))
        self._set_scene(scene_text(instr['target'], spec, draw.T))
        self._answer('placed', msg.placement)

    def _forced_nudge_missed(self, msg) -> bool:
        """Whether a forced nudge has to be made again before a new placement is drawn.

        A nudge lands when the operator hears the capture begin, and the scanner's last look
        at the target may already be taken by then (a one-view capture on a loaded machine):
        a nudge after the capture moved nothing the scanner kept. A forced nudge is there to
        be caught, so one that was not (the next instruction is not its placement's retake
        for motion), or one never made because its placement was drawn again before its
        capture, is forced on a later placement."""
        if self._nudge_at is not None:
            at, self._nudge_at = self._nudge_at, None
            if msg.state == 'place' and (msg.stage, msg.placement) == at and \
                    'moved during' in msg.text:
                return False
            self.log(f'simulated operator: {at[0]} placement {at[1]}: the nudge came after '
                     'the capture\'s last look; it is made again on a later placement')
            return True
        cur = None if self._current is None else self._current[1]
        return cur is not None and cur.forced and cur.mistake == 'moved_during_capture'

    def _force(self, instr, draw, mistake):
        forced = draw_placement(instr, np.random.default_rng(len(self.forced) + 17),
                                self.person)
        forced.mistake = mistake if mistake != 'exact' else ''
        forced.forced = bool(forced.mistake)
        if mistake == 'exact':
            forced.T = draw.T.copy()
            forced.T[:3, 3] = np.asarray(instr['centre'], dtype=np.float64)
            forced.error_m = np.zeros(3)
            return forced
        if isinstance(mistake, tuple):  # (offset [m], tilt [rad]) in tests
            off, tilt = mistake
            T = np.eye(4)
            T[:3, :3] = _rot([tilt, 0.0, 0.0]) @ _quat_matrix(instr['orientation'])
            T[:3, 3] = np.asarray(instr['centre'], dtype=np.float64) + np.asarray(off)
            return Draw(T, np.asarray(off, dtype=np.float64), float(tilt), 'forced offset',
                        forced=True)
        if mistake == 'outside_region':
            ext = np.asarray(instr['extents'], dtype=np.float64)
            draw.T[:3, 3] = np.asarray(instr['centre']) + np.array([4.0 * ext[0], 0, 0])
            draw.error_m = draw.T[:3, 3] - np.asarray(instr['centre'])
        draw.mistake, draw.forced = mistake, True
        return draw

    def _hold(self, instr):
        """While the scanner captures: the hand's small motion, or a nudge (a mistake)."""
        instr0, draw = self._current
        wait_s = 0.0  # the hand's small motion while a scan runs is not simulated
        if draw.mistake == 'moved_during_capture' and not self._nudged:
            wait_s = 2.0  # a nudge the simulator refuses mid-scan lands when the scan ends
            self._nudged = True
            if draw.forced:
                self._nudge_at = (instr['stage'], instr['placement'])
            nudge = self.rng.normal(size=3)
            nudge = nudge / np.linalg.norm(nudge) * 0.004
            draw.T[:3, 3] += nudge
            draw.mistake = ''  # a person does not repeat it on the retake
            self.log(f'simulated operator: {instr["stage"]} placement {instr["placement"]}: '
                     f'nudged the target by {np.round(nudge * 1e3, 1).tolist()} mm during '
                     'the capture')
        elif self.person.hold_m > 0:
            draw.T[:3, 3] += self.rng.uniform(-1.0, 1.0, 3) * self.person.hold_m
        else:
            return
        spec_yaml = instr0['target_spec']
        import yaml

        self._set_scene(scene_text(instr0['target'], yaml.safe_load(spec_yaml) or {}, draw.T),
                        wait_s=wait_s)


def progress_text(msg) -> str:
    """A ``calibration/progress`` message as the console shows it: the placements, the
    standard errors against their targets and the advice."""
    lines = [f'  [{msg.stage} progress] {msg.placements_done} of at most '
             f'{msg.placements_max} placements kept; standard errors '
             + ('meet their targets' if msg.targets_met else 'not all at target yet')]
    if msg.parameter_names:
        lines.append(f'    {"parameter":>14s} {"sigma":>11s} {"target":>11s}')
        for n, u, s, t in zip(msg.parameter_names, msg.parameter_units, msg.sigma,
                              msg.sigma_target, strict=False):
            mark = 'ok' if s <= t else '--'
            lines.append(f'    {n:>14s} {s:11.3g} {t:11.3g} {u:5s} {mark}')
    if msg.advice:
        lines.append(f'    advice: {msg.advice}')
    return '\n'.join(lines)


def console(domain_id: int, stdin=None, out=None) -> int:
    """A person at the console plays the operator: every instruction is printed, and a line
    typed answers it (``p``/``placed``, ``u``/``undo``, ``s``/``skip``, ``d``/``done``,
    ``q`` to leave). Returns 0 when left, 1 when the input ends."""
    import queue

    import rclpy
    from galvoscan_msgs.msg import CalibrationInstruction, CalibrationProgress
    from galvoscan_msgs.srv import OperatorAction
    from rclpy.node import Node
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    from galvoscan_common.executor import ServiceClients

    stdin = stdin or sys.stdin
    out = out or sys.stdout
    words = {'p': 'placed', 'u': 'undo', 's': 'skip', 'd': 'done'}
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=int(domain_id))
    node = Node('console_operator', context=ctx)
    ex = rclpy.executors.SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    services = ServiceClients(node, ex)
    current = {'placement': 0, 'seq': -1}

    def show(msg):
        if msg.sequence == current['seq']:
            return
        current.update(placement=msg.placement, seq=msg.sequence)
        head = f'[{msg.stage or "-"} {msg.state}'
        if msg.placements_planned:
            head += f' {msg.placement + 1}/{msg.placements_planned}'
        print(f'{head}] {msg.text}', file=out, flush=True)
        if msg.state in ('place', 'move'):
            print('  answer: p(laced) / u(ndo) / s(kip) / d(one)', file=out, flush=True)

    node.create_subscription(CalibrationInstruction, 'calibration/instruction', show,
                             QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    shown = {'key': None}

    def show_progress(msg):
        key = (msg.stage, msg.placements_done, msg.advice)
        if not msg.stage or key == shown['key']:
            return
        shown['key'] = key
        print(progress_text(msg), file=out, flush=True)

    node.create_subscription(CalibrationProgress, 'calibration/progress', show_progress,
                             QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                                        durability=DurabilityPolicy.TRANSIENT_LOCAL))
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(x) for x in iter(stdin.readline, '')]
                     + [lines.put(None)], daemon=True).start()
    try:
        while True:
            ex.spin_once(timeout_sec=0.1)
            try:
                line = lines.get_nowait()
            except queue.Empty:
                continue
            if line is None:
                return 1
            word = line.strip().lower()
            if word in ('q', 'quit'):
                return 0
            action = words.get(word[:1], word) if word else ''
            if action not in words.values():
                print(f"  '{word}'? p(laced), u(ndo), s(kip), d(one) or q(uit)", file=out,
                      flush=True)
                continue
            resp = services.call(OperatorAction, 'calibration/operator', OperatorAction.Request(
                action=action, placement=current['placement']), 30.0, False)
            print(f'  {resp.message}', file=out, flush=True)
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def main(argv=None):
    p = argparse.ArgumentParser(
        prog='galvoscan operator',
        description='Play the operator of a running calibration node: print its instructions '
                    'and answer them from the keyboard, or (--sim) place the targets in the '
                    'simulator as a person would.')
    p.add_argument('--sim', action='store_true',
                   help='the simulated operator: place the targets in the simulator '
                        '(sim/set_scene) with a person\'s imprecision and mistakes')
    p.add_argument('--seed', type=int, default=0, help='--sim: seed of every placement error')
    p.add_argument('--exact', action='store_true',
                   help='--sim: the zero-error operator, every target exactly where asked')
    p.add_argument('--duration', type=float, default=0.0,
                   help='--sim: stop after S seconds (0: never)')
    args = p.parse_args(argv)
    import os

    logging.basicConfig(level=logging.INFO, format='[%(name)s] %(message)s')
    domain = int(os.environ.get('ROS_DOMAIN_ID', '0'))
    if not args.sim:
        return console(domain)
    op = SimulatedOperator(domain, args.seed, EXACT if args.exact else PERSON,
                           log_fn=lambda s: print(s, flush=True))
    op.start()
    t_end = time.monotonic() + args.duration if args.duration > 0 else math.inf
    try:
        while time.monotonic() < t_end:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    op.stop()
    return 0


if __name__ == '__main__':
    sys.exit(main())
