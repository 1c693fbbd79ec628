"""Evaluating candidates fast, with the same results: affine shortcuts and work spread over processes.

Discovery's cost is residual evaluations: every candidate is fitted twice (2-fold
cross-validation) by a least-squares search whose finite-difference Jacobians re-evaluate the
whole flight per parameter.  Two things cut that without changing what is computed:

- **Affine candidates.**  Many effects enter the equation error linearly: mass (``m f``),
  inertia (``J alpha + w x J w``), a motor's efficiency, the thrust and yaw-moment scales, a CoM
  offset, drag coefficients.  For those the residual over the whole flight *is*
  ``R(theta) = R(theta0) + sum_j (theta_j - theta0_j) D_j``.  :func:`affine` measures ``R0`` and
  the ``D_j`` with one evaluation per parameter, then checks the claim with true evaluations at
  both corners of the search range and at an interior point; only when all agree to 1e-9 of the
  residual's size is the fit run on this exact linear form (then the search's hundred
  evaluations cost microseconds, and its result is the same to rounding).  Anything that fails
  the check (time constants, delay, battery sag, ground effect, wind...) is fitted on true
  evaluations as before.
- **Processes.**  The candidates of one round are independent: :func:`run_tasks` runs them on
  ``workers()`` forked processes (the flight data, the judges and the compiled model are
  inherited, nothing is re-read or recompiled) and returns the results in task order, so the
  selection that follows sees exactly what a serial run would.  :func:`start` runs one piece of
  later work (the closed-loop twin) in a forked process meanwhile.

``WORKERS``/``AFFINE_FITS`` switch these off (``bench/bench_discover.py`` measures the old path
with them off and the frozen evaluation functions of ``bench/discover_before.py``).
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

#: worker processes for a round of candidates; None: ``$ROTORTWIN_DISCOVER_WORKERS`` or the CPUs
#: this process may use, at most 4 (a round has a handful of costly candidates); always 1 inside a
#: process that multiprocessing started (see :func:`workers`)
WORKERS: int | None = None
#: fit affine candidates on their exact linear form
AFFINE_FITS = True
#: the linear form must reproduce true evaluations to this fraction of the residual's size
AFFINE_RTOL = 1e-9


def workers() -> int:
    """Processes to use here: 1 inside a process that multiprocessing started (a Dask worker, a
    prove-suite worker: the flights are already spread over the cores; a daemonic one may not
    have children at all)."""
    if mp.current_process().daemon or mp.parent_process() is not None:
        return 1
    if WORKERS is not None:
        return max(int(WORKERS), 1)
    env = os.environ.get("ROTORTWIN_DISCOVER_WORKERS", "").strip()
    if env:
        try:
            return max(int(env), 1)
        except ValueError:
            raise ValueError(f"ROTORTWIN_DISCOVER_WORKERS: expected a whole number of processes, got {env!r}")
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        cpus = os.cpu_count() or 1
    return max(1, min(cpus, 4))


_TASK: Callable[[int], Any] | None = None


def single_threaded_blas() -> None:
    """One BLAS thread in this process (a worker: the processes are the parallelism; OpenBLAS's
    own threads would spin against the other workers on the same cores: a third more CPU, measured)."""
    import ctypes
    try:
        with open("/proc/self/maps", encoding="utf-8") as f:
            libs = {line.split()[-1] for line in f if "openblas" in line.lower() and ".so" in line}
    except OSError:  # pragma: no cover - not Linux
        return
    for path in sorted(libs):
        try:
            lib = ctypes.CDLL(path)
        except OSError:  # pragma: no cover
            continue
        for sym in ("scipy_openblas_set_num_threads64_", "scipy_openblas_set_num_threads",
                    "openblas_set_num_threads64_", "openblas_set_num_threads"):
            fn = getattr(lib, sym, None)
            if fn is not None:
                fn(1)


def _run(i: int) -> tuple[int, Any]:
    assert _TASK is not None
    return i, _TASK(i)


def run_tasks(task: Callable[[int], Any], n: int, cost: Sequence[float] | None = None,
              done: Callable[[int], None] | None = None) -> list:
    """``[task(0), ..., task(n - 1)]``, on ``workers()`` forked processes when there are several.

    ``cost`` (optional, any unit) orders the work, costliest first, so the last task to finish is
    a cheap one; ``done(i)`` is called as each task finishes (progress)."""
    global _TASK
    nw = min(workers(), n)
    out: list = [None] * n
    if nw <= 1 or "fork" not in mp.get_all_start_methods():
        for i in range(n):
            out[i] = task(i)
            if done is not None:
                done(i)
        return out
    order = sorted(range(n), key=lambda i: -cost[i]) if cost is not None else list(range(n))
    _TASK = task
    try:
        with mp.get_context("fork").Pool(nw, initializer=single_threaded_blas) as pool:
            for i, res in pool.imap_unordered(_run, order, chunksize=1):
                out[i] = res
                if done is not None:
                    done(i)
    finally:
        _TASK = None
    return out


class Pending:
    """A result computed in a forked process while this one goes on (see :func:`start`)."""

    def __init__(self, fn: Callable[[], Any], background: bool):
        self._fn = fn
        self._done = False
        self._value: Any = None
        self._proc = None
        if background:
            ctx = mp.get_context("fork")
            self._conn, child = ctx.Pipe(duplex=False)
            self._proc = ctx.Process(target=_child, args=(fn, child), daemon=True)
            self._proc.start()
            child.close()

    def result(self) -> Any:
        """The value (computed here and now when no process was started; a failure in the process
        is raised here)."""
        if not self._done:
            if self._proc is None:
                self._value = self._fn()
            else:
                try:
                    ok, value = self._conn.recv()
                except EOFError:
                    ok, value = False, RuntimeError(f"background process exited with code {self._proc.exitcode}")
                self._proc.join()
                self._conn.close()
                self._proc = None
                if not ok:
                    raise value
                self._value = value
            self._done = True
        return self._value

    def cancel(self) -> None:
        """Stop the process if the value is not wanted after all."""
        if self._proc is not None:
            self._proc.terminate()
            self._proc.join()
            self._conn.close()
            self._proc = None


def _child(fn: Callable[[], Any], conn) -> None:
    single_threaded_blas()
    try:
        out = (True, fn())
    except BaseException as e:  # noqa: BLE001 - handed to the parent, raised there
        out = (False, e)
    try:
        conn.send(out)
    except Exception as e:  # noqa: BLE001 - an unpicklable exception
        conn.send((False, RuntimeError(repr(e))))
    conn.close()


def start(fn: Callable[[], Any]) -> Pending:
    """``fn()`` started in a forked process when ``workers() > 1`` (else computed when asked for):
    work that a later step needs, overlapped with the steps before it."""
    return Pending(fn, workers() > 1 and "fork" in mp.get_all_start_methods())


class Affine:
    """``R(theta) = R0 + (theta - theta0) . D`` over all rows of a residual (see module doc)."""

    def __init__(self, theta0: np.ndarray, R0: np.ndarray, D: np.ndarray):
        self.theta0 = theta0
        self.R0 = R0          # (rows, channels)
        self.D = D            # (n, rows, channels)

    def __call__(self, theta: np.ndarray) -> np.ndarray:
        return self.R0 + np.tensordot(np.asarray(theta, float) - self.theta0, self.D, axes=1)

    def on(self, rows: np.ndarray) -> Callable[[np.ndarray], np.ndarray]:
        """theta -> the residual's rows ``rows``, flattened (as a least-squares residual)."""
        r0 = self.R0[rows].ravel()
        d = self.D[:, rows].reshape(len(self.theta0), -1)
        t0 = self.theta0

        def f(theta: np.ndarray) -> np.ndarray:
            return r0 + (np.asarray(theta, float) - t0) @ d
        return f


