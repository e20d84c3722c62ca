"""A step_simulation server without an rclpy executor: its own thread waits on the service
alone and takes requests / sends responses as C structs through ctypes.

Why: the lockstep step service is the latency-critical path (one round trip per step for a
client that steps one step at a time). Served by rclpy, every request costs a Python request
object (``convert_to_py``), a Python response object (``Response()`` plus its nested Result and
Time, ~15-30 us of generated ``__init__`` code) and its conversion back (``convert_from_py``), on
top of the executor's dispatch; even rclpy's C++ EventsExecutor spent ~170 us of CPU per call of
a do-nothing server here. This server waits with rclpy's wait set (the GIL released), then calls
``rcl_take_request`` and ``rcl_send_response`` with ctypes mirrors of
``redmax_msgs__srv__StepSimulation_Request`` (``uint64 steps``) and ``..._Response`` (Result
{uint8, string}, uint64, builtin_interfaces/Time): no Python message objects at all. The struct
layouts come from the generated C headers (``install_msgs/include/.../step_simulation__struct.h``,
``rmw/types.h``'s ``rmw_request_id_t`` with RMW_GID_STORAGE_SIZE 16 in Jazzy); the tests call
the service from rclpy clients and compare every field.

``handler(steps) -> (code, message, completed_steps, sim_time_seconds)`` runs in the server's
thread; requests are served one at a time in arrival order, as by a single-threaded executor.
``available()`` is False when ctypes cannot find librcl (the node then serves the service from
an rclpy executor as before).
"""
from __future__ import annotations

import ctypes
import threading
import time

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy  # loads librcl (for load_library)

from redmax_msgs.srv import StepSimulation

from .sender import load_library

RCL_RET_OK = 0
RCL_RET_TIMEOUT = 2
RCL_RET_SERVICE_TAKE_FAILED = 601
# rmw_fastrtps returns RMW_RET_TIMEOUT ("client will not receive response") when the response writer has
# not matched the client's response reader within its max_blocking_time: a client created just before its
# call, discovery slowed by load (22 of 64 fresh clients in one CI run at load ~4). The send is retried
# (each attempt blocks up to max_blocking_time) until this many seconds have passed.
RESPONSE_RETRY_S = 5.0


class _RequestId(ctypes.Structure):  # rmw_request_id_t
    _fields_ = [("writer_guid", ctypes.c_uint8 * 16), ("sequence_number", ctypes.c_int64)]


class _Request(ctypes.Structure):  # redmax_msgs__srv__StepSimulation_Request
    _fields_ = [("steps", ctypes.c_uint64)]


class _String(ctypes.Structure):  # rosidl_runtime_c__String
    _fields_ = [("data", ctypes.c_void_p), ("size", ctypes.c_size_t), ("capacity", ctypes.c_size_t)]


class _Result(ctypes.Structure):  # redmax_msgs__msg__Result
    _fields_ = [("result", ctypes.c_uint8), ("error_message", _String)]


class _Time(ctypes.Structure):  # builtin_interfaces__msg__Time
    _fields_ = [("sec", ctypes.c_int32), ("nanosec", ctypes.c_uint32)]


class _Response(ctypes.Structure):  # redmax_msgs__srv__StepSimulation_Response
    _fields_ = [("result", _Result), ("completed_steps", ctypes.c_uint64), ("sim_time", _Time)]


_RCL = None


def _rcl():
    global _RCL
    if _RCL is None:
        rcl = load_library("librcl.so")
        fns = None
        if rcl is not None:
            rcutils = load_library("librcutils.so")
            try:
                take, send = rcl.rcl_take_request, rcl.rcl_send_response
                take.argtypes = [ctypes.c_void_p, ctypes.POINTER(_RequestId), ctypes.c_void_p]
                send.argtypes = [ctypes.c_void_p, ctypes.POINTER(_RequestId), ctypes.c_void_p]
                take.restype = send.restype = ctypes.c_int
                reset = rcutils.rcutils_reset_error if rcutils is not None else (lambda: None)
                fns = (take, send, reset)
            except AttributeError:
                fns = None
        _RCL = fns or False
    return _RCL or None


def available() -> bool:
    return _rcl() is not None


def split_time(t: float):
    ns = int(round(t * 1e9))
    return ns // 1_000_000_000, ns % 1_000_000_000


