"""The CPU time real-time (SCHED_FIFO/RR) threads take, per wall second, summed over every process
(docs/hardware.md, the stalls): run it beside `safesysid arm-sim` and `safesysid run --arm lcm`.

    python experiments/rt_cpu.py --seconds 14
"""

from __future__ import annotations

import argparse
import os
import time

POLICY_FIELD = 38  # /proc/PID/task/TID/stat's policy, counted after the ")" that ends comm
UTIME_FIELD, STIME_FIELD = 11, 12


def realtime_ticks() -> dict[tuple[str, str], int]:
    """Clock ticks of CPU used so far by every real-time thread, by (pid, tid)."""
    ticks = {}
    for pid in filter(str.isdigit, os.listdir("/proc")):
        try:
            for tid in os.listdir(f"/proc/{pid}/task"):
                with open(f"/proc/{pid}/task/{tid}/stat") as f:
                    text = f.read()
                fields = text[text.rindex(")") + 2 :].split()
                if int(fields[POLICY_FIELD]) in (os.SCHED_FIFO, os.SCHED_RR):
                    ticks[(pid, tid)] = int(fields[UTIME_FIELD]) + int(fields[STIME_FIELD])
        except (OSError, IndexError, ValueError):
            continue  # the thread ended meanwhile
    return ticks


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=14.0)
    args = parser.parse_args()
    hz = os.sysconf("SC_CLK_TCK")
    before, per_second = realtime_ticks(), []
    for _ in range(int(args.seconds)):
        time.sleep(1.0)
        now = realtime_ticks()
        per_second.append(sum(v - before.get(k, v) for k, v in now.items()) / hz)
        before = now
    print("real-time CPU-seconds per wall second:", " ".join(f"{x:.2f}" for x in per_second))


if __name__ == "__main__":
    main()
