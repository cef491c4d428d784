"""What happens in a CLEVRER-like video, as its questions need it: the event
log (collisions, objects entering / exiting, the state at the end of the
video, the counterfactual worlds) written by the simulator
(`datasets/clevrer_like.py`) and read by the question generator
(`datasets/clevrer_like_questions.py`).
JSON-serialisable, one per video in `events.jsonl`.
"""

from __future__ import annotations

import dataclasses
from typing import Any

# How many verdicts `clevrer_like.extrapolation_verdict` gives a pair: 4 bins
# of its extrapolated clearance x 4 kinds of relative motion.
NUM_GAP_BINS = 4
NUM_VERDICTS = 4 * NUM_GAP_BINS


@dataclasses.dataclass(frozen=True)
class Collision:
  objects: tuple[int, int]  # (i, j), i < j
  frame: int  # onset frame


@dataclasses.dataclass
class EventLog:
  """Everything questions are generated from; JSON-serialisable (to_dict).

  Attributes:
    objects: per object, {'color', 'shape', 'size'} names.
    observed_frames: frames of the video; events at frames >= this are in
      the future (predictive questions).
    num_frames: frames simulated.
    collisions: every collision in onset order (observed and future).
    entering: (object, frame) of objects coming into view after frame 0.
    exiting: (object, frame) of objects leaving the view.
    moving_at_end: per object, whether it moves at the last observed frame.
    in_view_at_end: per object, whether it is in view at that frame.
    final_positions: per object, its centre [x, y, z] at the last simulated
      frame (None if it never appeared).
    counterfactual: removed object -> collisions in the world without it.
    extrapolated: predictive_design 'deflected' only (None otherwise, and
      then not written by to_dict): (i, j, verdict) for every pair i < j of
      objects in view at the last observed frame, verdict what extrapolating
      their last two observed positions over predicted_frames says
      (:func:`extrapolation_verdict`, 0 .. NUM_VERDICTS - 1).
  """

  objects: list[dict[str, str]]
  observed_frames: int
  num_frames: int
  collisions: list[Collision]
  entering: list[tuple[int, int]] = dataclasses.field(default_factory=list)
  exiting: list[tuple[int, int]] = dataclasses.field(default_factory=list)
  moving_at_end: list[bool] = dataclasses.field(default_factory=list)
  in_view_at_end: list[bool] = dataclasses.field(default_factory=list)
  final_positions: list[list[float] | None] = dataclasses.field(
      default_factory=list)
  counterfactual: dict[int, list[Collision]] = dataclasses.field(
      default_factory=dict)
  extrapolated: list[tuple[int, int, int]] | None = None

  @property
  def num_objects(self) -> int:
    return len(self.objects)

  def observed_collisions(self) -> list[Collision]:
    return [c for c in self.collisions if c.frame < self.observed_frames]

  def future_collisions(self) -> list[Collision]:
    return [c for c in self.collisions if c.frame >= self.observed_frames]

  def to_dict(self) -> dict[str, Any]:
    d = dataclasses.asdict(self)
    d['counterfactual'] = {str(k): [dataclasses.asdict(c) for c in v]
                           for k, v in self.counterfactual.items()}
    if d['extrapolated'] is None:
      del d['extrapolated']  # the logs of the 'direct' design, as before
    return d

  @classmethod
  def from_dict(cls, d: dict[str, Any]) -> EventLog:
    def collisions(items):
      return [Collision(tuple(c['objects']), int(c['frame'])) for c in items]
    return cls(
        objects=[dict(o) for o in d['objects']],
        observed_frames=int(d['observed_frames']),
        num_frames=int(d['num_frames']),
        collisions=collisions(d['collisions']),
        entering=[tuple(e) for e in d['entering']],
        exiting=[tuple(e) for e in d['exiting']],
        moving_at_end=list(d['moving_at_end']),
        in_view_at_end=list(d['in_view_at_end']),
        final_positions=list(d['final_positions']),
        counterfactual={int(k): collisions(v)
                        for k, v in d['counterfactual'].items()},
        extrapolated=(None if d.get('extrapolated') is None
                      else [tuple(p) for p in d['extrapolated']]))
