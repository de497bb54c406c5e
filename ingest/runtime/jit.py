"""How long numba spent compiling: the first run of a checkout compiles the kernels, later runs load them.

numba compiles a kernel on its first call with new argument types and
caches the machine code on disk (`cache=True`), so the first run after an
install or a change of the kernels' source spends a minute or so compiling
(about 60 s for dense GT on a 2-core VM) and every later run loads them in
milliseconds. A run's summary that mixed that minute into its stage times
without saying so would be misread as the pipeline's speed. numba announces
each compilation that misses its cache (the event `numba:compile`; loads from
the cache are not one), and `compiling` sums them.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

from numba.core import event


@contextmanager
def compiling() -> Iterator[list[float]]:
    """Seconds numba spent compiling in this process inside the block (nested compilations counted
    once): a one-item list, filled when the block ends."""
    took: list[float] = []
    with event.install_timer("numba:compile", took.append):
        yield took
    if not took:
        took.append(0.0)
