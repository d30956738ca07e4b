#!/usr/bin/env python3
"""Write docs/reference.md, galvoscan's interface reference, from the code itself.

    .venv/bin/python tools/gen_reference.py           # (re)write docs/reference.md
    .venv/bin/python tools/gen_reference.py --check   # exit 1 and show the difference if stale

Each node is built in this process with its default parameters (the driver configured and
activated on the simulator, as ``galvoscan run`` starts it) and asked what it has: its
publishers, subscriptions and services with their types and QoS, and every declared
parameter with its ParameterDescriptor (type, description, range, read-only). The unit of a
parameter is the bracketed unit its description ends with. Service fields come from the
service types, with the comments of their ``.srv`` files; the ``galvoscan`` subcommands from
their own ``--help``. ``tests/test_reference_doc.py`` fails when the committed page differs.
"""

from __future__ import annotations

import argparse
import contextlib
import difflib
import io
import os
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / 'docs' / 'reference.md'
MSGS = ROOT / 'msgs'

#: created by rclpy for every node; listed once, not per node
STANDARD_SERVICES = ('describe_parameters', 'get_parameter_types', 'get_parameters',
                     'get_type_description', 'list_parameters', 'set_parameters',
                     'set_parameters_atomically')
LIFECYCLE_SERVICES = ('change_state', 'get_available_states', 'get_available_transitions',
                      'get_state', 'get_transition_graph')
STANDARD_TOPICS = ('/parameter_events', '/rosout')
STANDARD_PARAMETERS = ('use_sim_time', 'start_type_description_service')
#: the Python whose argparse wrote the commands section
PYTHON = f'{sys.version_info.major}.{sys.version_info.minor}'
COMMANDS_HEADING = '## The `galvoscan` command'

#: (node name, console script, "module:Class", how it is started, note)
NODES = (
    ('galvo_driver', 'galvo_driver', 'galvo_driver.driver_node:GalvoDriverNode',
     'lifecycle node; `galvoscan run` starts it (autostart configures and activates it)'),
    ('stripe_extractor', 'stripe_extractor',
     'stripe_extractor.extractor_node:StripeExtractorNode', '`galvoscan run` starts it'),
    ('reconstructor', 'reconstructor', 'reconstructor.reconstructor_node:ReconstructorNode',
     '`galvoscan run` starts it'),
    ('calibration', 'calibration_node', 'calibration_tools.calibration_node:CalibrationNode',
     '`galvoscan run --nodes ...,calibration`; while capturing it also subscribes to '
     '`camera/image_raw`, `galvo/state` and the robot pose topic'),
    ('galvoscan_view', None, 'galvoscan_view.view_node:ViewNode',
     '`galvoscan view`; it forwards what it receives to the Foxglove channels below'),
)


def _qos(q) -> str:
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, ReliabilityPolicy

    rel = {ReliabilityPolicy.RELIABLE: 'reliable',
           ReliabilityPolicy.BEST_EFFORT: 'best effort'}.get(q.reliability, str(q.reliability))
    dur = {DurabilityPolicy.VOLATILE: 'volatile',
           DurabilityPolicy.TRANSIENT_LOCAL: 'transient local'}.get(q.durability,
                                                                    str(q.durability))
    hist = (f'keep last {q.depth}' if q.history == HistoryPolicy.KEEP_LAST
            else 'keep all')
    return f'{rel}, {dur}, {hist}'


def _type_name(cls) -> str:
    module = cls.__module__.split('.')
    return f'{module[0]}/{module[1]}/{cls.__name__}'


def _cell(text) -> str:
    return str(text).replace('|', '\\|').replace('\n', ' ')


def _srv_comments(srv_name: str) -> dict[tuple[str, str], str]:
    """``(part, field) -> comment`` from ``msgs/srv/<Name>.srv`` (galvoscan_msgs only)."""
    package, _, name = srv_name.split('/')
    path = MSGS / 'srv' / f'{name}.srv'
    if package != 'galvoscan_msgs' or not path.exists():
        return {}
    out, part = {}, 'request'
    for line in path.read_text().splitlines():
        if line.strip() == '---':
            part = 'response'
            continue
        m = re.match(r'\s*[\w/\[\]<=]+\s+(\w+)(?:\s*=[^#]*)?\s*(?:#\s*(.*))?$', line)
        if m and m.group(2):
            out[(part, m.group(1))] = m.group(2).strip()
    return out


def _fields(cls, part: str, comments) -> str:
    fields = cls.get_fields_and_field_types()
    if not fields:
        return '(empty)'
    items = []
    for name, kind in fields.items():
        note = comments.get((part, name))
        items.append(f'`{name}` ({kind})' + (f': {note}' if note else ''))
    return '<br>'.join(_cell(i) for i in items)


