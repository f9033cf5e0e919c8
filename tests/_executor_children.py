"""Child programs for the executor tests: a relay node that gets Ctrl-C while a callback runs.

``python -m tests._executor_children MODE DOMAIN TOPIC``: one node relays ``TOPIC`` to
``TOPIC/out``; its callback prints ``IN_CALLBACK``, sleeps ``CALLBACK_S`` (the parent sends SIGINT
meanwhile), publishes, and prints ``CALLBACK_DONE``. The node runs its callbacks by ``MODE``:

- ``thread``: the node's own thread (the default), the main thread sleeping;
- ``manual``: ``node.spin()`` on the main thread;
- ``single``: a ``SingleThreadedExecutor`` spinning on the main thread;
- ``multi``: a ``MultiThreadedExecutor`` spinning on the main thread.

The program catches KeyboardInterrupt as a user's would, prints ``INTERRUPTED`` and exits 0
after the node closed. SIGINT's default handler is restored first: a child of a background job
inherits it ignored.
"""

from __future__ import annotations

import signal
import sys
import time

STRING = "std_msgs/msg/String"
CALLBACK_S = 0.5


def main(mode: str, domain: int, topic: str) -> int:
    signal.signal(signal.SIGINT, signal.default_int_handler)
    from buffer_pubsub import Node

    executor_mode = "thread" if mode == "thread" else "manual"
    try:
        with Node("relay", domain_id=domain, executor=executor_mode) as node:
            out = node.create_publisher(STRING, f"{topic}/out")

            def relay(msg) -> None:
                print("IN_CALLBACK", flush=True)
                time.sleep(CALLBACK_S)
                out.publish(msg)
                print("CALLBACK_DONE", flush=True)

            node.create_subscription(STRING, topic, relay)
            node.create_publisher(STRING, topic).publish(out.msg_type(data="frame"))
            if mode == "thread":
                while True:
                    time.sleep(0.05)
            elif mode == "manual":
                node.spin()
            else:
                from buffer_pubsub.executors import MultiThreadedExecutor, SingleThreadedExecutor

                executor = (SingleThreadedExecutor() if mode == "single"
                            else MultiThreadedExecutor(num_threads=2))
                with executor:
                    executor.add_node(node)
                    executor.spin()
    except KeyboardInterrupt:
        print("INTERRUPTED", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], int(sys.argv[2]), sys.argv[3]))
