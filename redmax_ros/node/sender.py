"""How the node hands serialized messages to DDS.

rclpy's ``Publisher.publish(bytes)`` (``publish_raw``) keeps the GIL for the whole DDS write. A
write to a subscribed topic costs tens of us, and a write can block for a long time when a
reliable reader falls behind (seen: ~0.5 s in free-run); with the GIL held, every other Python
thread of the node (services, commands, diagnostics) freezes meanwhile.

``Sender`` calls ``rcl_publish_serialized_message`` through ctypes instead, in one of three modes
(``REDMAX_PUBLISH_MODE``):

* ``auto`` (default): ``thread`` while the node free-runs as fast as possible (``set_overlap``, called by
  the node before each published step), ``direct`` otherwise;
* ``direct``: in the calling thread, with the GIL released for a write to a topic with
  subscribers;
* ``thread``: handed to one FIFO publisher thread (a deque append and a raw-lock wake-up,
  ~1-2 us for the caller), so the DDS write (the GIL released) overlaps the next step on the other
  core; the queue is bounded (back-pressure);
* ``rclpy``: ``Publisher.publish`` in the calling thread, GIL held, as before.

In every mode a message on a volatile topic without subscribers is not written at all (it could
reach nobody; the log has it anyway).

What ``thread`` gains (2026-12-05, hand in free-run as fast as possible, h = 1 ms, joint_states
every step to a raw subscriber in another process): the compiled step made the simulation thread's
own work per step small (~100-150 us), and a DDS write of joint_states to a subscriber in another
process costs ~50 us of the writing thread's CPU right after a step (its thread CPU time measured
inside the write; ~20-30 us back to back), a third of a step. In the thread mode that write runs on
the other core: in one process at load 1.2-1.4, 5 539 steps/s against 4 708-4 866 with ``direct``
(+14-18 %); ``redmax_bench node`` (c) at load 1.6-2.2, RTF 6.01 against 5.69 with logging off and
5.01 against 4.40 with it; at load 3.6-4 RTF 3.3-4.8 against 2.3-3.2. (On 2026-11-22, with a step
costing ~160 us, the thread mode measured 0.95-0.98 x ``direct`` at load 1.1-1.5: a GIL hand-over
per message then ate what the overlap gained.) Why not always: the publisher thread writes what queued
up while it waited for the GIL back to back, and at load 3-4 a reliable Python subscriber taking
joint_states at 1 kHz (paced free-run, ``test_node_freerun.py``) then lost messages (39 of the 200 of a
0.2 s window received; the test failed in 2 of ~22 runs, and in none of 19 with ``direct``). Delivery at
real time is worth more to a controller than throughput, so ``auto`` overlaps the writes only in free-run
as fast as possible, where the node floods its subscribers either way (with recorded runs, 2026-12-05,
``redmax_bench node`` (c), hand, load 1.6-1.9: RTF logging off 12.2 ``direct`` / 14.2 ``thread`` / 13.9
``auto``, logging on 8.7 / 10.1 / 9.6).

Guarantees in every mode: messages go out in the order they were handed over (one FIFO in the
thread mode); ``drain`` waits until everything handed over is published (services and the action
call it before answering); ``close`` drains and stops the thread before the publishers may be
destroyed. If ctypes cannot find ``librcl``, the mode falls back to ``rclpy``.
"""
from __future__ import annotations

import collections
import ctypes
import os
import threading
import time

import rclpy  # noqa: F401  (loads librcl and librcutils, which load_library then finds)
from rclpy.qos import DurabilityPolicy


class _Allocator(ctypes.Structure):  # rcutils_allocator_t
    _fields_ = [(name, ctypes.c_void_p) for name in ("allocate", "deallocate", "reallocate", "zero_allocate",
                                                     "state")]


class _SerializedMessage(ctypes.Structure):  # rcl_serialized_message_t = rcutils_uint8_array_t
    # buffer is uint8_t *; declared c_char_p so that assigning a bytes object stores its data
    # pointer (and keeps the object alive) in ~0.4 us, vs ~3 us for cast(c_char_p(data), c_void_p)
    _fields_ = [("buffer", ctypes.c_char_p), ("buffer_length", ctypes.c_size_t),
                ("buffer_capacity", ctypes.c_size_t), ("allocator", _Allocator)]


class _ErrorString(ctypes.Structure):  # rcutils_error_string_t
    _fields_ = [("str", ctypes.c_char * 1024)]


