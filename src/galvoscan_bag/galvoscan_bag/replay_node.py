"""``galvoscan replay``: publish a bag's messages on their topics.

Messages are published as the stored CDR bytes (rclpy's ``Publisher.publish`` accepts ``bytes``
and calls ``publish_raw``), so nothing is deserialised. Timing follows the log times, divided by
``--rate``; rate 0 publishes as fast as possible. Each publisher offers the recorded reliability
and durability (reliable, volatile when none was recorded) with KEEP_LAST(``--qos-depth``).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable, Collection, Sequence
from pathlib import Path

import rclpy
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import ReliabilityPolicy

from galvoscan_common.runtime import freeze_startup_heap, tune_this_process

from .reader import BagReadError, read_messages, read_topics
from .ros_messages import import_message_class, qos_from_rosbags, split_ros_args


def _absolute(name: str) -> str:
    return name if name.startswith('/') else '/' + name


def parse_remaps(specs: Sequence[str]) -> dict[str, str]:
    """``['from:=to', ...]`` to {'/from': '/to'} (names made absolute)."""
    remaps = {}
    for spec in specs:
        source, sep, target = spec.partition(':=')
        if not sep or not source or not target:
            raise ValueError(f'bad remap {spec!r}: expected FROM:=TO')
        remaps[_absolute(source)] = _absolute(target)
    return remaps


class BagPlayer(Node):
    """Publishes the messages of one bag.

    Parameters
    ----------
    bag_path : path
        rosbag2 directory (or complete ``.mcap`` file).
    rate : float
        Playback speed factor; 1 = recorded timing, 0 = as fast as possible [1].
    topics : collection of str, optional
        Only these bag topics (as stored, e.g. '/galvo/state'); default all.
    remap : dict of str to str, optional
        Bag topic to published topic.
    qos_depth : int
        KEEP_LAST depth of the publishers [messages].
    """

    def __init__(
        self,
        bag_path: Path | str,
        *,
        rate: float = 1.0,
        topics: Collection[str] | None = None,
        remap: dict[str, str] | None = None,
        qos_depth: int = 100,
    ) -> None:
        super().__init__('bag_player')
        if not rate >= 0:
            raise ValueError(f'rate must be >= 0, got {rate}')
        self.bag_path = Path(bag_path)
        self.rate = rate
        infos = read_topics(self.bag_path)
        known = {info.topic for info in infos}
        if topics is not None:
            topics = {_absolute(t) for t in topics}
            unknown = set(topics) - known
            if unknown:
                raise ValueError(f'topics {sorted(unknown)} are not in bag {self.bag_path}')
        remap = {_absolute(k): v for k, v in (remap or {}).items()}
        unknown = set(remap) - known
        if unknown:
            raise ValueError(f'remapped topics {sorted(unknown)} are not in bag {self.bag_path}')
        self.topics = sorted(topics if topics is not None else known)
        self._bag_publishers = {}
        for info in infos:
            if info.topic not in self.topics:
                continue
            qos = qos_from_rosbags(info.qos[0] if info.qos else None, qos_depth)
            self._bag_publishers[info.topic] = self.create_publisher(
                import_message_class(info.msgtype), remap.get(info.topic, info.topic), qos
            )
        self.published = 0

    def wait_for_subscribers(self, count: int, timeout: float) -> bool:
        """Wait until every publisher has at least ``count`` subscriptions; False on timeout."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and rclpy.ok():
            if all(p.get_subscription_count() >= count for p in self._bag_publishers.values()):
                return True
            time.sleep(0.02)
        return all(p.get_subscription_count() >= count for p in self._bag_publishers.values())

    def play_once(self, should_stop: Callable[[], bool] = lambda: not rclpy.ok()) -> int:
        """Publish the bag once with its timing; returns the number of messages published."""
        count = 0
        start = time.monotonic()
        first = None
        for message in read_messages(self.bag_path, self.topics):
            if first is None:
                first = message.log_time_ns
            if self.rate > 0:
                target = start + (message.log_time_ns - first) * 1e-9 / self.rate
                while True:
                    if should_stop():
                        return count
                    delay = target - time.monotonic()
                    if delay <= 0:
                        break
                    time.sleep(min(delay, 0.05))
            elif should_stop():
                return count
            self._bag_publishers[message.topic].publish(message.data)
            count += 1
            self.published += 1
        return count

    def wait_for_acks(self, timeout: float) -> bool:
        """Wait until reliable subscribers acknowledged everything published (or timeout)."""
        ok = True
        for publisher in self._bag_publishers.values():
            if publisher.qos_profile.reliability == ReliabilityPolicy.RELIABLE:
                ok = publisher.wait_for_all_acked(Duration(seconds=timeout)) and ok
        return ok


