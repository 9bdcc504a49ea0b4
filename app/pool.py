"""Runs on a local process pool, streamed to a JSON-lines file so an interrupted batch resumes
where it stopped, with a progress bar on stderr (`safesysid compare`).

`safesysid sweep` uses the same pool, reader and signal handling (its Ray path aside): Ctrl-C
reaches the whole process group, the workers ignore it and the parent
terminates them; SIGTERM unwinds like Ctrl-C; a line cut by a kill is dropped on resume.
"""

from __future__ import annotations

import json
import os
import signal
import sys
from collections.abc import Callable, Hashable, Iterator
from contextlib import contextmanager
from pathlib import Path

from safesysid.progress import Progress


def read_jsonl(path: Path, key: Callable[[dict], Hashable]) -> list[dict]:
    """The finished runs of a JSON-lines file. A line cut by a kill (not JSON, or without its
    key) and a repeated key are dropped and the file rewritten without them, so appending after
    a resume never glues a new line onto a broken one."""
    if not path.exists():
        return []
    text = path.read_text()
    done, seen, clean = [], set(), True
    for line in text.splitlines():
        try:
            record = json.loads(line)
            k = key(record)
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            clean = False  # run it again
            continue
        if k in seen:
            clean = False
            continue
        seen.add(k)
        done.append(record)
    if not clean or (text and not text.endswith("\n")):
        tmp = path.with_suffix(".jsonl.tmp")
        tmp.write_text("".join(json.dumps(r, default=float) + "\n" for r in done))
        os.replace(tmp, path)
    return done


@contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM (a scheduler's kill) unwinds like Ctrl-C: the workers are stopped and every
    finished run is already on disk."""

    def interrupt(signum: int, frame: object) -> None:
        raise KeyboardInterrupt

    try:
        previous = signal.signal(signal.SIGTERM, interrupt)
    except ValueError:  # not the main thread: leave signals alone
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _worker_signals() -> None:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the parent handles it
    signal.signal(signal.SIGTERM, signal.SIG_DFL)  # the parent's terminate() ends a worker at once


def _call(job: tuple) -> tuple:
    fn, args = job
    return args, fn(*args)


def pool_results(fn: Callable[..., dict], jobs: list[tuple], workers: int) -> Iterator[tuple[tuple, dict]]:
    """(args, fn(*args)) for each argument tuple of `jobs` as it finishes, on a local process pool
    (fn must be a module-level function). Closing the generator terminates the workers."""
    import multiprocessing

    import safesysid.online  # noqa: F401 -- imported once here, not in every forked worker

    pool = multiprocessing.Pool(processes=max(1, workers), initializer=_worker_signals)
    finished = False
    try:
        yield from pool.imap_unordered(_call, [(fn, args) for args in jobs])
        finished = True
    finally:
        if finished:
            pool.close()  # every job done: the workers exit on their sentinels
        else:  # an interrupt: stop the running jobs (their results were never written)
            _kill_workers(pool)
            pool.terminate()
        pool.join()


def _kill_workers(pool: object) -> None:
    """SIGKILL every worker: Pool.terminate()'s SIGTERM has been seen to leave a worker idle in
    its queue's lock forever, and terminate() then waits on it without a timeout."""
    for worker in getattr(pool, "_pool", ()):
        if worker.exitcode is None:
            worker.kill()


def run_streamed(
    fn: Callable[..., dict],
    jobs: list[tuple],
    workers: int,
    *,
    jsonl: Path,
    describe: Callable[[tuple, dict], str],
    label: str = "runs",
) -> tuple[list[dict], bool]:
    """Run fn(*job) for each job on `workers` processes, appending each summary to `jsonl` as it
    finishes (flushed and fsynced: a kill loses only the runs in flight), with a progress bar
    (describe(job, summary): its note). Returns (the new summaries, interrupted by Ctrl-C or
    SIGTERM). An exception of a run propagates after the pool is stopped."""
    progress = Progress(len(jobs), label)
    new, interrupted = [], False
    results = pool_results(fn, jobs, workers)
    with sigterm_as_interrupt(), jsonl.open("a") as fh:
        try:
            for job, summary in results:
                fh.write(json.dumps(summary, default=float) + "\n")
                fh.flush()
                os.fsync(fh.fileno())
                new.append(summary)
                progress.step(describe(job, summary))
        except KeyboardInterrupt:
            interrupted = True
            print(f"\n{label}: interrupted after {progress.done}/{len(jobs)}; finished runs kept", file=sys.stderr)
        finally:
            results.close()  # stops the workers
    return new, interrupted