def _unit(description: str) -> str:
    """The first bracketed unit of a description (``[Hz]``, ``[m]``, ``[1]``), or ''."""
    m = re.search(r'\[([^\[\]]{1,12})\]', description)
    return m.group(1) if m else ''


def _range(desc) -> str:
    if desc.floating_point_range:
        r = desc.floating_point_range[0]
        return f'{r.from_value:g} … {r.to_value:g}'
    if desc.integer_range:
        r = desc.integer_range[0]
        return f'{r.from_value} … {r.to_value}'
    return desc.additional_constraints or ''


_PTYPES = {1: 'bool', 2: 'int', 3: 'float', 4: 'string', 5: 'bytes', 6: 'bool[]', 7: 'int[]',
           8: 'float[]', 9: 'string[]'}


def _value(v) -> str:
    if isinstance(v, str):
        return f"`'{v}'`"
    if isinstance(v, float):
        return f'`{v:g}`'
    if isinstance(v, (list, tuple)) or type(v).__name__ == 'array':
        items = list(v)
        if len(items) > 6:
            return f'`[{", ".join(f"{x:g}" if isinstance(x, float) else str(x) for x in items)}]`'
        return f'`{items}`'
    return f'`{v}`'


def node_section(node, script, note) -> list[str]:
    name = node.get_name()
    lines = [f'## `{name}`', '']
    lines.append(f'Console script: `{script}`. ' if script else '')
    lines[-1] += note[0].upper() + note[1:] + '.'
    lines.append('')
    pubs = sorted((p.topic_name, _type_name(p.msg_type), _qos(p.qos_profile))
                  for p in node.publishers if p.topic_name not in STANDARD_TOPICS)
    subs = sorted((s.topic_name, _type_name(s.msg_type), _qos(s.qos_profile))
                  for s in node.subscriptions if s.topic_name not in STANDARD_TOPICS)
    for title, rows in (('Publishes', pubs), ('Subscribes', subs)):
        lines += [f'**{title}**', '']
        if rows:
            lines += ['| topic | type | QoS |', '|---|---|---|']
            lines += [f'| `{t}` | `{ty}` | {q} |' for t, ty, q in rows]
        else:
            lines.append('nothing')
        lines.append('')
    services, lifecycle = [], False
    for srv in node.services:
        full = node.resolve_service_name(srv.srv_name)
        own, _, base = full.rpartition('/')
        if own == f'/{name}' and base in STANDARD_SERVICES:
            continue
        if own == f'/{name}' and base in LIFECYCLE_SERVICES:
            lifecycle = True
            continue
        services.append((full, srv))
    lines += ['**Services**', '']
    if services:
        lines += ['| service | type | request | response |', '|---|---|---|---|']
        for full, srv in sorted(services, key=lambda s: s[0]):
            tname = _type_name(srv.srv_type)
            comments = _srv_comments(tname)
            lines.append(f'| `{full}` | `{tname}` | '
                         f'{_fields(srv.srv_type.Request, "request", comments)} | '
                         f'{_fields(srv.srv_type.Response, "response", comments)} |')
    else:
        lines.append('none of its own')
    lines.append('')
    if lifecycle:
        lines += [f'Lifecycle services: `/{name}/change_state`, `get_state`, '
                  '`get_available_states`, `get_available_transitions`, '
                  '`get_transition_graph` (`lifecycle_msgs`).', '']
    params = sorted(n for n in node._parameters if n not in STANDARD_PARAMETERS)
    lines += ['**Parameters**', '']
    if params:
        lines += ['| parameter | type | unit | default | range | description |',
                  '|---|---|---|---|---|---|']
        for pname in params:
            desc = node.describe_parameter(pname)
            text = desc.description + (' (read-only)' if desc.read_only else '')
            ptype = _PTYPES.get(desc.type, str(desc.type))
            lines.append(f'| `{pname}` | {ptype} | {_cell(_unit(desc.description))} | '
                         f'{_cell(_value(node.get_parameter(pname).value))} | '
                         f'{_cell(_range(desc))} | {_cell(text)} |')
    else:
        lines.append('none')
    lines.append('')
    return lines


def _build(cls_path: str, ctx):
    import importlib

    module, cls = cls_path.split(':')
    cls = getattr(importlib.import_module(module), cls)
    if cls.__name__ == 'ViewNode':
        from galvoscan_view.state import ViewState

        return cls(ViewState(), server=None, context=ctx)   # no server: nothing is forwarded
    return cls(context=ctx)