def load_library(name):
    """The shared library ``name`` (e.g. ``librcl.so``) as a ``ctypes.CDLL``, as this process has
    loaded it (rclpy loads librcl), or None."""
    try:
        return ctypes.CDLL(name)  # already loaded by rclpy: found by its soname
    except OSError:
        pass
    try:  # by the path rclpy loaded it from
        with open("/proc/self/maps") as f:
            for line in f:
                path = line.split()[-1]
                if os.path.basename(path) == name:
                    return ctypes.CDLL(path)
    except OSError:
        pass
    return None


def _rcl_publish():
    """(rcl_publish_serialized_message releasing the GIL, the same holding the GIL,
    rcutils_get_error_string, rcutils_reset_error) or None."""
    rcl, rcutils = load_library("librcl.so"), load_library("librcutils.so")
    if rcl is None or rcutils is None:
        return None
    try:
        fn = rcl.rcl_publish_serialized_message
        held = ctypes.PyDLL(rcl._name).rcl_publish_serialized_message
        get_err, reset_err = rcutils.rcutils_get_error_string, rcutils.rcutils_reset_error
    except (AttributeError, OSError):
        return None
    for f in (fn, held):
        f.argtypes = [ctypes.c_void_p, ctypes.POINTER(_SerializedMessage), ctypes.c_void_p]
        f.restype = ctypes.c_int
    get_err.argtypes, get_err.restype = [], _ErrorString
    reset_err.argtypes, reset_err.restype = [], None
    return fn, held, get_err, reset_err


class _Wake:
    """A wake-up flag for one waiting thread (the publisher thread): ``threading.Event`` at a fraction
    of its cost. ``set`` releases a raw lock (~0.5 us; ``Event.set`` takes a Condition and notifies its
    waiters, ~2 us), ``wait_clear`` blocks in the lock's acquire (GIL released) until set, then clears.
    The lock is held exactly while the flag is clear."""

    def __init__(self):
        self._lock = threading.Lock()
        self._lock.acquire()
        self._guard = threading.Lock()
        self._flag = False

    def is_set(self) -> bool:
        return self._flag

    def set(self):
        with self._guard:
            if not self._flag:
                self._flag = True
                self._lock.release()

    def wait_clear(self):
        """Wait until set, then clear (what was handed over before ``set`` is visible to the caller)."""
        self._lock.acquire()
        with self._guard:
            self._flag = False


