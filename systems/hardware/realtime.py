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


WORKER_PRIORITY = 10  # a forked worker of a real-time loop: real-time, below the loops (50)


def lower_realtime() -> None:
    """A forked worker of a SCHED_FIFO loop: SCHED_FIFO WORKER_PRIORITY, so the loops preempt it and
    the machine's other processes do not (at nice -20 it got ~12 % of a core under load 35: its
    calls missed t_p). The kernel caps all real-time tasks together at sched_rt_runtime_us (95 %)
    of the CPUs: the loops and the worker must fit in it (docs/hardware.md)."""
    try:
        if os.sched_getscheduler(0) == os.SCHED_FIFO:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(WORKER_PRIORITY))
    except (PermissionError, OSError, AttributeError):
        pass
