"""The one ``main`` of every node: Jazzy-style init/spin/shutdown, bad parameters -> exit 2."""
import sys

import rclpy
from rclpy.executors import ExternalShutdownException


def spin_node(node_cls, name, args=None):
    """Create ``node_cls()``, spin it until Ctrl-C or shutdown, and clean up.

    A ValueError raised while the node declares and validates its parameters is a user
    error: it is printed as one line (``<name>: bad parameters: <reason>``) and the
    process exits with status 2, as docs/design.md §3 asks of invalid start-up parameters.
    """
    rclpy.init(args=args)
    try:
        node = node_cls()
    except ValueError as exc:
        print(f'{name}: bad parameters: {exc}', file=sys.stderr)
        rclpy.try_shutdown()
        return 2
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
