"""Peer process for tests/test_interfaces_dds.py.

It echoes every galvoscan_msgs message from ``echo_in/<Type>`` to ``echo_out/<Type>`` and
serves every galvoscan_msgs service as ``peer/<Type>``. A service response is filled
deterministically from the sha256 of the request's field values (see :func:`fill`), and its
``message`` field carries that hash, so the caller can check the request arrived intact.
"""

import hashlib
import random
import sys

import galvoscan_msgs.msg
import galvoscan_msgs.srv
import numpy as np

MESSAGE_TYPES = [galvoscan_msgs.msg.GalvoState, galvoscan_msgs.msg.StripeCenters,
                 galvoscan_msgs.msg.CalibrationStage, galvoscan_msgs.msg.CalibrationInstruction,
                 galvoscan_msgs.msg.CalibrationProgress]
SERVICE_TYPES = [getattr(galvoscan_msgs.srv, n) for n in sorted(dir(galvoscan_msgs.srv))
                 if not n.startswith('_') and hasattr(getattr(galvoscan_msgs.srv, n), 'Request')]

_SCALARS = {
    'boolean': lambda r: r.random() < 0.5,
    'float': lambda r: float(np.float32(r.uniform(-1e3, 1e3))),
    'double': lambda r: r.uniform(-1e6, 1e6),
    'string': lambda r: ''.join(r.choice('abcxyz_0123') for _ in range(r.randint(0, 12))),
}
for _bits in (8, 16, 32, 64):
    _SCALARS[f'uint{_bits}'] = (lambda b: lambda r: r.randrange(0, 2 ** b))(_bits)
    _SCALARS[f'int{_bits}'] = (lambda b: lambda r: r.randrange(-2 ** (b - 1), 2 ** (b - 1)))(_bits)
_SCALARS['octet'] = _SCALARS['uint8']


def fill(msg, seed):
    """Fill every field of ``msg`` (recursively) with values drawn from ``seed``."""
    rng = random.Random(seed)
    _fill(msg, rng)
    return msg


def _fill(msg, rng):
    for name, ftype in msg.get_fields_and_field_types().items():
        if ftype.startswith('sequence<'):
            inner = ftype[len('sequence<'):-1].split(',')[0]
            n = rng.randint(0, 7)
            if inner in _SCALARS:
                values = [_SCALARS[inner](rng) for _ in range(n)]
                current = getattr(msg, name)
                if hasattr(current, 'typecode'):  # array.array field
                    current = type(current)(current.typecode, values)
                    setattr(msg, name, current)
                else:
                    setattr(msg, name, values)
            else:
                raise AssertionError(f'unhandled sequence type {ftype}')
        elif ftype in _SCALARS:
            setattr(msg, name, _SCALARS[ftype](rng))
        elif ftype.endswith(']') and ftype.split('[')[0] in _SCALARS:  # fixed-size array
            inner, n = ftype[:-1].split('[')
            setattr(msg, name, [_SCALARS[inner](rng) for _ in range(int(n))])
        elif ftype == 'builtin_interfaces/Time':
            setattr(msg, name, type(getattr(msg, name))(
                sec=rng.randrange(0, 2 ** 31), nanosec=rng.randrange(0, 10 ** 9)))
        else:  # nested message
            _fill(getattr(msg, name), rng)


def request_digest(request):
    """sha256 of the request's field values (CDR bytes are not canonical: padding varies)."""
    return hashlib.sha256(repr(request).encode()).hexdigest()


def expected_response(srv_type, request):
    digest = request_digest(request)
    response = fill(srv_type.Response(), int(digest[:12], 16))
    response.message = digest
    return response


def main():
    import rclpy
    from rclpy.node import Node

    rclpy.init(args=sys.argv)
    node = Node('dds_echo_peer')
    keep = []
    for mtype in MESSAGE_TYPES:
        pub = node.create_publisher(mtype, f'echo_out/{mtype.__name__}', 10)
        keep.append(node.create_subscription(
            mtype, f'echo_in/{mtype.__name__}', lambda m, p=pub: p.publish(m), 10))
    for stype in SERVICE_TYPES:
        keep.append(node.create_service(
            stype, f'peer/{stype.__name__}',
            lambda req, resp, s=stype: expected_response(s, req)))
    node.get_logger().info('peer ready')
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


if __name__ == '__main__':
    main()
