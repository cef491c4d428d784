"""How far the host may run ahead of the devices.

jax dispatches each update asynchronously: without a sync, the host loop
queues update after update while the devices compute the first ones (seen
on CPU: 31 updates queued). A stop signal is noted by the host, so the
state it saves is that of the host's step, and every queued update must be
computed first: the stop came about 40 s late. `StepsInFlight` waits, after
dispatching update n, until update n - `limit` is done (its outputs are
ready): at most `limit` updates are ever queued beyond the finished ones,
which keeps the devices busy while the host prepares the next step.
"""

from __future__ import annotations

import collections
from typing import Any

import jax

# Updates queued beyond those the devices finished (docs/reliability.md).
MAX_STEPS_AHEAD = 2


class StepsInFlight:
  """The outputs of the last updates dispatched, oldest first."""

  def __init__(self, limit: int = MAX_STEPS_AHEAD):
    self.limit = limit
    self._queued: collections.deque[Any] = collections.deque()

  def dispatched(self, outputs: Any) -> None:
    """Notes an update's outputs (arrays it returns, not donated later);
    waits for the oldest while more than `limit` are queued."""
    self._queued.append(outputs)
    while len(self._queued) > self.limit:
      jax.block_until_ready(self._queued.popleft())
