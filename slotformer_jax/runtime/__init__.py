"""Run-time pieces shared by training, evaluation, extraction and the tasks:
sharding over the mesh, compute precision, checkpoints, several processes,
XLA flags. Nothing here trains or reads a config."""
