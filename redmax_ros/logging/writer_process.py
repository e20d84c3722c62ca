"""The MCAP writer process behind ``McapLogger(writer="process")`` (not for direct use).

Started by the logger as ``python -m redmax_ros.logging.writer_process '<json config>'``. Reads
records from stdin shaped like MCAP records (``[opcode u8][length u64][content]``): Message
records ready to be copied into chunks, and control records (topic registration, flush request,
close), and writes them with :class:`redmax_ros.logging.mcap_log.FileSession`. Reports JSON lines on stdout: ``opened`` (a
new file), ``written`` (messages written so far, at most every 0.2 s), ``flushed`` (a flush
request is done), ``error``, and finally ``closed``.

It runs at a lower scheduling priority (nice +10, ``REDMAX_LOG_NICE``): when the cores are
busy, the simulation and the node's DDS threads go first; the writer catches up (nothing is
dropped: records wait in the pipe and the node's buffer). It ignores SIGINT, SIGTERM and SIGHUP:
a Ctrl-C in the terminal or a stop signal to the process group must not cut the file short while the node drains; the file is finished on the close frame
or when stdin reaches EOF (the node exited, however it exited).
"""
from __future__ import annotations

import json
import os
import select
import signal
import sys
import time

from redmax_ros.logging.mcap_log import FRAME, K_CLOSE, K_FLUSH, K_MESSAGE, K_TOPIC, FileSession, Topic

REPORT_EVERY = 0.2  # s between 'written' reports
NICE = 10  # scheduling priority increment: on a busy machine the simulation goes first (REDMAX_LOG_NICE)


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, signal.SIG_IGN)
    try:  # lower priority: the writer has slack (records wait in the pipe and the node's buffer,
        # nothing is dropped), the simulation thread and the node's DDS threads have none
        os.nice(int(os.environ.get("REDMAX_LOG_NICE", NICE)))
    except (OSError, ValueError, AttributeError):
        pass
    status_fd = os.dup(1)
    os.dup2(2, 1)  # stray prints go to stderr, never into the status stream
    sys.stdout = sys.stderr

    def report(**kw):
        try:
            os.write(status_fd, (json.dumps(kw) + "\n").encode())
        except OSError:  # the node is gone (it exited first): nothing to report to, the file is complete
            pass

    cfg = json.loads(argv[0])
    try:
        sess = FileSession(**cfg, on_open=lambda path: report(opened=str(path)))
    except BaseException as e:
        report(error=f"cannot open the MCAP file: {type(e).__name__}: {e}")
        return 1

    rc = 0
    fd = sys.stdin.fileno()
    buf = bytearray()
    last_report, reported = time.monotonic(), -1
    try:
        done = False
        while not done:
            ready, _, _ = select.select([fd], [], [], max(0.0, sess.next_deadline() - time.monotonic()))
            if ready:
                data = os.read(fd, 1 << 20)
                if not data:  # EOF: the caller is gone (or closed without a close frame)
                    done = True
                buf += data
            pos, n = 0, len(buf)
            while n - pos >= 9:
                pos = sess.add_records(buf, pos, n)  # the bulk: ready-made Message records
                if n - pos < 9:
                    break
                kind, length = FRAME.unpack_from(buf, pos)
                end = pos + 9 + length
                if end > n:
                    break
                if kind == K_MESSAGE:  # complete but not taken by add_records: cannot happen
                    raise RuntimeError("message record left unconsumed")
                if kind == K_TOPIC:
                    sess.register(Topic.from_json(buf[pos + 9:end]))
                elif kind == K_FLUSH:
                    sess.flush()
                    report(flushed=int.from_bytes(buf[pos + 9:end], "little"), written=sess.written)
                elif kind == K_CLOSE:
                    done = True
                    pos = end
                    break
                else:
                    raise ValueError(f"unknown record kind 0x{kind:02x}")
                pos = end
            if pos:
                del buf[:pos]
            sess.tick()
            now = time.monotonic()
            if sess.written != reported and now - last_report >= REPORT_EVERY:
                report(written=sess.written)
                last_report, reported = now, sess.written
    except BaseException as e:  # disk full, bad frame, ...: say why, finish what we have
        report(error=f"{type(e).__name__}: {e}")
        rc = 1
    finally:
        try:
            sess.finish()
        except BaseException as e:
            report(error=f"finishing {sess.files[-1] if sess.files else 'the file'}: {type(e).__name__}: {e}")
            rc = 1
        report(closed=True, written=sess.written)
    return rc


if __name__ == "__main__":
    sys.exit(main())