def affine(residual: Callable[[np.ndarray], np.ndarray], theta0: np.ndarray, lower: np.ndarray,
           upper: np.ndarray, rtol: float = AFFINE_RTOL) -> Affine | None:
    """The exact linear form of ``residual`` (theta -> (rows, channels)) over the box
    [lower, upper], or None when it is not affine there (or cannot be evaluated somewhere in it).

    One evaluation per parameter measures the slopes (a step of half the wider side of the box);
    three true evaluations check them, at both corners of the box and at an interior point that
    moves every parameter by a different fraction."""
    theta0 = np.asarray(theta0, float).copy()
    lower = np.asarray(lower, float)
    upper = np.asarray(upper, float)
    n = len(theta0)
    try:
        R0 = np.asarray(residual(theta0), float)
        D = np.empty((n,) + R0.shape)
        for j in range(n):
            up, down = upper[j] - theta0[j], theta0[j] - lower[j]
            h = 0.5 * up if up >= down else -0.5 * down
            if h == 0.0:
                return None
            th = theta0.copy()
            th[j] += h
            D[j] = (np.asarray(residual(th), float) - R0) / h
        form = Affine(theta0, R0, D)
        size = max(float(np.abs(R0).max()), float(np.max(np.abs(D) * np.abs(upper - lower)[:, None, None])), 1e-300)
        fracs = 0.2 + 0.6 * (np.arange(n) + 1) / (n + 1)
        for th in (lower, upper, lower + fracs * (upper - lower)):
            if np.max(np.abs(np.asarray(residual(th), float) - form(th))) > rtol * size:
                return None
    except (ValueError, ArithmeticError):
        return None
    if not (np.all(np.isfinite(R0)) and np.all(np.isfinite(D))):
        return None
    return form