class Sender:
    """``send(publisher, data)`` from any thread, in one of three modes (``REDMAX_PUBLISH_MODE``):

    ``auto`` (default): ``thread`` while ``set_overlap(True)``, else ``direct``. ``direct``: published in
    the calling thread through ctypes, the GIL released for a write to a topic with subscribers.
    ``thread``: handed to the publisher thread. ``rclpy``:
    ``Publisher.publish`` in the calling thread, the GIL held (the node before this module).

    ``on_error(text)`` is called for a failed ctypes publish while ``context_ok()`` is true;
    during shutdown failures are dropped silently."""

    MODES = ("direct", "thread", "auto", "rclpy")

    def __init__(self, context_ok=lambda: True, on_error=None, mode=None, max_queue=256, rcl=None, threaded=None):
        if threaded is not None:  # older spelling: threaded=True/False
            mode = "thread" if threaded else "rclpy"
        if mode is None:
            mode = os.environ.get("REDMAX_PUBLISH_MODE", "auto")
        if mode not in self.MODES:
            raise ValueError(f"publish mode must be one of {', '.join(self.MODES)}, got {mode!r}")
        self._context_ok = context_ok
        self._on_error = on_error
        # rcl: (publish releasing the GIL, publish holding it, get_error_string, reset_error) as
        # from _rcl_publish(); injectable for tests
        self._rcl = (rcl or _rcl_publish()) if mode != "rclpy" else None
        self.mode = mode if self._rcl is not None else "rclpy"
        self.max_queue = int(max_queue)
        self.published = 0
        self.failed = 0
        self.waits = 0  # times a sender waited for room in the queue (DDS slower than the producer)
        self._producers_waiting = 0
        self._info = {}  # publisher -> (handle, rcl_publisher_t address, volatile)
        self._sub_cache = {}
        self.hold_unsubscribed = True
        self._q = collections.deque()
        self._lock = threading.Lock()
        self._local = threading.local()
        self._inlines = 0  # threads inside inline() (send reads the thread-local flag only then)
        self._wake = _Wake()
        self._idle = threading.Condition()
        self._queued = 0  # messages handed to the thread
        self._stop = False
        self._thread = None
        self._overlap = False  # mode auto: messages go to the publisher thread while set (set_overlap)
        if self.mode in ("thread", "auto"):
            self._thread = threading.Thread(target=self._run, name="redmax-publisher", daemon=True)
            self._thread.start()

    @property
    def threaded(self) -> bool:
        return self._thread is not None

    def set_overlap(self, on: bool):
        """Mode ``auto``: from now on hand messages to the publisher thread (``on``), or publish them in the
        calling thread (what was handed to the thread before is drained first, so the order holds). Call it
        from the thread that sends (the node's simulation thread)."""
        on = bool(on)
        if on == self._overlap:
            return
        self._overlap = on
        if not on:
            self.drain()

    def send(self, pub, data: bytes, wake=True, count=None):
        """Hand over one serialized message. ``wake=False`` leaves the publisher thread asleep
        (the caller sends more right away and wakes it with the last one: one GIL hand-over per
        step instead of one per message). ``count``: the topic's subscriber count as the caller
        has just read it (the direct and thread modes then do not read it again)."""
        mode = self.mode
        if mode == "direct" or (mode == "auto" and not self._overlap):  # (the queue: thread mode, auto overlapping)
            return self._publish_direct(pub, data, count)
        if mode == "rclpy":
            return self._publish_here(pub, data)
        info = self._info.get(pub)
        if info is None:
            info = self._describe(pub)
        if not count and info[2]:  # see _nobody_listens
            if count is None:
                count = info[0].get_subscription_count()
            if count == 0:
                return None
        if self._stop or (self._inlines and getattr(self._local, "inline", False)):
            return self._publish_here(pub, data)
        if type(data) is not bytes:
            data = bytes(data)
        with self._lock:
            self._q.append((info[1], data, pub, count))
            self._queued += 1
            full = len(self._q) > self.max_queue
        if full:
            self._wait_for_room()
        elif wake and not self._wake.is_set():  # appended before the check: the consumer clears, then drains
            self._wake.set()

    def _publish_direct(self, pub, data, n=None):
        """Publish in the calling thread through ctypes: the GIL is released for a write to a
        topic with subscribers (other Python threads run meanwhile; a write that blocks on a
        slow reader does not freeze them), kept for one without. ``n``: subscriber count if the
        caller just read it."""
        fn, held, get_err, reset_err = self._rcl
        info = self._info.get(pub)
        if info is None:
            info = self._describe(pub)
        handle, ptr, volatile = info
        if n is None:
            n = handle.get_subscription_count()
        if n == 0 and volatile:
            return None  # nobody could ever receive it (see _nobody_listens)
        if not isinstance(data, bytes):
            data = bytes(data)
        msg = getattr(self._local, "msg", None)
        if msg is None:
            msg = self._local.msg = _SerializedMessage()
        msg.buffer = data
        msg.buffer_length = msg.buffer_capacity = len(data)
        ret = (fn if n else held)(ptr, ctypes.byref(msg), None)
        if ret != 0:
            self._failure(ret, get_err, reset_err)

    def _wait_for_room(self):
        """Back-pressure: a DDS write can block (a reliable writer whose history is full of
        unacknowledged samples waits for a slow reader). The queue must not grow without bound
        meanwhile (memory, and every later message, diagnostics included, would be late): the
        producer waits, without the GIL, until the queue is half empty, as it waited inside a
        synchronous publish before. Other Python threads (services) keep running."""
        self.waits += 1
        self._wake.set()
        with self._idle:
            self._producers_waiting += 1
            try:
                while len(self._q) > self.max_queue // 2 and self._thread is not None and self._thread.is_alive():
                    self._idle.wait(1.0)
            finally:
                self._producers_waiting -= 1

    @property
    def backlog(self) -> int:
        """Messages waiting for the publisher thread."""
        return len(self._q)

    def inline(self):
        """Context manager: this thread's messages are published right away in this thread, with
        rclpy as before the publisher thread existed. For a caller that waits for them anyway (the
        lockstep step service): no hand-over to the publisher thread and back. (A GIL-releasing
        ctypes publish here measured no faster in lockstep, so the plain rclpy call is used.)
        Whatever this thread queued before is drained first, so its messages keep their order."""
        return _Inline(self)

    def _failure(self, ret, get_err, reset_err):
        text = get_err().str.decode(errors="replace")
        reset_err()
        if self._on_error is not None and self._context_ok():
            try:
                self._on_error(f"publish failed (rcl code {ret}): {text}")
            except Exception:
                pass

    def wake(self):
        """Wake the publisher thread for what was sent with ``wake=False``."""
        if not self._wake._flag and self._thread is not None:
            self._wake.set()

    def _publish_here(self, pub, data):
        try:
            pub.publish(data)
        except Exception:
            if self._context_ok():
                raise  # a real failure; during shutdown the context is gone: drop silently

    def drain(self, timeout=5.0) -> bool:
        """Wait until everything handed over before this call is published."""
        if not self.threaded:
            return True
        target = self._queued
        if self.published + self.failed >= target:
            return True  # nothing pending: do not wake the publisher thread (it would take the GIL)
        self.wake()
        with self._idle:
            return self._idle.wait_for(lambda: self.published + self.failed >= target or self._thread is None
                                       or not self._thread.is_alive(), timeout)

    def close(self, timeout=5.0):
        """Publish what is queued, then stop the thread (before the publishers are destroyed)."""
        if self._thread is None:
            return
        self.drain(timeout)
        self._stop = True
        self._wake.set()
        self._thread.join(timeout)
        self._thread = None

    def _describe(self, pub):
        handle = pub.handle
        volatile = getattr(pub, "qos_profile", None) is not None and \
            pub.qos_profile.durability == DurabilityPolicy.VOLATILE
        info = self._info[pub] = (handle, handle.pointer, volatile)
        return info

    def _nobody_listens(self, pub) -> bool:
        """A message on a volatile topic without a matched subscriber reaches nobody, ever (a
        volatile writer gives late joiners nothing): skip the DDS write (~4 us). Checked on every
        message (~0.7 us), so a subscriber that has matched gets everything from then on, as
        DDS would deliver it. Transient-local topics are always written (their last message
        is kept for late joiners). The MCAP log is written before and independently."""
        info = self._info.get(pub)
        if info is None:
            info = self._describe(pub)
        return info[2] and info[0].get_subscription_count() == 0

    def _subscribed(self, pub, now) -> bool:
        """Whether ``pub`` has subscribers (refreshed every 0.1 s)."""
        hit = self._sub_cache.get(pub)
        if hit is None or now >= hit[1]:
            try:
                n = pub.get_subscription_count()
            except Exception:
                n = 1
            hit = self._sub_cache[pub] = (n > 0, now + 0.1)
        return hit[0]

    def _run(self):
        """Publish in FIFO order. A write to a topic with subscribers (delivery: tens of us) runs
        with the GIL released; a write to a topic nobody subscribes to takes a few us and runs with
        the GIL held: releasing it would cost a GIL hand-over back and forth with the simulation
        thread for each such message (with joint_states subscribed and /clock, solver_stats not,
        one hand-over per step instead of three)."""
        fn, held, get_err, reset_err = self._rcl
        msg = _SerializedMessage()
        q, wake, idle = self._q, self._wake, self._idle
        monotonic = time.monotonic
        while True:
            wake.wait_clear()
            done = 0
            while q:
                ptr, data, pub, n = q.popleft()
                msg.buffer = data
                msg.buffer_length = msg.buffer_capacity = len(data)
                if n is None:  # a transient-local topic: its count was not read
                    call = fn if not self.hold_unsubscribed or self._subscribed(pub, monotonic()) else held
                else:  # the count the sender read just before
                    call = fn if n or not self.hold_unsubscribed else held
                ret = call(ptr, ctypes.byref(msg), None)
                if ret != 0:
                    self.failed += 1
                    self._failure(ret, get_err, reset_err)
                else:
                    done += 1
                if self._producers_waiting and len(q) <= self.max_queue // 2:
                    self.published += done
                    done = 0
                    with idle:
                        idle.notify_all()
            if done:
                self.published += done
            with idle:
                idle.notify_all()
            if self._stop and not q:
                break


class _Inline:
    def __init__(self, sender):
        self.s = sender

    def __enter__(self):
        s = self.s
        self.counted = s.threaded
        if self.counted:
            s.drain()
            with s._lock:
                s._inlines += 1
            s._local.inline = True
        return self

    def __exit__(self, *exc):
        s = self.s
        s._local.inline = False
        if self.counted:
            with s._lock:
                s._inlines -= 1
        return False
