"""What long work says while it runs: progress bars on the lead host, and,
before a stage decodes many frames with a slot model that generates them
token by token (STEVE), what that costs and how to make it shorter.

Generation is sequential: STEVE decodes one frame in `decode_steps` (its
number of tokens) decoder passes, so a few videos of rollout pictures are
minutes of work on a CPU. The stages that decode (evaluation, render, the
explorer, the contact pictures) call `announce_decoding` before they start
and show a bar whose rate and time left come from the work already done.

A bar whose one unit takes minutes (one video of the explorer, a split that
is one batch) would sit at 0/1: `Steps` says the sub-steps inside it (the
chunks of a batch, the frames a jitted loop decodes token by token:
`tick` inside the jitted body), at most one line every
`STEP_LINE_SECONDS`. `compiling` says, before a program's first call, why
the first unit takes longer.
"""

from __future__ import annotations

import contextlib
import logging
import time
from typing import TYPE_CHECKING, Any, Iterable, Iterator, TypeVar

import tqdm

if TYPE_CHECKING:
  import jax

logger = logging.getLogger(__name__)

T = TypeVar('T')

# Seconds between two lines of one unit's sub-steps: minutes of work say
# where they are; a unit done sooner says nothing.
STEP_LINE_SECONDS = 30.0


def _process_index() -> int:
  """jax's process index, imported here: the data writers' worker
  processes import this module (through the datasets) and need no jax."""
  import jax  # pylint: disable=g-import-not-at-top
  return jax.process_index()


def bar(items: Iterable[T], *, desc: str, total: int | None = None,
        unit: str = 'it') -> Iterator[T]:
  """`items` with a progress bar (done, rate, time left) on the lead
  host; `total` when `items` has no length."""
  return iter(tqdm.tqdm(items, desc=desc, total=total, unit=unit,
                        disable=_process_index() != 0,
                        dynamic_ncols=True))


def announce_decoding(what: str, slot_model: Any, num_frames: int,
                      shorten: str) -> None:
  """One log line before `what` decodes `num_frames` frames, when the slot
  model generates each frame in several sequential decoder passes: how many
  passes in all, on which platform, and the config fields that make the work
  smaller (`shorten`)."""
  steps = slot_model.decode_steps
  if steps <= 1 or num_frames <= 0 or _process_index() != 0:
    return
  import jax  # pylint: disable=g-import-not-at-top
  platform = jax.devices()[0].platform
  slow = ' -- minutes per video' if platform == 'cpu' else ''
  logger.warning(
      '%s: %s generates each decoded frame token by token, %d decoder passes '
      'a frame; %d frames = %d sequential passes on %s%s. Shorten with %s.',
      what, slot_model.label, steps, num_frames, steps * num_frames,
      platform.upper(), slow, shorten)


def compiling(what: str, first: str) -> None:
  """One log line before `what`'s first call compiles its program (minutes
  on a CPU without a line otherwise); `first`: what takes longer."""
  if _process_index() == 0:
    logger.info('%s: compiling (the first %s takes longer)', what, first)


class Steps:
  """The sub-steps of one long unit, e.g. the chunks of a batch of videos:
  '<what>: <done>/<total> <unit> (<s> s each, ~<s> s left)' on the lead
  host, at most one line every `STEP_LINE_SECONDS`."""

  def __init__(self, what: str, total: int, unit: str = 'step'):
    self.what, self.total, self.unit = what, total, unit
    self.done = 0
    self._started = self._said = time.monotonic()

  def reached(self, done: int) -> None:
    """`done` sub-steps are finished (a count that goes back is ignored:
    the devices of a sharded loop each report the same step)."""
    if done <= self.done:
      return
    self.done = min(done, self.total)
    now = time.monotonic()
    if now - self._said < STEP_LINE_SECONDS or _process_index() != 0:
      return
    self._said = now
    each = (now - self._started) / self.done
    logger.info('%s: %d/%d %s (%.1f s each, ~%.0f s left)', self.what,
                self.done, self.total, self.unit, each,
                each * (self.total - self.done))

  def advance(self) -> None:
    self.reached(self.done + 1)


# The `Steps` that `tick`s inside a jitted call count (`ticking`).
_ticking: Steps | None = None


@contextlib.contextmanager
def ticking(steps: Steps) -> Iterator[Steps]:
  """Within it, `tick(i)` in a jitted program's loop body reports to
  `steps` that i steps are done when the device reaches step i."""
  global _ticking  # pylint: disable=global-statement
  before, _ticking = _ticking, steps
  try:
    yield steps
  finally:
    _ticking = before


def _reached(index: Any) -> None:
  steps = _ticking
  if steps is not None:
    steps.reached(int(index))


def tick(index: jax.Array, decode_steps: int) -> None:
  """(Traced, at the start of a loop body that decodes.) Loop step `index`
  (0-based) starts: `index` steps are done, counted by the `ticking` Steps,
  if any, on the host. Only where one unit takes minutes: on a CPU, for a
  slot model whose `decode_steps` (sequential decoder passes per frame) is
  above 1. Elsewhere the program stays the one without the host callback:
  jax's persistent compile cache never serves a program with one (its key
  holds the callback's address in this process), and on an accelerator it
  would be a round trip per step."""
  import jax  # pylint: disable=g-import-not-at-top
  if decode_steps > 1 and jax.default_backend() == 'cpu':
    jax.debug.callback(_reached, index)
