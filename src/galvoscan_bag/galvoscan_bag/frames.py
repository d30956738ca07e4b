"""Camera frames paired with their galvo states, read from a bag (no rclpy).

The driver publishes ``camera/image_raw`` and ``galvo/state`` with the same header stamp;
a bag recorded from it holds both. :func:`read_frames` pairs them back into
:class:`galvoscan_common.frame.Frame` objects, in stamp order. A state without an image (the
serial backend has no camera) gives a frame with ``image=None`` if ``states_only`` is set.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from galvoscan_common.frame import Frame

from .reader import deserialize, read_messages, read_topics

IMAGE_TOPIC = '/camera/image_raw'
STATE_TOPIC = '/galvo/state'
_DTYPES = {'mono8': np.uint8, '8UC1': np.uint8, 'mono16': np.uint16, '16UC1': np.uint16}


def _abs(topic: str) -> str:
    return topic if topic.startswith('/') else '/' + topic


def _stamp_ns(header) -> int:
    return int(header.stamp.sec) * 1_000_000_000 + int(header.stamp.nanosec)


def image_array(msg) -> np.ndarray:
    """The pixels of a (rosbags) sensor_msgs/Image as an (H, W) array; ValueError if bad."""
    dtype = _DTYPES.get(msg.encoding)
    if dtype is None:
        raise ValueError(f"image encoding '{msg.encoding}' is not one of {', '.join(_DTYPES)}")
    itemsize = np.dtype(dtype).itemsize
    if msg.height == 0 or msg.width == 0 or msg.step < msg.width * itemsize \
            or len(msg.data) != msg.step * msg.height:
        raise ValueError(f'image of {msg.width}x{msg.height}, step {msg.step}, '
                         f'{len(msg.data)} bytes is inconsistent')
    rows = np.frombuffer(np.asarray(msg.data, np.uint8).tobytes(), np.uint8)
    rows = rows.reshape(msg.height, msg.step)[:, :msg.width * itemsize]
    img = rows.copy().view(np.dtype(dtype).newbyteorder('>' if msg.is_bigendian else '<'))
    return img.astype(dtype, copy=False)


def _frame(state, image) -> Frame:
    stamp_ns = _stamp_ns(state.header)
    return Frame(seq=int(state.seq), stamp=stamp_ns * 1e-9, stamp_ns=stamp_ns,
                 voltages=np.array([state.g1_pan_voltage, state.g1_tilt_voltage,
                                    state.g2_pan_voltage, state.g2_tilt_voltage]),
                 laser_on=bool(state.laser_on), status=int(state.status),
                 image=None if image is None else image_array(image))


def read_frames(path, image_topic=IMAGE_TOPIC, state_topic=STATE_TOPIC,
                states_only=False, max_pending=200) -> Iterator[Frame]:
    """Yield a bag's frames, each image paired with the state of the same header stamp.

    Streams in log-time order, holding at most ``max_pending`` unpaired messages per topic
    (the oldest unpaired ones are dropped), so a bag of any length fits in memory.

    Parameters
    ----------
    path : str or Path
        rosbag2 directory.
    states_only : bool
        Also yield states that have no image (``image=None``); otherwise they are skipped.

    Raises
    ------
    ValueError
        The bag has no state topic.
    """
    image_topic, state_topic = _abs(image_topic), _abs(state_topic)
    present = {t.topic for t in read_topics(Path(path))}
    if state_topic not in present:
        raise ValueError(f'{path}: no {state_topic} topic; found {sorted(present)}')
    has_images = image_topic in present
    topics = [state_topic] + ([image_topic] if has_images else [])
    images, states = {}, {}
    for message in read_messages(path, topics):
        msg = deserialize(message)
        key = _stamp_ns(msg.header)
        if message.topic == image_topic:
            state = states.pop(key, None)
            if state is not None:
                yield _frame(state, msg)
            else:
                images[key] = msg
        else:
            image = images.pop(key, None)
            if image is not None or (states_only and not has_images):
                yield _frame(msg, image)
            else:
                states[key] = msg
        for pending in (images, states):
            while len(pending) > max_pending:
                old = min(pending)
                state = states.pop(old) if pending is states else None
                images.pop(old, None)
                if state is not None and states_only:
                    yield _frame(state, None)
    if states_only:
        for key in sorted(states):
            yield _frame(states[key], None)
