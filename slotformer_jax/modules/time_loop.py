"""The models' loops over time (SAVi's frames, SlotFormer's and Slot-LSTM's
rollouts): `nn.scan` with the parameters shared by every step."""

from __future__ import annotations

from typing import Any, Callable

import flax.linen as nn


def scan_with_shared_params(body: Callable[..., Any], module: nn.Module,
                            **scan_kwargs) -> Callable[..., Any]:
  """`nn.scan(body, variable_broadcast='params', **scan_kwargs)` for a loop
  run inside a method of `module` (bound).

  Flax traces a scan body a second time to check that broadcast variables
  are loop invariants, which also creates them at init. Outside init the
  parameters are only read inside these loops, so the body is traced once
  (flax's `check_constancy_invariants=False`): the same program, traced in
  less time (docs/performance.md, "The test suite's wall time").
  """
  return nn.scan(body, variable_broadcast='params',
                 check_constancy_invariants=module.is_initializing(),
                 **scan_kwargs)
