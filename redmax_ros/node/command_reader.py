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

Superseded messages are not read: a subscription may have a ``key`` (raw bytes -> hashable, or None when
it cannot tell; cdr.joint_state_key for joint_commands). Of the messages one drain takes from that
subscription, one whose key a newer message of the same drain repeats would only set what the newer one
sets again, so it goes to ``superseded`` (logged and counted as coalesced, not deserialized nor
validated), as if DDS's keep-last had dropped it; every other message goes to its callback, in arrival
order. Under a 10 kHz flood of the wrist's commands on the hand this cut the command thread from ~33 %
to 5-7 % of a core (redmax_bench node --only flood).
"""
from __future__ import annotations

import threading
import time

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy

BURST_PAUSE = 0.005  # s between drains while messages keep coming (<= 200 drains/s under a flood)
MAX_DRAIN = 1000  # messages one drain takes from one subscription at most


class CommandReader:
    """Serve ``subs`` (rclpy raw subscriptions of ``node``, a node no executor spins) with ``callbacks``
    (bytes -> None, one per subscription) from a thread of its own. ``keys`` and ``superseded``: per
    subscription a key function and the callback of superseded messages (None: every message goes to
    its callback). ``on_error(text)`` reports a callback failure (never raises)."""

    def __init__(self, node, subs, callbacks, on_error=None, burst_pause: float = BURST_PAUSE, keys=None,
                 superseded=None):
        self.node = node
        self.subs = list(subs)
        self.callbacks = list(callbacks)
        self.keys = list(keys) if keys is not None else [None] * len(self.subs)
        self.superseded_cbs = list(superseded) if superseded is not None else [None] * len(self.subs)
        self.superseded = 0  # messages dropped unread because a newer one with the same key followed
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
            for s, cb, key, sup in zip(subs, cbs, self.keys, self.superseded_cbs):
                msgs = self._take(s)
                if not msgs:
                    continue
                n += len(msgs)
                stale = self._stale(msgs, key) if key is not None and sup is not None and len(msgs) > 1 else ()
                for i, data in enumerate(msgs):
                    try:
                        if i in stale:
                            sup(data)
                        else:
                            cb(data)
                    except Exception as e:  # the callbacks guard themselves; this is a last resort
                        self._error(f"command callback failed: {type(e).__name__}: {e}")
                self.superseded += len(stale)
            if n:
                self.taken += n
                self.drains += 1
                if n > 1 and self.burst_pause > 0 and not self._stop:
                    time.sleep(self.burst_pause)

    def _take(self, s) -> list:
        """Every message waiting on subscription ``s`` (raw bytes, arrival order), at most MAX_DRAIN."""
        msgs = []
        while not self._stop and len(msgs) < MAX_DRAIN:
            try:
                with s.handle:
                    got = s.handle.take_message(s.msg_type, True)
            except Exception:  # the subscription is being destroyed (close)
                break
            if got is None:
                break
            msgs.append(got[0])
        return msgs

    @staticmethod
    def _stale(msgs, key) -> set:
        """Indices of the messages whose key a newer message in ``msgs`` repeats."""
        seen, stale = set(), set()
        for i in range(len(msgs) - 1, -1, -1):
            k = key(msgs[i])
            if k is None:
                continue
            if k in seen:
                stale.add(i)
            else:
                seen.add(k)
        return stale

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
