"""Downstream tasks on top of the dynamics model (Sections 4.3-4.4), pure:
readouts and their fitting, AUCCESS, VQA losses and metrics. The stages that
feed them slots and rollouts are in `stages/`."""
