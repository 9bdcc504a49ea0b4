"""Real-time scheduling where permitted (SCHED_FIFO needs root or CAP_SYS_NICE), said in the summary."""

from __future__ import annotations

import os

FIFO_PRIORITY = 50  # above normal processes, below the kernel's own real-time threads (99)


def request_realtime(priority: int = FIFO_PRIORITY) -> dict:
    """Put this process, every thread of it, on SCHED_FIFO; {"scheduler", "warning"} for summary
    files. Every thread: the policy is per thread, and a thread started before (LCM's receive
    thread, started with the DrakeLcm) kept normal scheduling: under load it fell behind, its
    socket overflowed and the arm lost commands for 20-35 ms (the watchdog tripped)."""
    from threadpoolctl import threadpool_limits

    # One BLAS thread: an idle OpenBLAS thread spins after each call, and a spinning real-time
    # thread starves every normal process on its CPU (the workers, a normal-priority receiver).
    threadpool_limits(1)
    try:
        for thread in _threads():
            os.sched_setscheduler(thread, os.SCHED_FIFO, os.sched_param(priority))
        return {"scheduler": f"SCHED_FIFO {priority}", "warning": None}
    except (PermissionError, OSError, AttributeError) as err:
        warning = f"real-time scheduling not permitted ({err}): the 1 kHz loop shares the CPU at normal priority"
        return {"scheduler": "normal", "warning": warning}


def _threads() -> list[int]:
    """This process' thread ids (Linux); [0], this thread, elsewhere."""
    try:
        return [int(tid) for tid in os.listdir("/proc/self/task")]
    except OSError:
        return [0]


def lower_realtime(nice: int) -> None:
    """A forked worker of a SCHED_FIFO loop (or of one about to be): normal scheduling at `nice`,
    so the loops preempt it. Not real-time itself: the kernel caps real-time tasks at sched_rt_runtime_us (95 %)
    of each second, and a CPU-bound real-time worker used it up and stalled the loops for tens of
    ms (RT throttling, measured: docs/hardware.md). In a session (autogroup) of its own with the
    same nice: the kernel shares the CPU between autogroups first, so a nice within the run's
    group alone left it 10 % of a core beside four other users' sessions."""
    try:
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
        os.setpriority(os.PRIO_PROCESS, 0, nice)
        os.setsid()
        with open("/proc/self/autogroup", "w") as autogroup:
            autogroup.write(str(nice))
    except (PermissionError, OSError, AttributeError):
        pass