def channels_section() -> list[str]:
    from galvoscan_view.view_node import CHANNELS, TF_CHANNELS

    lines = ['### Foxglove channels of `galvoscan view`', '',
             '| channel | type | dropped for a slow client | latched messages |',
             '|---|---|---|---|']
    for c in (*CHANNELS, *TF_CHANNELS):
        lines.append(f'| `{c.topic}` | `{c.msgtype}` | {"yes" if c.lossy else "never"} | '
                     f'{c.latched or ""} |')
    return lines + ['']


def messages_section() -> list[str]:
    lines = ['## Messages of `galvoscan_msgs`', '']
    for path in sorted((MSGS / 'msg').glob('*.msg')):
        lines += [f'### `galvoscan_msgs/msg/{path.stem}`', '', '```', path.read_text().rstrip(),
                  '```', '']
    return lines


def _help(argv) -> str:
    from galvoscan.cli import main

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf), contextlib.redirect_stderr(io.StringIO()):
        try:
            main(argv)
        except SystemExit:
            pass
    return buf.getvalue().rstrip()


def commands_section() -> list[str]:
    from galvoscan.cli import DELEGATED

    lines = [COMMANDS_HEADING, '',
             f'Each subcommand\'s `--help`, as Python {PYTHON} prints it (argparse words its help '
             'a little differently from one Python version to the next).', '',
             '```', _help(['--help']), '```', '']
    commands = ['run', *DELEGATED, 'demo']
    for cmd in commands:
        lines += [f'### `galvoscan {cmd}`', '', '```', _help([cmd, '--help']), '```', '']
        if cmd == 'rig':
            for sub in ('random', 'reset', 'check'):
                lines += [f'#### `galvoscan rig {sub}`', '', '```',
                          _help(['rig', sub, '--help']), '```', '']
    return lines


def generate() -> str:
    saved = {k: os.environ.get(k) for k in ('COLUMNS', 'ROS_AUTOMATIC_DISCOVERY_RANGE')}
    os.environ['COLUMNS'] = '100'          # argparse wraps --help at the terminal's width
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    try:
        return _generate()
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def _generate() -> str:
    import random

    import rclpy

    from galvoscan_common.runtime import private_domain
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=private_domain(random.Random(os.getpid())))
    head = [
        '# Interface reference', '',
        '<!-- Generated by `.venv/bin/python tools/gen_reference.py` from the code; do not '
        'edit by hand. tests/test_reference_doc.py fails when it is out of date. -->', '',
        "Every node's topics (with message types and QoS), services (with request and "
        'response fields) and parameters (with type, unit, default, range and description '
        'from its ParameterDescriptor), and every `galvoscan` subcommand. Topic names are '
        'as the nodes resolve them without a namespace. Every node also has rclpy\'s '
        'parameter services (`~/describe_parameters`, `~/get_parameters`, `~/set_parameters`, '
        '...), publishes `/rosout` and `/parameter_events`, and has the `use_sim_time` '
        'parameter. Every node publishes its status on `diagnostics` '
        '([running-and-scanning.md](running-and-scanning.md#diagnostics)).', '',
        '| node | console script |', '|---|---|']
    head += [f'| [`{n}`](#{n}) | {f"`{s}`" if s else "(in `galvoscan view`)"} |'
             for n, s, _, _ in NODES]
    head += ['', '']
    body = []
    nodes = []
    try:
        for name, script, cls_path, note in NODES:
            node = _build(cls_path, ctx)
            nodes.append(node)
            assert node.get_name() == name, (node.get_name(), name)
            body += node_section(node, script, note)
            if name == 'galvoscan_view':
                body += channels_section()
    finally:
        for node in reversed(nodes):
            safe = getattr(node, 'make_safe', None)
            if safe is not None:
                safe()
            node.destroy_node()
        rclpy.try_shutdown(context=ctx)
    text = '\n'.join(head + body + messages_section() + commands_section())
    return text.rstrip() + '\n'


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    p.add_argument('--check', action='store_true',
                   help='do not write; exit 1 if docs/reference.md is out of date')
    p.add_argument('--out', type=Path, default=OUT)
    args = p.parse_args(argv)
    text = generate()
    if args.check:
        old = args.out.read_text() if args.out.exists() else ''
        if old != text:
            sys.stdout.writelines(difflib.unified_diff(
                old.splitlines(True), text.splitlines(True), str(args.out), 'from the code'))
            print(f'{args.out} is out of date: run .venv/bin/python tools/gen_reference.py',
                  file=sys.stderr)
            return 1
        return 0
    args.out.write_text(text)
    print(f'wrote {args.out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