class StepServer:
    """Serve ``StepSimulation`` named ``name`` on ``node`` (an rclpy Node that no executor spins)
    from a thread of its own. ``on_error(text)`` reports a failed take/send (never raises)."""

    def __init__(self, node, name, handler, on_error=None, qos_profile=None):
        fns = _rcl()
        if fns is None:
            raise RuntimeError("librcl not found through ctypes")
        self._take, self._send, self._reset_error = fns
        self.node = node
        self.handler = handler
        self.on_error = on_error
        # created by rclpy (type support, QoS, name resolution, graph), never added to an executor
        # (qos_profile: the request queue; requests beyond its depth would be dropped by the middleware)
        kw = {} if qos_profile is None else {"qos_profile": qos_profile}
        self.service = node.create_service(StepSimulation, name, lambda req, resp: resp, **kw)
        self._context = node.context
        self._guard = _rclpy.GuardCondition(self._context.handle)
        self._ws = _rclpy.WaitSet(0, 1, 0, 0, 1, 0, self._context.handle)
        self._stop = False
        self.served = 0
        self.retried_sends = 0  # sends repeated after a middleware timeout (client not matched yet)
        self._thread = threading.Thread(target=self._run, name="redmax-step", daemon=True)

    @property
    def service_name(self):
        return self.service.srv_name

    def start(self):
        self._thread.start()

    def _error(self, text):
        if self.on_error is not None:
            try:
                self.on_error(text)
            except Exception:
                pass

    def _run(self):
        take, send = self._take, self._send
        header, req, resp = _RequestId(), _Request(), _Response()
        empty = ctypes.create_string_buffer(b"")
        hp, rp, sp = ctypes.byref(header), ctypes.byref(req), ctypes.byref(resp)
        ws, guard, handle = self._ws, self._guard, self.service.handle
        with handle:
            ptr = handle.pointer
            while not self._stop:
                ws.clear_entities()
                ws.add_service(handle)
                ws.add_guard_condition(guard)
                try:
                    ws.wait(-1)  # GIL released; the guard condition wakes it for close()
                except Exception:  # the context is shutting down
                    if self._stop or not self._context.ok():
                        break
                    raise
                while not self._stop:
                    ret = take(ptr, hp, rp)
                    if ret == RCL_RET_SERVICE_TAKE_FAILED:
                        break
                    if ret != RCL_RET_OK:
                        self._error(f"step_simulation: rcl_take_request failed (rcl code {ret})")
                        break
                    try:
                        code, message, done, t = self.handler(int(req.steps))
                    except Exception as e:  # the handler guards itself; this is a last resort
                        code, message, done, t = 4, f"{type(e).__name__}: {e}", 0, 0.0
                    text = message.encode() if message else b""
                    buf = ctypes.create_string_buffer(text) if text else empty  # NUL-terminated, alive until sent
                    resp.result.result = code
                    resp.result.error_message.data = ctypes.addressof(buf)
                    resp.result.error_message.size = len(text)
                    resp.result.error_message.capacity = len(text) + 1
                    resp.completed_steps = done
                    resp.sim_time.sec, resp.sim_time.nanosec = split_time(t)
                    self.served += 1  # before the send: a client holding the response sees it counted
                    ret = self._send_retrying(ptr, hp, sp)
                    if ret != RCL_RET_OK and not self._stop and self._context.ok():
                        self._error(f"step_simulation: rcl_send_response failed (rcl code {ret})")

    def _send_retrying(self, ptr, hp, sp) -> int:
        """rcl_send_response, retried while it times out on a client the middleware has not matched yet
        (RESPONSE_RETRY_S in all); the last rcl return code."""
        end = time.monotonic() + RESPONSE_RETRY_S
        while True:
            ret = self._send(ptr, hp, sp)
            if ret != RCL_RET_TIMEOUT or self._stop or not self._context.ok() or time.monotonic() > end:
                return ret
            self.retried_sends += 1
            self._reset_error()

    def close(self, timeout=5.0):
        self._stop = True
        try:
            self._guard.trigger_guard_condition()
        except Exception:
            pass
        if self._thread.is_alive():
            self._thread.join(timeout)
        for fn in (lambda: self.node.destroy_service(self.service), self._guard.destroy_when_not_in_use,
                   self._ws.destroy_when_not_in_use):
            try:
                fn()
            except Exception:
                pass
