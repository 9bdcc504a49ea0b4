"""One BLAS thread for the tall, thin matrices of the planner and the diagnosis."""

from __future__ import annotations

from threadpoolctl import threadpool_limits


def single_threaded_blas() -> threadpool_limits:
    """Run with one BLAS thread (threadpoolctl, as a context manager; ~0.4 ms to enter): on tall,
    thin matrices BLAS threads only spin (diagnosis design matrices on a shared machine: a threaded
    GEMM of that shape measured ~500x slower; a planning call: the same wall time at twice the CPU)."""
    return threadpool_limits(limits=1, user_api="blas")
