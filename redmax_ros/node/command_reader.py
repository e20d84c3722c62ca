"""The command subscriptions (joint_commands, joint_trajectory, point_commands, body_commands) read by one
thread, in bursts.

rclpy's executors call Python once per message; under a flood (10 kHz of joint_commands) that thread
took the GIL ~7000 times a second for ~75 us each and the free-run simulation thread, which shares the
GIL, fell to 16-26 % of its unflooded real-time factor (redmax_bench node --only flood, before this
module). Here one thread waits on the subscriptions with rclpy's wait set (GIL released), then takes
every message that is there (raw bytes, ``Subscription.take_message``) and hands each to its callback
(validation and coalescing, engine.py) under one GIL acquisition. After a burst (more than one message
in a drain) it sleeps ``burst_pause`` [s] (GIL released) before waiting again, so under a flood it
drains at most 1 / burst_pause times a second; the subscriptions' KEEP_LAST depth (10) keeps the
latest samples meanwhile and DDS drops older ones, never the latest. A lone message (commands at
normal rates) is handled as soon as it arrives.
"""
from __future__ import annotations

import threading
import time

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

BURST_PAUSE = 0.005  # s between drains while messages keep coming (<= 200 drains/s under a flood)


class CommandReader:
    """Serve ``subs`` (rclpy raw subscriptions of ``node``, a node no executor spins) with ``callbacks``
    (bytes -> None, one per subscription) from a thread of its own. ``on_error(text)`` reports a
    callback failure (never raises)."""

    def __init__(self, node, subs, callbacks, on_error=None, burst_pause: float = BURST_PAUSE):
        self.node = node
        self.subs = list(subs)
        self.callbacks = list(callbacks)
        self.on_error = on_error
        self.burst_pause = float(burst_pause)
        self._context = node.context
        self._guard = _rclpy.GuardCondition(self._context.handle)
        self._ws = _rclpy.WaitSet(len(self.subs), 1, 0, 0, 0, 0, self._context.handle)
        self._stop = False
        self.taken = 0  # messages taken
        self.drains = 0  # wake-ups that took at least one message
        self._thread = threading.Thread(target=self._run, name="redmax-commands", daemon=True)

    def start(self):
        self._thread.start()

    def _run(self):
        ws, guard, subs, cbs = self._ws, self._guard, self.subs, self.callbacks
        while not self._stop:
            ws.clear_entities()
            for s in subs:
                ws.add_subscription(s.handle)
            ws.add_guard_condition(guard)
            try:
                ws.wait(-1)  # GIL released; the guard condition wakes it for close()
            except Exception:  # the context is shutting down
                if self._stop or not self._context.ok():
                    break
                raise
            n = 0
            for s, cb in zip(subs, cbs):
                while not self._stop:
                    try:
                        with s.handle:
                            got = s.handle.take_message(s.msg_type, True)
                    except Exception:  # the subscription is being destroyed (close)
                        break
                    if got is None:
                        break
                    n += 1
                    try:
                        cb(got[0])
                    except Exception as e:  # the callbacks guard themselves; this is a last resort
                        self._error(f"command callback failed: {type(e).__name__}: {e}")
            if n:
                self.taken += n
                self.drains += 1
                if n > 1 and self.burst_pause > 0 and not self._stop:
                    time.sleep(self.burst_pause)

    def _error(self, text):
        if self.on_error is not None:
            try:
                self.on_error(text)
            except Exception:
                pass

    def close(self, timeout=5.0):
        self._stop = True
        try:
            self._guard.trigger_guard_condition()
        except Exception:
            pass
        if self._thread.is_alive():
            self._thread.join(timeout)
        for fn in [*(lambda s=s: self.node.destroy_subscription(s) for s in self.subs),
                   self._guard.destroy_when_not_in_use, self._ws.destroy_when_not_in_use, self.node.destroy_node]:
            try:
                fn()
            except Exception:
                pass
