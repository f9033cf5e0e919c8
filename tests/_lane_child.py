"""A fast-lane peer process for tests: ``python tests/_lane_child.py reader|writer NAME ...``.

reader NAME DEPTH: attach a LaneReader to a LaneWaker, then ``wait(None)`` in a loop (woken only
    by the ring's doorbell); prints ``ready``, then ``msg <text>`` per message; answers
    ``cpu?`` with ``cpu <seconds of CPU this process used>``; exits on ``stop``.
writer NAME COUNT INTERVAL_S: open the reader's service (retrying for 10 s), write ``m0`` ..
    ``m<COUNT-1>``, print ``done``, then write each stdin line as a message; exit on EOF.
"""

from __future__ import annotations

import sys
import time

from buffer_pubsub import fast_lane


def reader(name: str, depth: int) -> None:
    lane = fast_lane.LaneReader(name, depth=depth)
    waker = fast_lane.LaneWaker()
    running = True

    def on_message(data: bytes) -> None:
        nonlocal running
        text = data.decode()
        if text == "stop":
            running = False
        elif text == "cpu?":
            print(f"cpu {time.process_time():.6f}", flush=True)
        else:
            print(f"msg {text}", flush=True)

    waker.attach(lane, on_message)
    waker.wait(0.0)  # apply the attachment
    print("ready", flush=True)
    while running:
        waker.wait(None)
    waker.close()
    lane.close()


def writer(name: str, count: int, interval_s: float) -> None:
    deadline = time.monotonic() + 10.0
    while True:
        try:
            lane = fast_lane.LaneWriter(name)
            break
        except fast_lane.LaneUnavailableError:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)
    for i in range(count):
        lane.write(f"m{i}".encode())
        if interval_s:
            time.sleep(interval_s)
    print("done", flush=True)
    for line in sys.stdin:
        lane.write(line.strip().encode())
    lane.close()


if __name__ == "__main__":
    role, service = sys.argv[1], sys.argv[2]
    if role == "reader":
        reader(service, int(sys.argv[3]))
    else:
        writer(service, int(sys.argv[3]), float(sys.argv[4]))
