"""The ready-made Foxglove layout and rviz2 config name what the graph really publishes.

Topics, types and frames are taken from the interface reference (docs/reference.md), which
tests/test_reference_doc.py keeps equal to the code, and from the Foxglove channels of
``galvoscan view``; message paths are checked against the message's own fields.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[1]
VIEWERS = ROOT / 'docs' / 'viewers'
REFERENCE = ROOT / 'docs' / 'reference.md'

#: panel types of Foxglove (and Lichtblick) that the layout may use
FOXGLOVE_PANELS = {'3D', 'Image', 'Plot', 'DiagnosticSummary', 'DiagnosticStatusPanel',
                   'RawMessages', 'StateTransitions'}
RVIZ_DISPLAYS = {'rviz_default_plugins/Grid', 'rviz_default_plugins/TF',
                 'rviz_default_plugins/PointCloud2', 'rviz_default_plugins/MarkerArray',
                 'rviz_default_plugins/Image'}


def _sections(text: str) -> dict[str, str]:
    parts = re.split(r'^## `([\w]+)`\s*$', text, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def published(reference: str | None = None) -> dict[str, str]:
    """topic -> type of everything the nodes publish (from the reference's tables)."""
    text = reference if reference is not None else REFERENCE.read_text()
    out = {}
    for body in _sections(text).values():
        block = body.split('**Publishes**', 1)[1].split('**Subscribes**', 1)[0]
        for topic, kind in re.findall(r'^\| `([^`]+)` \| `([^`]+)` \|', block, flags=re.M):
            out[topic] = kind
    return out


def parameter_default(node: str, name: str) -> str:
    body = _sections(REFERENCE.read_text())[node]
    m = re.search(rf"^\| `{name}` \| \w+ \| [^|]* \| `'([^']*)'` \|", body, flags=re.M)
    assert m, f'{node}.{name} not in the reference'
    return m.group(1)


def foxglove_channels() -> dict[str, str]:
    from galvoscan_view.view_node import CHANNELS, TF_CHANNELS

    return {c.topic: c.msgtype for c in (*CHANNELS, *TF_CHANNELS)}


def layout_topics(layout: dict) -> set[str]:
    """Every topic a panel of the layout reads."""
    topics = set()
    for key, config in layout['configById'].items():
        kind = key.split('!')[0]
        if kind == '3D':
            topics |= set(config['topics'])
        elif kind == 'Image':
            topics.add(config['imageMode']['imageTopic'])
        elif kind == 'Plot':
            topics |= {p['value'].split('.')[0] for p in config['paths']}
        elif kind.startswith('Diagnostic'):
            topics.add(config['topicToRender'])
    return topics


def test_the_foxglove_layout_shows_what_the_view_serves():
    from galvoscan_msgs.msg import GalvoState

    layout = json.loads((VIEWERS / 'galvoscan.foxglove.json').read_text())
    kinds = {key.split('!')[0] for key in layout['configById']}
    assert kinds <= FOXGLOVE_PANELS, kinds - FOXGLOVE_PANELS
    assert {'3D', 'Image', 'Plot'} <= kinds and any(k.startswith('Diagnostic') for k in kinds)

    channels = foxglove_channels()
    graph = published()
    for topic in layout_topics(layout):
        assert topic in channels, f'{topic}: not a channel of galvoscan view'
        # a channel the view makes up itself (the stripe image) needs no publisher
        assert topic.lstrip('/') in graph or topic in graph or topic == '/camera/image_stripe', \
            f'{topic}: no node publishes it'
    assert channels['/camera/image_stripe'] == 'sensor_msgs/msg/Image'

    # the clouds in v0 and in the cell frame, named as the reconstructor names them
    frames = {c['followTf'] for k, c in layout['configById'].items() if k.startswith('3D')}
    assert frames == {parameter_default('reconstructor', 'frame_id'),
                      parameter_default('reconstructor', 'cell_frame')}
    for key, config in layout['configById'].items():
        if key.startswith('3D'):
            assert {'/points', '/points/scan'} <= set(config['topics'])
        if key.startswith('Plot'):
            fields = GalvoState.get_fields_and_field_types()
            for path in config['paths']:
                topic, field = path['value'].split('.', 1)
                assert topic == '/galvo/state' and field in fields, path['value']

    # every panel of the configuration is placed in the mosaic, and nothing else is
    placed = set(re.findall(r'"([\w]+![\w]+)"', json.dumps(layout['layout'])))
    assert placed == set(layout['configById'])


def test_the_rviz_config_shows_what_the_graph_publishes():
    config = yaml.safe_load((VIEWERS / 'galvoscan.rviz').read_text())
    manager = config['Visualization Manager']
    graph = published()
    assert manager['Global Options']['Fixed Frame'] == parameter_default('reconstructor',
                                                                         'cell_frame')
    displays = manager['Displays']
    assert {d['Class'] for d in displays} <= RVIZ_DISPLAYS
    for d in displays:
        if 'Topic' not in d:
            continue
        topic = d['Topic']['Value']
        assert topic.lstrip('/') in graph or topic in graph, f'{topic}: no node publishes it'
        kind = graph.get(topic.lstrip('/'), graph.get(topic))
        assert kind.split('/')[-1] == d['Class'].split('/')[-1], (topic, kind, d['Class'])
    by_topic = {d['Topic']['Value']: d['Topic'] for d in displays if 'Topic' in d}
    assert by_topic['/points/scan']['Durability Policy'] == 'Transient Local'
    assert {'/points', '/points/scan', '/markers'} <= set(by_topic)


def test_the_checks_see_a_topic_no_node_publishes():
    reference = REFERENCE.read_text()
    assert '/points' in published(reference) and '/galvo/state' in published(reference)
    assert '/points_typo' not in published(reference)
    layout = {'configById': {'Image!x': {'imageMode': {'imageTopic': '/camera/image_typo'}}}}
    assert layout_topics(layout) == {'/camera/image_typo'}
    assert '/camera/image_typo' not in foxglove_channels()
