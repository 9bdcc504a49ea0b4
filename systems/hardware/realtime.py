"""Real-time scheduling where permitted (SCHED_FIFO needs root or CAP_SYS_NICE), said in the summary."""

from __future__ import annotations

import os

FIFO_PRIORITY = 50  # above normal processes, below the kernel's own real-time threads (99)


def request_realtime(priority: int = FIFO_PRIORITY) -> dict:
    """Put this process on SCHED_FIFO; {"scheduler", "warning"} for summary files."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        return {"scheduler": f"SCHED_FIFO {priority}", "warning": None}
    except (PermissionError, OSError, AttributeError) as err:
        warning = f"real-time scheduling not permitted ({err}): the 1 kHz loop shares the CPU at normal priority"
        return {"scheduler": "normal", "warning": warning}


WORKER_NICE = -20  # a forked worker of a real-time loop: the strongest normal priority


def lower_realtime() -> None:
    """A forked worker of a SCHED_FIFO loop: back to normal scheduling at nice WORKER_NICE. Not
    real-time: the kernel caps all real-time tasks together at sched_rt_runtime_us (95 %) of the
    CPUs, and a CPU-bound real-time worker beside two real-time loops on 2 cores hits the cap,
    which then stalls the loops for up to 50 ms of each second (measured: status_lost events)."""
    try:
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            os.setpriority(os.PRIO_PROCESS, 0, WORKER_NICE)
    except (PermissionError, OSError, AttributeError):
        pass
