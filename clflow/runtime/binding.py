"""Launches bound once and enqueued many times.

A small simulation's substep is bound by the host's time to enqueue it (docs/gpu.md): every
call rebuilds the same argument dicts, checks them against the kernels' signatures and lays
them out in order. Here a block of launches (a substep) runs once under
:meth:`Device.recording`, which binds each launch (arguments checked and laid out, buffers
resolved, work sizes padded, each on a kernel object of its own whose arguments are set
once) and each zeroing of an array instead of enqueuing them; later calls replay the
recorded steps, setting only the time ``t`` (the one argument a substep changes from call to
call) before each enqueue.

A recording is valid while the objects its arguments came from are the same: a
:class:`LaunchCache` keys it by their identities, holds them by weak reference and drops it
as soon as one of them is collected (its buffers go with it).
"""

from __future__ import annotations

import weakref
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any


@dataclass
class BoundLaunch:
    """One launch laid out: the kernel, its padded work sizes, its argument values in the
    kernel's order (buffers for arrays) and where the time ``t`` goes (None: not taken);
    ``owned``: the kernel object is this launch's alone, its arguments already set (a
    recorded launch: a replay sets only the time)."""

    kernel: Any
    global_size: tuple
    local_size: tuple | None
    raw: list
    time_index: int | None
    hosts: list  # host tensors its zero-copy arrays alias
    owned: bool = False


@dataclass
class Fill:
    """Zero ``array`` (a DeviceArray) in queue order."""

    array: Any


@dataclass
class Recording:
    """The steps of a recorded block in order, the host tensors their zero-copy arrays alias
    (kept alive until the queue has run a replay) and the scratch buffers it took, which it
    owns from then on (a replay writes them)."""

    steps: list = field(default_factory=list)
    hosts: dict = field(default_factory=dict)  # id -> host tensor
    scratch: list = field(default_factory=list)

    def owns(self, buffer) -> bool:
        return any(b is buffer for b in self.scratch)


class LaunchCache:
    """Recordings of one block of launches, keyed by the objects its arguments come from
    (compared by identity, held weakly) and extra values (numbers it depends on); at most
    ``limit``, the least recently used dropped first (an array the block zeroes is held by its
    Fill step: a recording keyed by such an array leaves only that way)."""

    def __init__(self, limit: int = 256):
        self.limit = limit
        self._entries: OrderedDict[tuple, tuple[list, Recording]] = OrderedDict()

    def recording(self, device, objects: Sequence[Any], extra: tuple, block: Callable[[], None]) -> Recording:
        """The recording of ``block`` (a function that launches kernels and zeroes arrays on
        ``device``, nothing else) for ``objects`` and ``extra``: recorded now unless cached."""
        key = (*map(id, objects), *extra)
        entry = self._entries.get(key)
        if entry is not None and all(ref() is obj for ref, obj in zip(entry[0], objects)):
            self._entries.move_to_end(key)
            return entry[1]
        with device.recording() as recording:
            block()
        drop = lambda _, key=key: self._entries.pop(key, None)  # noqa: E731
        self._entries[key] = ([weakref.ref(obj, drop) for obj in objects], recording)
        if len(self._entries) > self.limit:
            self._entries.popitem(last=False)
        return recording

    def __len__(self) -> int:
        return len(self._entries)
