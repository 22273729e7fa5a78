"""BLAS (OpenBLAS, MKL) held to one thread for a block of work."""

import sys

__all__ = ["one_blas_thread"]

_CONTROLLER = {}


def one_blas_thread():
    """A limiter that holds BLAS to one thread until ``restore_original_limits()`` (or the ``with`` block's end).

    Two reasons to: a dense product's last bits depend on how many threads
    OpenBLAS splits it over, so on one thread a result is the same on every
    machine and in a forked child as in its parent; and two processes each
    running a multithreaded BLAS on two CPUs spin-wait for each other (a
    500 x 500 product ran four times slower while the other process
    computed). NumPy, SciPy and OpenCV each load a BLAS of their own, some
    only when first imported, so the loaded libraries are looked up again
    (threadpoolctl, a few ms) whenever modules have been imported since the
    last look; a library loaded later would otherwise keep all its threads.
    """
    if _CONTROLLER.get("modules") != len(sys.modules):
        from threadpoolctl import ThreadpoolController

        _CONTROLLER["controller"] = ThreadpoolController()
        _CONTROLLER["modules"] = len(sys.modules)
    return _CONTROLLER["controller"].limit(limits=1, user_api="blas")
