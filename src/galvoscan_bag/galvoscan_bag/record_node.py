"""``galvoscan record``: record topics as CDR bytes into a rosbag2 directory.

Subscriptions are raw (``raw=True``): the callback gets the serialised bytes, which go to the
bag unchanged with the node clock's receive time as log time. Each topic is subscribed once its
type is known (given on the command line, one of :data:`DEFAULT_TOPICS`, or discovered from the
graph) and, with ``--qos auto``, once a publisher exists: the subscription then adapts to the
publishers' offered QoS (reliable only if all publishers are; transient-local only if all are),
which is stored in metadata.yaml.

The bag is flushed chunk by chunk (every ``--flush-interval`` seconds and every ``--chunk-size``
bytes), so SIGKILL loses at most the last chunk; ``galvoscan bag-recover`` repairs such a bag.
SIGINT and SIGTERM close the bag cleanly.

Note: on this rclpy (7.1), ``EventsExecutor.spin()`` and ``spin_until_future_complete()`` do not
return on SIGINT/SIGTERM, so :func:`main` loops over ``spin_once``.
"""

from __future__ import annotations

import argparse
import contextlib
import signal
import sys
import time
from collections.abc import Sequence
from datetime import datetime
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.experimental import EventsExecutor
from rclpy.node import Node
from rclpy.qos import (
    DurabilityPolicy,
    HistoryPolicy,
    QoSProfile,
    ReliabilityPolicy,
)

from galvoscan_common.runtime import freeze_startup_heap, tune_this_process

from .ros_messages import import_message_class, qos_to_rosbags, split_ros_args
from .writer import ROSBAGS_CHUNK_LIMIT, BagWriter

#: Topics recorded when none are named, with their types.
DEFAULT_TOPICS: dict[str, str] = {
    'camera/image_raw': 'sensor_msgs/msg/Image',
    'camera/camera_info': 'sensor_msgs/msg/CameraInfo',
    'galvo/state': 'galvoscan_msgs/msg/GalvoState',
    'stripe/centers': 'galvoscan_msgs/msg/StripeCenters',
    'points': 'sensor_msgs/msg/PointCloud2',
}

#: Topics that ``--all`` leaves out.
EXCLUDED_WITH_ALL = frozenset({'/rosout', '/parameter_events'})

QOS_MODES = ('auto', 'reliable', 'best_effort')


