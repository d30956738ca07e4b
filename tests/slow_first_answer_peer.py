"""A service server in its own process whose first answer comes late (for the resend test).

``python slow_first_answer_peer.py DELAY`` serves ``slow/set_bool`` (std_srvs/SetBool): the
first request is answered after DELAY seconds, later ones at once; every answer's message
counts the requests received so far. Prints ``ready`` once the service exists.
"""

import sys
import time

import rclpy
from rclpy.node import Node
from std_srvs.srv import SetBool


def main():
    delay = float(sys.argv[1])
    rclpy.init()
    node = Node('slow_first_answer_peer')
    seen = []

    def answer(req, resp):
        seen.append(time.monotonic())
        if len(seen) == 1:
            time.sleep(delay)
        resp.success, resp.message = True, f'requests received: {len(seen)}'
        print(f'request {len(seen)}', flush=True)
        return resp

    node.create_service(SetBool, 'slow/set_bool', answer)
    print('ready', flush=True)
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, rclpy.executors.ExternalShutdownException):
        pass


if __name__ == '__main__':
    main()
