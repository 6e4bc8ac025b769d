"""The inference thread: one daemon thread that runs submitted calls in order (an Executor).

`concurrent.futures.ThreadPoolExecutor` would do, except that the interpreter joins its threads
at exit: a batch still computing when the drain timeout ends (minutes, for a large image on
`full`) would keep the process alive past it. A daemon thread does not, so the drain timeout
bounds shutdown; the abandoned batch's requests have been answered 503 `draining` by then.
A process must not finish normally while such a thread computes (torch's static destructors
then abort it): `python -m crestereo_pp.service` ends with `os._exit` when `any_busy()`.
"""

from __future__ import annotations

import queue
import threading
import weakref
from collections.abc import Callable
from concurrent.futures import Executor, Future
from typing import Any

_EXECUTORS: weakref.WeakSet[DaemonThreadExecutor] = weakref.WeakSet()


def any_busy() -> bool:
    """Whether any daemon thread executor of this process is running a call now."""
    return any(executor.busy for executor in list(_EXECUTORS))


class DaemonThreadExecutor(Executor):
    """An Executor of exactly one daemon thread, started at construction."""

    def __init__(
        self, name: str, initializer: Callable[..., object] | None = None, initargs: tuple[Any, ...] = ()
    ) -> None:
        self._calls: queue.SimpleQueue[
            tuple[Future[Any], Callable[..., Any], tuple[Any, ...], dict[str, Any]] | None
        ] = queue.SimpleQueue()
        self._initializer, self._initargs = initializer, initargs
        self._closed = False
        self.busy = False
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()
        _EXECUTORS.add(self)

    def submit(self, fn: Callable[..., Any], /, *args: Any, **kwargs: Any) -> Future[Any]:
        if self._closed:
            raise RuntimeError("the executor is shut down")
        future: Future[Any] = Future()
        self._calls.put((future, fn, args, kwargs))
        return future

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        """Run no more calls after those already submitted (cancelled instead with
        `cancel_futures`); `wait`: until the thread has finished them."""
        self._closed = True
        if cancel_futures:
            while True:
                try:
                    item = self._calls.get_nowait()
                except queue.Empty:
                    break
                if item is not None:
                    item[0].cancel()
        self._calls.put(None)
        if wait:
            self._thread.join()

    def _run(self) -> None:
        if self._initializer is not None:
            self._initializer(*self._initargs)
        while (item := self._calls.get()) is not None:
            future, fn, args, kwargs = item
            if not future.set_running_or_notify_cancel():
                continue
            self.busy = True
            try:
                future.set_result(fn(*args, **kwargs))
            except BaseException as exc:  # handed to the caller, as ThreadPoolExecutor does
                future.set_exception(exc)
            finally:
                self.busy = False