class BagRecorder(Node):
    """Subscribes raw to topics and writes every message into a :class:`BagWriter`.

    Parameters
    ----------
    bag : BagWriter
        An open writer; the caller closes it.
    topics : dict of str to (str or None)
        Topic name (relative names resolve in the node's namespace) to message type
        ('pkg/msg/Name'), or None to take the type from the graph.
    all_topics : bool
        Also record every other topic that appears (except /rosout and /parameter_events).
    qos_mode : {'auto', 'reliable', 'best_effort'}
        ``auto`` waits for a publisher and matches its offered QoS.
    qos_depth : int
        KEEP_LAST depth of the subscriptions [messages].
    max_messages : int or None
        Set :attr:`done` once this many messages are written in total.
    discovery_period : float
        Graph polling period for types and publishers [s].
    """

    def __init__(
        self,
        bag: BagWriter,
        topics: dict[str, str | None],
        *,
        all_topics: bool = False,
        qos_mode: str = 'auto',
        qos_depth: int = 100,
        max_messages: int | None = None,
        discovery_period: float = 0.2,
    ) -> None:
        super().__init__('bag_recorder')
        if qos_mode not in QOS_MODES:
            raise ValueError(f'qos_mode must be one of {QOS_MODES}, got {qos_mode!r}')
        if qos_depth < 1:
            raise ValueError(f'qos_depth must be >= 1, got {qos_depth}')
        if max_messages is not None and max_messages < 1:
            raise ValueError(f'max_messages must be >= 1 or None, got {max_messages}')
        if not topics and not all_topics:
            raise ValueError('topics is empty and all_topics is False: nothing to record')
        self.bag = bag
        self.all_topics = all_topics
        self.qos_mode = qos_mode
        self.qos_depth = qos_depth
        self.max_messages = max_messages
        self.total = 0
        self.done = False
        self._wanted: dict[str, str | None] = {
            self.resolve_topic_name(name): msgtype for name, msgtype in topics.items()
        }
        self._raw_subscriptions: dict[str, object] = {}
        self._failed: set[str] = set()
        self._discovery_timer = self.create_timer(discovery_period, self._discover)
        # Flush quiet recordings too: the writer itself only flushes on write.
        self._flush_timer = self.create_timer(0.1, self._flush_if_due)
        self._discover()

    def silent_topics(self) -> list[str]:
        """The requested topics (resolved names) with no message recorded, sorted."""
        counts = self.bag.counts
        return sorted(t for t in self._wanted if not counts.get(t))

    @property
    def subscribed_topics(self) -> list[str]:
        """Topics with an active subscription."""
        return sorted(self._raw_subscriptions)

    def _flush_if_due(self) -> None:
        if self.bag.is_open:
            self.bag.flush_if_due()

    def _discover(self) -> None:
        graph = dict(self.get_topic_names_and_types())
        if self.all_topics:
            for name in graph:
                if name not in EXCLUDED_WITH_ALL:
                    self._wanted.setdefault(name, None)
        for name, msgtype in self._wanted.items():
            if name in self._raw_subscriptions or name in self._failed:
                continue
            if msgtype is None:
                types = graph.get(name, [])
                if len(types) != 1:
                    continue  # unknown yet (or ambiguous): try again later
                msgtype = types[0]
            self._try_subscribe(name, msgtype)

    def _try_subscribe(self, name: str, msgtype: str) -> None:
        publishers = [
            info for info in self.get_publishers_info_by_topic(name) if info.topic_type == msgtype
        ]
        if self.qos_mode == 'auto' and not publishers:
            return
        try:
            msg_class = import_message_class(msgtype)
            self.bag.add_topic(name, msgtype, [qos_to_rosbags(p.qos_profile) for p in publishers])
        except ValueError as err:
            self.get_logger().error(f'cannot record {name}: {err}')
            self._failed.add(name)
            return
        qos = self._subscription_qos(publishers)
        self._raw_subscriptions[name] = self.create_subscription(
            msg_class, name, self._make_callback(name), qos, raw=True
        )
        self.get_logger().info(
            f'recording {name} [{msgtype}] {qos.reliability.name.lower()} '
            f'{qos.durability.name.lower()}'
        )

    def _subscription_qos(self, publishers: list) -> QoSProfile:
        if self.qos_mode == 'best_effort':
            reliability = ReliabilityPolicy.BEST_EFFORT
        elif self.qos_mode == 'reliable':
            reliability = ReliabilityPolicy.RELIABLE
        elif all(p.qos_profile.reliability == ReliabilityPolicy.RELIABLE for p in publishers):
            reliability = ReliabilityPolicy.RELIABLE
        else:
            reliability = ReliabilityPolicy.BEST_EFFORT
        durability = DurabilityPolicy.VOLATILE
        if publishers and all(
            p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in publishers
        ):
            durability = DurabilityPolicy.TRANSIENT_LOCAL
        return QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=self.qos_depth,
            reliability=reliability,
            durability=durability,
        )

    def _make_callback(self, topic: str):
        bag = self.bag
        clock = self.get_clock()

        def on_message(data: bytes) -> None:
            if self.done:
                return
            bag.write(topic, data, clock.now().nanoseconds)
            self.total += 1
            if self.max_messages is not None and self.total >= self.max_messages:
                self.done = True

        return on_message


def parse_topic_specs(specs: Sequence[str]) -> dict[str, str | None]:
    """``['name', 'name:pkg/msg/Type', ...]`` to {name: type or None}; defaults fill types."""
    topics: dict[str, str | None] = {}
    for spec in specs:
        name, _, msgtype = spec.partition(':')
        if not name:
            raise ValueError(f'bad topic {spec!r}: expected NAME or NAME:pkg/msg/Type')
        default = DEFAULT_TOPICS.get(name.lstrip('/'))
        topics[name] = msgtype or default
    return topics


