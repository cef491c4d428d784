"""Every path of a run, in one place.

A workdir (the run's `--workdir`)::

    config.json                 the settings this workdir was run with
    config_history.jsonl        every accepted settings change
    wall_times.json             seconds per stage, one line per invocation
    .lock  .processes/          one writer at a time; several processes' heartbeats
    <stage-1 model>/            e.g. savi/, or dvae/ + tokens/<split>/ + steve/
                                (slot_models/): checkpoints/<step>/,
                                model_config.json, identity.json,
                                train_log.jsonl, tensorboard/
    slots/<split>/              extracted slots (data/slots.py)
    slotformer/  slot_lstm/     the dynamics models, as a stage-1 model
    eval/  render/  explore/    metrics, pictures, the run explorer
    seed_<s>/                   several seeds (config.seeds, docs/seeds.md):
                                seed s's tokens/<split>/ (STEVE),
                                slots/<split>/, eval/, render/, explore/;
                                the trained stages above hold the seeds'
                                one stacked checkpoint, eval/ their summary
                                (mean +- std over the seeds)
    readout/<condition>/seed_<s>/    contact readouts
    planning/<condition>/seed_<s>/   planning classifiers
    vqa/<inputs>_s<seed>/            Aloe, one folder per input kind and seed

Stage 1 (the slot model, its slots and its intermediate data) lives in
`stage1`: the workdir itself, or another run's workdir given by
`config.stage1_workdir` (stage-2 ablations share one stage 1, read-only).
"""

from __future__ import annotations

import dataclasses
import os


@dataclasses.dataclass(frozen=True)
class Paths:
  """The paths of one run.

  Attributes:
    root: the run's workdir (`--workdir`).
    stage1: where the slot model and its slots live: `root`, or another
      run's workdir (read-only, see `foreign_stage1`).
    seed: None, or the paths of seed `seed` of a several-seed run
      (`for_seed`): its slots and results under `seed_<seed>/`.
  """

  root: str
  stage1: str
  seed: int | None = None

  @classmethod
  def of(cls, workdir: str, stage1_workdir: str | None = None) -> Paths:
    """The paths of `workdir`, whose stage 1 is `stage1_workdir` when set."""
    return cls(root=workdir, stage1=stage1_workdir or workdir)

  def for_seed(self, seed: int) -> Paths:
    """The paths of seed `seed` of a several-seed run: its derived data
    (STEVE's tokens) and slots under `<stage1>/seed_<seed>/`, its results
    under `<root>/seed_<seed>/`; the trained stages (one stacked checkpoint
    for all seeds) where they are."""
    return dataclasses.replace(self, seed=int(seed))

  def _of_seed(self, base: str, *names: str) -> str:
    """`base/names`, or `base/seed_<s>/names` for seed s's paths."""
    if self.seed is None:
      return os.path.join(base, *names)
    return os.path.join(base, f'seed_{self.seed}', *names)

  @property
  def foreign_stage1(self) -> bool:
    """True when stage 1 is another workdir's (this run never writes it)."""
    return (os.path.realpath(self.stage1) != os.path.realpath(self.root))

  # ---- the workdir's own files ---------------------------------------------

  @property
  def config_file(self) -> str:
    return os.path.join(self.root, 'config.json')

  @property
  def config_history(self) -> str:
    return os.path.join(self.root, 'config_history.jsonl')

  @property
  def wall_times(self) -> str:
    return os.path.join(self.root, 'wall_times.json')

  @property
  def lock(self) -> str:
    return os.path.join(self.root, '.lock')

  @property
  def heartbeats(self) -> str:
    """Several processes' heartbeat files (runtime/processes.py)."""
    return os.path.join(self.root, '.processes')

  # ---- stage 1 ----------------------------------------------------------------

  def model(self, name: str) -> str:
    """The folder of stage-1 model `name` ('savi', 'dvae', 'steve', ...)."""
    return os.path.join(self.stage1, name)

  def derived(self, name: str, split: str) -> str:
    """Data a stage-1 model derives from the videos of `split` for the next
    one (STEVE: the dVAE's 'tokens'); seed s's under `seed_<s>/`."""
    return self._of_seed(self.stage1, name, split)

  def slots(self, split: str) -> str:
    """The extracted slots of `split` (data/slots.py)."""
    return self._of_seed(self.stage1, 'slots', split)

  # ---- stage 2 and what follows ----------------------------------------------

  def dynamics(self, name: str) -> str:
    """The folder of dynamics model `name` ('slotformer', 'slot_lstm')."""
    return os.path.join(self.root, name)

  @property
  def eval(self) -> str:
    return self._of_seed(self.root, 'eval')

  @property
  def render(self) -> str:
    return self._of_seed(self.root, 'render')

  @property
  def explore(self) -> str:
    return self._of_seed(self.root, 'explore')

  @property
  def readouts(self) -> str:
    """Contact readouts and the run's results: readout/."""
    return os.path.join(self.root, 'readout')

  def readout(self, condition: str, seed: int) -> str:
    """One contact readout: readout/<condition>/seed_<seed>/; a seed
    view's (its chain's readout) under seed_<s>/readout/."""
    return os.path.join(self._of_seed(self.root, 'readout'), condition,
                        f'seed_{seed}')

  @property
  def planning(self) -> str:
    """Planning classifiers and the run's results: planning/."""
    return os.path.join(self.root, 'planning')

  def planner(self, condition: str, seed: int) -> str:
    """One success classifier: planning/<condition>/seed_<seed>/; a seed
    view's (its chain's) under seed_<s>/planning/."""
    return os.path.join(self._of_seed(self.root, 'planning'), condition,
                        f'seed_{seed}')

  @property
  def vqa(self) -> str:
    return os.path.join(self.root, 'vqa')

  @property
  def vqa_slots(self) -> str:
    """Each split's slots + SlotFormer rollout read by Aloe: vqa/slots/;
    a seed view's (its chain's) under seed_<s>/vqa/slots/."""
    return os.path.join(self._of_seed(self.root, 'vqa'), 'slots')

  def aloe(self, inputs: str, seed: int) -> str:
    """Aloe on `inputs` ('rollout', 'observed', 'blind') with `seed`: its
    checkpoints (with several seeds the stacked one, shared by the seed
    views) and a one-seed run's results."""
    return os.path.join(self.vqa, f'{inputs}_s{seed}')

  def aloe_results(self, inputs: str, seed: int) -> str:
    """Where Aloe's evaluation writes: `aloe` for a one-seed run (and
    the several seeds' summary); a seed view's under seed_<s>/vqa/."""
    return os.path.join(self._of_seed(self.root, 'vqa'), f'{inputs}_s{seed}')


def command(workdir: str, mode: str | None = None) -> str:
  """The command line that runs stage `mode` (None: every stage) on
  `workdir`, as messages suggest it."""
  line = ('python -m slotformer_jax.main --config=<config> '
          f'--workdir={workdir}')
  return f'{line} --mode={mode}' if mode else line