def build_parser() -> argparse.ArgumentParser:
    """Command-line arguments of ``galvoscan replay``."""
    parser = argparse.ArgumentParser(
        prog='galvoscan replay',
        description='Publish a bag with its recorded timing (scaled by --rate). Stop with Ctrl-C.',
    )
    parser.add_argument('bag', type=Path, help='rosbag2 directory (or complete .mcap file)')
    parser.add_argument(
        '-r', '--rate', type=float, default=1.0,
        help='speed factor: 1 = recorded timing, 2 = twice as fast, 0 = as fast as possible',
    )
    parser.add_argument('-l', '--loop', action='store_true', help='replay until stopped')
    parser.add_argument('--topics', nargs='+', default=None, help='only these bag topics')
    parser.add_argument(
        '--remap', action='append', default=[], metavar='FROM:=TO',
        help='publish bag topic FROM on TO (repeatable)',
    )
    parser.add_argument(
        '--qos-depth', type=int, default=100, help='publisher queue depth (default 100)'
    )
    parser.add_argument(
        '--wait-subscribers', type=int, default=0, metavar='N',
        help='before playing, wait until every topic has N subscribers (default 0)',
    )
    parser.add_argument(
        '--wait-timeout', type=float, default=10.0,
        help='longest wait for --wait-subscribers [s] (default 10); then play anyway',
    )
    parser.add_argument(
        '--delay', type=float, default=0.0, help='pause after start-up before playing [s]'
    )
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Replay a bag once (or with ``--loop`` until Ctrl-C/SIGTERM). Returns an exit status."""
    argv = list(sys.argv[1:] if argv is None else argv)
    cli_args, ros_args = split_ros_args(argv)
    args = build_parser().parse_args(cli_args)
    try:
        remap = parse_remaps(args.remap)
        if args.qos_depth < 1:
            raise ValueError(f'--qos-depth must be >= 1, got {args.qos_depth}')
        if args.delay < 0 or args.wait_timeout < 0 or args.wait_subscribers < 0:
            raise ValueError('--delay, --wait-timeout and --wait-subscribers must be >= 0')
    except ValueError as err:
        print(f'galvoscan replay: error: {err}', file=sys.stderr)
        return 1

    tune_this_process()
    rclpy.init(args=['galvoscan replay', *ros_args])
    node = None
    status = 0
    try:
        node = BagPlayer(
            args.bag, rate=args.rate, topics=args.topics, remap=remap, qos_depth=args.qos_depth
        )
        if args.wait_subscribers and not node.wait_for_subscribers(
            args.wait_subscribers, args.wait_timeout
        ):
            node.get_logger().warning('not every topic has its subscribers yet; playing anyway')
        freeze_startup_heap()
        end = time.monotonic() + args.delay
        while rclpy.ok() and time.monotonic() < end:
            time.sleep(min(0.05, max(0.0, end - time.monotonic())))
        while rclpy.ok():
            if node.play_once() == 0 or not args.loop:
                break
        if rclpy.ok():
            node.wait_for_acks(2.0)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except (BagReadError, FileNotFoundError, ValueError) as err:
        print(f'galvoscan replay: error: {err}', file=sys.stderr)
        status = 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    if node is not None:
        print(f'published {node.published} messages from {args.bag}')
    return status


if __name__ == '__main__':
    sys.exit(main())