def build_parser() -> argparse.ArgumentParser:
    """Command-line arguments of ``galvoscan record``."""
    parser = argparse.ArgumentParser(
        prog='galvoscan record',
        description='Record topics (CDR bytes, receive time) into a rosbag2 directory '
        '(metadata.yaml + MCAP, with message definitions). Stop with Ctrl-C.',
    )
    parser.add_argument(
        'topics', nargs='*', metavar='TOPIC[:TYPE]',
        help='topics to record; default: ' + ', '.join(DEFAULT_TOPICS),
    )
    parser.add_argument(
        '-o', '--output', type=Path, default=None,
        help='new bag directory (default: rosbag2_YYYY_MM_DD-HH_MM_SS)',
    )
    parser.add_argument('-a', '--all', action='store_true', help='record every topic')
    parser.add_argument('-d', '--duration', type=float, default=None, help='stop after [s]')
    parser.add_argument(
        '-n', '--max-messages', type=int, default=None, help='stop after this many messages'
    )
    parser.add_argument(
        '--flush-interval', type=float, default=0.5,
        help='write the pending chunk at least this often [s] (default 0.5)',
    )
    parser.add_argument(
        '--chunk-size', type=int, default=ROSBAGS_CHUNK_LIMIT,
        help=f'chunk size [bytes], at most {ROSBAGS_CHUNK_LIMIT} (default)',
    )
    parser.add_argument('--fsync', action='store_true', help='fsync after every chunk')
    parser.add_argument(
        '--qos', choices=QOS_MODES, default='auto',
        help='subscription reliability (default auto: match the publishers)',
    )
    parser.add_argument(
        '--qos-depth', type=int, default=100, help='subscription queue depth (default 100)'
    )
    return parser


@contextlib.contextmanager
def signals_ignored():
    """Ignore SIGINT/SIGTERM inside the block (so a second Ctrl-C cannot cut a bag's close)."""
    previous = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            previous[sig] = signal.signal(sig, signal.SIG_IGN)
        except ValueError:  # not the main thread: nothing to protect
            pass
    try:
        yield
    finally:
        for sig, handler in previous.items():
            if handler is not None:
                signal.signal(sig, handler)


def main(argv: Sequence[str] | None = None) -> int:
    """Run the recorder until Ctrl-C, SIGTERM, ``--duration`` or ``--max-messages``.

    Returns 0 on success, 1 on an error (the bag is closed in every case).
    """
    argv = list(sys.argv[1:] if argv is None else argv)
    cli_args, ros_args = split_ros_args(argv)
    args = build_parser().parse_args(cli_args)
    try:
        topics = parse_topic_specs(args.topics) if args.topics else dict(DEFAULT_TOPICS)
        if args.duration is not None and not args.duration > 0:
            raise ValueError(f'--duration must be > 0 s, got {args.duration}')
        output = args.output or Path(datetime.now().strftime('rosbag2_%Y_%m_%d-%H_%M_%S'))
        bag = BagWriter(
            output, chunk_size=args.chunk_size, flush_interval=args.flush_interval,
            fsync=args.fsync,
        )
    except (ValueError, FileExistsError) as err:
        print(f'galvoscan record: error: {err}', file=sys.stderr)
        return 1

    tune_this_process()
    rclpy.init(args=['galvoscan record', *ros_args])
    node = None
    status = 0
    try:
        bag.open()
        node = BagRecorder(
            bag, topics, all_topics=args.all, qos_mode=args.qos, qos_depth=args.qos_depth,
            max_messages=args.max_messages,
        )
        executor = EventsExecutor()
        executor.add_node(node)
        freeze_startup_heap()
        deadline = None if args.duration is None else time.monotonic() + args.duration
        while rclpy.ok() and not node.done:
            executor.spin_once(timeout_sec=0.1)
            if deadline is not None and time.monotonic() >= deadline:
                break
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception as err:  # report, but still close the bag below
        print(f'galvoscan record: error: {type(err).__name__}: {err}', file=sys.stderr)
        status = 1
    finally:
        with signals_ignored():
            silent = [] if node is None or args.all else node.silent_topics()
            if node is not None:
                node.destroy_node()
            bag.close()
            rclpy.try_shutdown()
    if not bag.path.exists():  # never opened (e.g. the folder cannot be made): no summary
        return status
    counts = bag.counts
    print(f'recorded {sum(counts.values())} messages to {bag.path}')
    for topic, count in sorted(counts.items()):
        print(f'  {topic}: {count}')
    if silent:
        print(f'galvoscan record: warning: no message on {", ".join(silent)} (no publisher, '
              'a misspelt name, or another ROS_DOMAIN_ID?)', file=sys.stderr)
    return status


if __name__ == '__main__':
    sys.exit(main())
