"""What long work says while it runs: progress bars on the lead host, and,
before a stage decodes many frames with a slot model that generates them
token by token (STEVE), what that costs and how to make it shorter.

Generation is sequential: STEVE decodes one frame in `decode_steps` (its
number of tokens) decoder passes, so a few videos of rollout pictures are
minutes of work on a CPU. The stages that decode (evaluation, render, the
explorer, the contact pictures) call `announce_decoding` before they start
and show a bar whose rate and time left come from the work already done.
"""

from __future__ import annotations

import logging
from typing import Any, Iterable, Iterator, TypeVar

import jax
import tqdm

logger = logging.getLogger(__name__)

T = TypeVar('T')


def bar(items: Iterable[T], *, desc: str, total: int | None = None,
        unit: str = 'it') -> Iterator[T]:
  """`items` with a progress bar (done, rate, time left) on the lead
  host; `total` when `items` has no length."""
  return iter(tqdm.tqdm(items, desc=desc, total=total, unit=unit,
                        disable=jax.process_index() != 0,
                        dynamic_ncols=True))


def announce_decoding(what: str, slot_model: Any, num_frames: int,
                      shorten: str) -> None:
  """One log line before `what` decodes `num_frames` frames, when the slot
  model generates each frame in several sequential decoder passes: how many
  passes in all, on which platform, and the config fields that make the work
  smaller (`shorten`)."""
  steps = slot_model.decode_steps
  if steps <= 1 or num_frames <= 0 or jax.process_index() != 0:
    return
  platform = jax.devices()[0].platform
  slow = ' -- minutes per video' if platform == 'cpu' else ''
  logger.warning(
      '%s: %s generates each decoded frame token by token, %d decoder passes '
      'a frame; %d frames = %d sequential passes on %s%s. Shorten with %s.',
      what, slot_model.label, steps, num_frames, steps * num_frames,
      platform.upper(), slow, shorten)
